"""Cubic (Catmull–Rom) interpolation of radial tables, differentiable in the table and the positions.

The Lorenz–Mie profiles ``A, B, C`` of a sphere vary on the scale of its scattering lobes,
so they are sampled on a radial grid and interpolated to the pixels (`interpolated_profiles`),
four weights per point, as one sparse-matrix product.
"""

from __future__ import annotations

import warnings

import torch

__all__ = ["CatmullRom", "interpolated_profiles"]


def _catmull_rom_weights(position: torch.Tensor, last: int, *, derivative: bool = False) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    """First sample (``i - 1``) of each position's interval and the four Catmull–Rom weights of samples ``i - 1 … i + 2``.

    ``last``: the grid's last sample index. With ``derivative`` the weights of the cubic's
    slope (per sample spacing) instead. Positions beyond the grid extrapolate its end cubic.
    """
    base = torch.clamp(torch.floor(position.detach()), 1, last - 2)
    t = position - base
    t2 = t * t
    if derivative:
        weights = (-1.5 * t2 + 2.0 * t - 0.5, 4.5 * t2 - 5.0 * t, -4.5 * t2 + 4.0 * t + 0.5, 1.5 * t2 - t)
    else:
        t3 = t2 * t
        weights = (-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2)
    return base.long() - 1, weights


def _interpolation_matrix(first: torch.Tensor, weights: tuple[torch.Tensor, ...], samples: int) -> torch.Tensor:
    """Sparse (B·P, B·R) matrix of the weights: row ``(b, p)`` holds point p's four weights on grid b's samples."""
    count, points = first.shape
    columns = first[..., None] + torch.arange(4, device=first.device) + (torch.arange(count, device=first.device) * samples)[:, None, None]
    rows = torch.arange(0, 4 * count * points + 1, 4, device=first.device)
    values = torch.stack([w.detach() for w in weights], dim=-1)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)
        return torch.sparse_csr_tensor(rows, columns.reshape(-1), values.reshape(-1), size=(count * points, count * samples), check_invariants=False)


class CatmullRom(torch.autograd.Function):
    """Cubic interpolation of (B, R, D) real tables at (B, P) fractional sample positions: (B, P, D).

    Forward as one sparse-matrix product (four weights per point): the points of a patch
    outnumber its radial samples a hundredfold, so the product's cost is the points'.
    Differentiable in the table and the positions.
    """

    @staticmethod
    def forward(table, position):
        count, samples, channels = table.shape
        first, weights = _catmull_rom_weights(position, samples - 1)
        # a contiguous table keeps the sparse product on its fast path (measured: 3× slower strided)
        out = _interpolation_matrix(first, weights, samples) @ table.reshape(count * samples, channels).contiguous()
        return out.reshape(*position.shape, channels)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(*inputs)

    @staticmethod
    def backward(ctx, grad):
        table, position = ctx.saved_tensors
        count, samples, channels = table.shape
        grad_table = grad_position = None
        if ctx.needs_input_grad[0]:
            first, weights = _catmull_rom_weights(position, samples - 1)
            flat = (first + (torch.arange(count, device=first.device) * samples)[:, None]).reshape(-1)
            grad_table = torch.zeros((count * samples, channels), dtype=grad.dtype, device=grad.device)
            for offset, weight in enumerate(weights):
                grad_table.index_add_(0, flat + offset, (grad * weight[..., None]).reshape(-1, channels))
            grad_table = grad_table.reshape(count, samples, channels)
        if ctx.needs_input_grad[1]:
            grad_position = (grad * _interpolate_slope(table.detach(), position.detach())).sum(dim=-1)
        return grad_table, grad_position


def _interpolate_slope(table: torch.Tensor, position: torch.Tensor) -> torch.Tensor:
    """Slope (per sample spacing) of the cubic interpolation of (B, R, D) tables at (B, P) positions: (B, P, D); not differentiable."""
    count, samples, channels = table.shape
    first, weights = _catmull_rom_weights(position, samples - 1, derivative=True)
    return (_interpolation_matrix(first, weights, samples) @ table.reshape(count * samples, channels).contiguous()).reshape(*position.shape, channels)


def _profile_table(profiles: torch.Tensor) -> torch.Tensor:
    """(C, B, R) complex profiles as a (B, R, 2C) real table (`CatmullRom`'s layout)."""
    channels, count, samples = profiles.shape
    return torch.view_as_real(profiles).permute(1, 2, 0, 3).reshape(count, samples, 2 * channels)


def interpolated_profiles(profiles: torch.Tensor, step: torch.Tensor, rho_um: torch.Tensor, *, slope: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """(3, K, B, P) complex ``A, B, C`` of K copies of the profiles (3, K·B, R) at the radii (B, P) of B point sets.

    The copies share each point set's grid (``step``, (B,)), so the interpolation weights are
    computed once. With ``slope``, also their derivatives in ρ (per µm; not differentiable).
    """
    count, points = rho_um.shape
    copies = profiles.shape[1] // count
    samples = profiles.shape[-1]
    table = _profile_table(profiles.reshape(3 * copies, count, samples))  # (B, R, 2·3K): channels (component, copy)
    position = rho_um / step[:, None] + 1.0
    shape = (count, points, 3, copies, 2)
    # contiguous per component: the many elementwise operations that follow run 3-5× slower on strided complex views
    values = torch.view_as_complex(CatmullRom.apply(table, position).reshape(shape)).permute(2, 3, 0, 1).contiguous()
    if not slope:
        return values
    slopes = torch.view_as_complex(_interpolate_slope(table.detach(), position.detach()).reshape(shape)).permute(2, 3, 0, 1) / step[:, None]
    return values, slopes
