"""Holograms of opaque discs (the seed's particle model), batched and differentiable in torch, by the angular spectrum."""

from __future__ import annotations

import math

import torch

__all__ = ["disc_holograms"]


class _BesselJ1(torch.autograd.Function):
    """J1 with its derivative ``J0(x) - J1(x)/x`` (torch's J1 has none)."""

    @staticmethod
    def forward(x):
        return torch.special.bessel_j1(x)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(inputs[0], output)
        ctx.save_for_forward(inputs[0], output)

    @staticmethod
    def _derivative(x, j1):
        safe = torch.where(x == 0, torch.ones_like(x), x)
        return torch.where(x == 0, torch.full_like(x, 0.5), torch.special.bessel_j0(x) - j1 / safe)

    @staticmethod
    def backward(ctx, grad):
        x, j1 = ctx.saved_tensors
        return grad * _BesselJ1._derivative(x, j1)

    @staticmethod
    def jvp(ctx, tangent):
        x, j1 = ctx.saved_tensors
        return tangent * _BesselJ1._derivative(x, j1)


def disc_holograms(
    x_px: torch.Tensor,
    y_px: torch.Tensor,
    z_um: torch.Tensor,
    diameter_um: torch.Tensor,
    *,
    shape: tuple[int, int],
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
) -> torch.Tensor:
    """Holograms of opaque discs (the seed's particle model) on a ``shape`` patch, by the angular spectrum.

    The disc's pixel-averaged coverage has the spectrum ``a J1(2π a f) / f`` times the
    pixel's ``sinc(f_x p) sinc(f_y p)`` (what `_synthesis.disc_coverage` samples); its
    scattered field ``-coverage`` is propagated by the exact transfer function of
    `napari_lbs._core.physics._optics` on a grid padded to twice the patch (light leaving the patch
    is dropped, not wrapped, up to that margin).

    Parameters
    ----------
    x_px, y_px : (B,) tensors
        Disc centres in the patch's pixel coordinates (column, row; pixel centres at integers).
    z_um : (B,) tensor
        Distances to the sensor (µm, the propagation convention of the config's medium).
    diameter_um : (B,) tensor
    shape : (rows, cols)
    wavelength_um, pixel_um, medium_index : float

    Returns
    -------
    (B, rows, cols) float64 tensor, unobstructed light = 1.
    """
    rows, cols = shape
    grid = (2 * rows, 2 * cols)
    fy = torch.fft.fftfreq(grid[0], d=pixel_um, dtype=torch.float64, device=x_px.device)[:, None]
    fx = torch.fft.fftfreq(grid[1], d=pixel_um, dtype=torch.float64, device=x_px.device)[None, :]
    f = torch.sqrt(fx**2 + fy**2)
    lam = wavelength_um / medium_index
    q = lam**2 * f**2
    propagating = q < 1.0
    rate = -2.0 * math.pi / lam * torch.where(propagating, q / (torch.sqrt(torch.clamp(1.0 - q, min=0.0)) + 1.0), torch.zeros_like(q))
    radius = diameter_um.to(torch.float64)[:, None, None] / 2.0
    argument = 2.0 * math.pi * radius * f
    safe_f = torch.where(f == 0, torch.ones_like(f), f)
    disc = torch.where(f == 0, math.pi * radius**2, radius * _BesselJ1.apply(argument) / safe_f)
    spectrum = disc / pixel_um**2 * torch.sinc(fx * pixel_um) * torch.sinc(fy * pixel_um)
    shift = -2.0 * math.pi * pixel_um * (fx * x_px.to(torch.float64)[:, None, None] + fy * y_px.to(torch.float64)[:, None, None])
    phase = shift + rate * z_um.to(torch.float64)[:, None, None]
    field = torch.fft.ifft2(torch.where(propagating, -spectrum, torch.zeros_like(spectrum)) * (torch.cos(phase) + 1j * torch.sin(phase)))
    field = field[:, :rows, :cols]
    return (1.0 + field.real) ** 2 + field.imag**2
