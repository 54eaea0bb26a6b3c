"""Lorenz–Mie holograms of single spheres, batched and differentiable in torch.

Lorenz–Mie convention (Lee et al. 2007, the convention of pylorenzmie)
----------------------------------------------------------------------
A unit plane wave, polarised along x (image columns), lights a sphere of radius ``a``
and complex index ``n_p + i κ`` in a medium of index ``n_m``; the sensor plane lies a
distance ``z`` (µm, in the medium, positive) downstream of the sphere's centre. Fields are
relative to the incident wave at the sensor (its carrier removed), so the hologram is

    I = |x̂ + E_s|² = |1 + E_x|² + |E_y|² + |E_z|²,   unobstructed light = 1,

with ``E_s`` the exact scattered field (Bohren & Huffman, Ch. 4) times ``exp(-i k z)``.

Speed without approximation
---------------------------
Under a plane wave the scattered field depends on the azimuth φ about the sphere only as
(every vector harmonic of plane-wave scattering has m = 1; Bohren & Huffman, Sec. 4.4)::

    E_x = e^{iΦ} (A(ρ) + sin²φ (B(ρ) - A(ρ))),  E_y = e^{iΦ} cosφ sinφ (A - B),  E_z = e^{iΦ} cosφ C(ρ),

with ``Φ = k (r - z)``, ``r = √(ρ² + z²)``. The carrier ``e^{iΦ}`` holds every fast fringe
and is evaluated exactly at each pixel; ``A, B, C`` vary on the scale of the scattering
lobes (≈ λ z / d, tens of pixels at the lensless depths and as many at a microscope's), so
they are summed over partial waves on a one-dimensional ρ grid and interpolated (cubic
Catmull–Rom, `napari_lbs._core.physics._interpolation`) to the pixels. The partial-wave
sum is therefore paid per radial sample, not per pixel.

Mie coefficients
----------------
Number of terms: Wiscombe (1980) (``x + 4.05 x^{1/3} + 2``, at least ``|m x|``). The
logarithmic derivative ``D_n(m x)`` by downward recurrence, ``D_n(x)`` likewise, the ratio
``ψ_n/ξ_n`` and ``D_n^{(3)}`` upward (Peña & Pal 2009, Yang 2003): every quantity stays
bounded for any batch of sizes, so small and large spheres share one set of terms.
complex128 throughout: at a size parameter of 200 the float32 coefficients lose the index.

References
----------
C. F. Bohren and D. R. Huffman, *Absorption and Scattering of Light by Small Particles*
(Wiley, 1983), Ch. 4 and App. A. W. J. Wiscombe, Appl. Opt. 19, 1505 (1980).
O. Peña and U. Pal, Comput. Phys. Commun. 180, 2348 (2009).
S.-H. Lee et al., Opt. Express 15, 18275 (2007).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from napari_lbs._core.physics._interpolation import CatmullRom, interpolated_profiles

__all__ = [
    "azimuthal_mean_holograms",
    "fields_from_profiles",
    "holograms_from_fields",
    "lateral_derivatives",
    "mie_coefficients",
    "radial_profiles",
    "radial_step",
    "sphere_fields",
    "sphere_holograms",
    "term_count",
]


def term_count(size_parameter: float, relative_index: complex) -> int:
    """Partial waves to keep (Wiscombe 1980; at least ``|m x|``, Yang 2003)."""
    x = abs(float(size_parameter))
    stop = x + 4.0 * x ** (1 / 3) + 1 if x <= 8 else x + 4.05 * x ** (1 / 3) + 2
    return max(math.floor(stop), int(abs(x * complex(relative_index))), 1)


def _reciprocal(w: torch.Tensor) -> torch.Tensor:
    """``1 / w`` of a complex tensor through real arithmetic (torch's complex division is several times slower)."""
    re, im = w.real, w.imag
    inverse = 1.0 / (re * re + im * im)
    return torch.complex(re * inverse, -im * inverse)


def _in_numpy(*tensors: torch.Tensor) -> bool:
    """Whether the recurrences over orders run in numpy: on the CPU, no gradient wanted through ``tensors``.

    numpy's per-operation cost on these short rows is a tenth to a half of torch's, and the
    loops run hundreds of orders of tens of operations each.
    """
    return tensors[0].device.type == "cpu" and not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))


def mie_coefficients(size_parameter: torch.Tensor, relative_index: torch.Tensor, *, terms: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mie coefficients ``a_n, b_n`` (n = 1 … terms) of homogeneous spheres.

    Parameters
    ----------
    size_parameter : (B,) real tensor
        ``k_m a`` (k_m the wave number in the medium, a the radius).
    relative_index : (B,) complex tensor
        ``(n_p + i κ) / n_m``.
    terms : int
        Number of orders; `term_count` of the largest sphere (the others' extra orders vanish).

    Returns
    -------
    (a, b) : (B, terms) complex128 tensors (Bohren & Huffman Eq. 4.53).
    """
    if _in_numpy(size_parameter, relative_index):
        x, m = (t.detach().to(torch.complex128).numpy() for t in (size_parameter, relative_index))
        return tuple(torch.from_numpy(np.ascontiguousarray(c)) for c in _mie_recurrences(np, x, m, terms))
    return _mie_recurrences(torch, size_parameter.to(torch.complex128), relative_index.to(torch.complex128), terms)


def _mie_recurrences(xp, x, m, terms: int) -> tuple:
    """`mie_coefficients` of complex128 (B,) size parameters ``x`` and relative indices ``m``: (B, terms) ``a`` and ``b``.

    ``xp``: numpy (arrays; no gradient) or torch (tensors, differentiable). In numpy,
    ``D_n(x)``, ``ψ_n / ξ_n`` and ``D_n^{(3)}(x)``, which depend on the size parameter alone,
    run once per distinct ``x`` (a size–index scan repeats each size for many indices); in
    torch the reciprocals go through real arithmetic (its complex division is several times
    slower).
    """
    count = x.shape[0]
    if xp is np:
        sizes, which = np.unique(x, return_inverse=True)
        reciprocal, divide = (lambda w: 1.0 / w), (lambda v, w: v / w)
        # D_n(m x) and D_n(x) end to end: their counts differ
        join, split = np.concatenate, (lambda t: (t[..., :count], t[..., count:]))
        per_sphere, own = (lambda t: t[which]), (lambda t: t)
    else:
        sizes = x
        reciprocal, divide = _reciprocal, (lambda v, w: v * _reciprocal(w))
        join, split = torch.stack, (lambda t: (t[..., 0, :], t[..., 1, :]))
        per_sphere = own = lambda t: t.contiguous()
    mx = m * x
    # For real m the downward recurrence of D_n(mx) forgets its start only where the Bessel
    # functions decay, beyond n ≈ |mx| + 4|mx|^{1/3}; starting at |mx| (pylorenzmie 3.4.0)
    # leaves errors of order 1 in a_n for non-absorbing spheres of size parameter ≥ 50.
    largest = float(abs(mx).max().item()) if count else 0.0
    start = max(terms, int(largest)) + 16 + int(4.0 * largest ** (1 / 3))
    # D_n(mx) and D_n(x) together; multiplications by 1/z cost less than divisions
    z = join([mx, sizes])
    inverse = reciprocal(z)
    log_derivative = xp.zeros_like(z)
    kept = [log_derivative] * (terms + 1)
    for n in range(start, 0, -1):
        t = n * inverse
        log_derivative = t - reciprocal(log_derivative + t)
        if n - 1 <= terms:
            kept[n - 1] = log_derivative
    inner, outer = split(xp.stack(kept))  # (terms + 1, ·): the upward recurrences read one order at a time
    inv_x = split(inverse)[1]
    psi_xi = 0.5 * (1.0 - xp.exp(2j * sizes))  # ψ_0 ξ_0
    ratio = 1j * xp.sin(sizes) * xp.exp(-1j * sizes)  # ψ_0 / ξ_0
    d3 = xp.full_like(sizes, 1j)
    ratios, d3s = [], []
    for n in range(1, terms + 1):
        n_over_x = n * inv_x
        up_psi = n_over_x - outer[n - 1]  # ψ_n / ψ_{n-1}
        up_xi = n_over_x - d3
        psi_xi = psi_xi * up_psi * up_xi
        ratio = divide(ratio * up_psi, up_xi)
        d3 = outer[n] + divide(1j, psi_xi)
        ratios.append(ratio)
        d3s.append(d3)
    ratio, d3, outer = (per_sphere(t) for t in (xp.stack(ratios, -1), xp.stack(d3s, -1), outer[1:].T))
    inner = own(inner[1:].T)
    ha = divide(inner, m[:, None])
    hb = inner * m[:, None]
    return divide(ratio * (ha - outer), ha - d3), divide(ratio * (hb - outer), hb - d3)


def radial_step(z_um: torch.Tensor, diameter_um: torch.Tensor, *, wavelength_um: float, medium_index: float, samples_per_lobe: int = 12) -> torch.Tensor:
    """Radial sample spacing (µm) per sphere: its narrowest scattering lobe ``λ_m z / d`` over ``samples_per_lobe``.

    Twelve keep the interpolation error near 1e-4 of the fringes' amplitude (the comparison
    with pylorenzmie); six, 16 times that, still far below a camera's noise. Each sphere
    gets its own spacing, so its hologram does not depend on the batch it is computed in.
    """
    lobe_um = (wavelength_um / medium_index) * z_um.detach().to(torch.float64) / diameter_um.detach().to(torch.float64)
    return torch.clamp(lobe_um / samples_per_lobe, min=1e-3)


def radial_profiles(
    z_um: torch.Tensor,
    diameter_um: torch.Tensor,
    index_contrast: torch.Tensor,
    absorption: torch.Tensor,
    *,
    rho_max_um: float,
    wavelength_um: float,
    medium_index: float,
    terms: int | None = None,
    radial_step_um: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The spheres' ``A, B, C`` profiles (module docstring) from ρ = 0 to ``rho_max_um``.

    Arguments as `sphere_fields`; ``diameter_um``, ``index_contrast`` and ``absorption``
    may also be (S, B): S spheres at each of the B depths, which share the angular and
    radial functions of the partial-wave sums (`_profile_sums`), so S sets cost little
    more than one. Returns ``(profiles, step)``: (3, S·B, R) complex128 samples (set-major)
    ``step`` (B,) µm apart (the first one at ρ = -step, mirrored), for `fields_from_profiles`.
    """
    k = 2.0 * math.pi * medium_index / wavelength_um
    count = z_um.shape[0]
    sets = diameter_um.reshape(-1, count).shape[0]
    size = (k * diameter_um.to(torch.float64) / 2.0).reshape(-1)
    relative = (((medium_index + index_contrast.to(torch.float64)) + 1j * absorption.to(torch.float64)) / medium_index).reshape(-1)
    if terms is None:
        largest = int(torch.argmax(size.detach()))
        terms = term_count(float(size[largest].detach()), complex(relative[largest].detach()))
    a_eff, b_eff = (c.reshape(sets, count, terms).transpose(0, 1) for c in weighted_coefficients(*mie_coefficients(size, relative, terms=terms)))
    if radial_step_um is None:
        radial_step_um = radial_step(z_um, diameter_um.reshape(sets, count)[0], wavelength_um=wavelength_um, medium_index=medium_index)
    step = torch.as_tensor(radial_step_um, dtype=torch.float64, device=z_um.device).expand(count)
    samples = math.ceil(rho_max_um / float(step.min())) + 4
    grid = ((torch.arange(samples, dtype=torch.float64, device=z_um.device) - 1.0)[None, :] * step[:, None]).abs()
    profiles = torch.stack(_profile_sums(a_eff, b_eff, k, z_um.to(torch.float64), grid))  # (3, B, S, R)
    return profiles.transpose(1, 2).reshape(3, sets * count, samples), step


def _carrier(rho2: torch.Tensor, z_um: torch.Tensor, k: float) -> torch.Tensor:
    """``e^{i k (r - z)}`` (the fringes), written without cancellation; ``z_um`` broadcast against ``rho2``."""
    phase = k * rho2 / (torch.sqrt(rho2 + z_um**2) + z_um)
    return torch.polar(torch.ones_like(phase), phase)


def fields_from_profiles(
    profiles: torch.Tensor, step: torch.Tensor, dx_um: torch.Tensor, dy_um: torch.Tensor, z_um: torch.Tensor, *, wavelength_um: float, medium_index: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(E_x, E_y, E_z)`` (K·B, P) at sensor points (B, P) from `radial_profiles` of K·B spheres (K copies of B, ``z_um`` (K·B,)).

    Copy ``j`` of point set ``b`` is profile row ``j·B + b``: perturbed copies of the same
    spheres at the same points share the interpolation. Copies at their point set's depth
    (other materials or sizes of the same spheres) may give ``z_um`` (B,): the carrier is then
    evaluated once for all of them.
    """
    k = 2.0 * math.pi * medium_index / wavelength_um
    count = dx_um.shape[0]
    copies = profiles.shape[1] // count
    dx, dy = dx_um.to(torch.float64), dy_um.to(torch.float64)
    rho2 = dx**2 + dy**2
    rho = torch.sqrt(rho2 + 1e-300)
    along_x, along_y, axial = interpolated_profiles(profiles, step, rho)
    carrier = _carrier(rho2, z_um.to(torch.float64).reshape(-1, count, 1), k)
    inv = 1.0 / (rho2 + 1e-300)
    ex = carrier * (along_x + (dy**2 * inv) * (along_y - along_x))
    ey = carrier * ((dx * dy * inv) * (along_x - along_y))
    ez = carrier * ((dx / rho) * axial)
    return tuple(f.reshape(copies * count, -1) for f in (ex, ey, ez))


def _pixel_transfer(dx_um: torch.Tensor, dy_um: torch.Tensor, z_um: torch.Tensor, *, k: float, pixel_um: float) -> torch.Tensor:
    """A square pixel's transfer ``sinc(h x) sinc(h y)`` at the fringes' local frequency, ``h = k p / (2π r)``; ``z_um`` broadcast."""
    half = k * pixel_um / (2.0 * math.pi * torch.sqrt(dx_um**2 + dy_um**2 + z_um**2))  # sinc(u) = sin(πu)/(πu): u = κ_x p / 2π
    return torch.sinc(half * dx_um) * torch.sinc(half * dy_um)


def lateral_derivatives(
    profiles: torch.Tensor,
    step: torch.Tensor,
    dx_um: torch.Tensor,
    dy_um: torch.Tensor,
    z_um: torch.Tensor,
    *,
    wavelength_um: float,
    medium_index: float,
    pixel_um: float | None,
    others: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``∂I/∂x`` and ``∂I/∂y`` (B, P) of the holograms `holograms_from_fields` makes from these profiles, at each sensor point.

    Analytic: the interpolated profiles' slopes in ρ, the carrier's ``dΦ/dρ = k ρ / r``,
    the azimuthal factors' and the pixel transfer's derivatives. A point moved by ``+h``
    is the sphere moved by ``-h``. ``others``: fields (B, P) added to the sphere's (their
    interference with it, as the refinement's neighbours), fixed.
    """
    k = 2.0 * math.pi * medium_index / wavelength_um
    dx, dy = dx_um.to(torch.float64), dy_um.to(torch.float64)
    z = z_um.to(torch.float64)[:, None]
    rho2 = dx**2 + dy**2
    rho = torch.sqrt(rho2 + 1e-300)
    values, slopes = interpolated_profiles(profiles, step, rho, slope=True)
    (a, b, c), (a1, b1, c1) = values[:, 0], slopes[:, 0]
    r = torch.sqrt(rho2 + z**2)
    carrier = _carrier(rho2, z, k)
    inv = 1.0 / (rho2 + 1e-300)
    cos_p, sin_p = dx / rho, dy / rho  # ∂ρ/∂x, ∂ρ/∂y
    g, h = dy**2 * inv, dx * dy * inv  # sin²φ, cosφ sinφ
    fields = (carrier * (a + g * (b - a)), carrier * (h * (a - b)), carrier * (cos_p * c))
    transfer = 1.0
    if pixel_um is not None:
        scale = k * pixel_um / (2.0 * math.pi * r)
        u, v = scale * dx, scale * dy
        su, sv = torch.sinc(u), torch.sinc(v)
        slope_of = lambda w, s: torch.where(w == 0, torch.zeros_like(w), (torch.cos(math.pi * w) - s) / torch.where(w == 0, torch.ones_like(w), w))
        dsu, dsv = slope_of(u, su), slope_of(v, sv)
        transfer = su * sv
    derivatives = []
    # per axis: ∂ρ, ∂sin²φ, ∂(cosφ sinφ), ∂cosφ
    for rho_w, g_w, h_w, q_w, axis in ((cos_p, -2.0 * g * cos_p / rho, dy * inv * (1.0 - 2.0 * cos_p**2), g / rho, 0),
                                       (sin_p, 2.0 * sin_p * (1.0 - g) / rho, dx * inv * (1.0 - 2.0 * sin_p**2), -h / rho, 1)):
        turn = 1j * k * rho / r * rho_w  # ∂(iΦ)
        d_fields = (
            carrier * (a1 * rho_w + g_w * (b - a) + g * (b1 - a1) * rho_w) + turn * fields[0],
            carrier * (h_w * (a - b) + h * (a1 - b1) * rho_w) + turn * fields[1],
            carrier * (q_w * c + cos_p * c1 * rho_w) + turn * fields[2],
        )
        d_transfer = 0.0
        if pixel_um is not None:
            d_scale = -scale * (dx if axis == 0 else dy) / r**2
            d_transfer = dsu * (d_scale * dx + (scale if axis == 0 else 0.0)) * sv + su * dsv * (d_scale * dy + (scale if axis == 1 else 0.0))
        total = d_fields[0] * transfer + fields[0] * d_transfer
        total = total + sum(f.conj() * d for f, d in zip(fields, d_fields, strict=True))
        if others is not None:
            total = total + sum(d * o.conj() for d, o in zip(d_fields, others, strict=True))
        derivatives.append(2.0 * total.real)
    return derivatives[0], derivatives[1]


def sphere_fields(
    dx_um: torch.Tensor,
    dy_um: torch.Tensor,
    z_um: torch.Tensor,
    diameter_um: torch.Tensor,
    index_contrast: torch.Tensor,
    absorption: torch.Tensor,
    *,
    wavelength_um: float,
    medium_index: float,
    terms: int | None = None,
    radial_step_um: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Scattered field ``(E_x, E_y, E_z)`` of spheres at sensor points, relative to the incident wave.

    Parameters
    ----------
    dx_um, dy_um : (B, P) real tensors
        Sensor points relative to each sphere's centre (µm; x along the polarisation, the columns).
    z_um : (B,) tensor
        Distance from each centre to the sensor, in the medium (µm, positive).
    diameter_um, index_contrast, absorption : (B,) tensors
        Diameter (µm), ``n_p - n_m`` and the imaginary part κ of the particle's index.
    wavelength_um, medium_index : float
        Vacuum wavelength (µm) and the medium's index ``n_m``.
    terms : int, optional
        Partial waves (default: `term_count` of the largest sphere).
    radial_step_um : (B,) tensor, optional
        Spacing of each sphere's radial samples (default: `radial_step`).

    Returns
    -------
    Three (B, P) complex128 tensors, differentiable in every input.
    """
    rho_max = float(torch.sqrt(dx_um.detach() ** 2 + dy_um.detach() ** 2).max())
    profiles, step = radial_profiles(z_um, diameter_um, index_contrast, absorption, rho_max_um=rho_max, wavelength_um=wavelength_um, medium_index=medium_index,
                                     terms=terms, radial_step_um=radial_step_um)
    return fields_from_profiles(profiles, step, dx_um, dy_um, z_um, wavelength_um=wavelength_um, medium_index=medium_index)


def holograms_from_fields(fields: tuple[torch.Tensor, torch.Tensor, torch.Tensor], dx_um: torch.Tensor, dy_um: torch.Tensor, z_um: torch.Tensor, *,
                          wavelength_um: float, medium_index: float, pixel_um: float | None) -> torch.Tensor:
    """``|x̂ + E_s|²`` (K·B, P) from `sphere_fields`' or `fields_from_profiles`' output at points (B, P); ``pixel_um`` as in `sphere_holograms`.

    ``z_um``: (K·B,), or (B,) where every copy lies at its point set's depth (the pixels' transfer computed once).
    """
    ex, ey, ez = fields
    cross = ex
    if pixel_um is not None:
        k = 2.0 * math.pi * medium_index / wavelength_um
        count = dx_um.shape[0]
        transfer = _pixel_transfer(dx_um, dy_um, z_um.reshape(-1, count, 1), k=k, pixel_um=pixel_um)
        cross = (ex.reshape(-1, *dx_um.shape) * transfer).reshape(ex.shape)
    return 1.0 + 2.0 * cross.real + ex.real**2 + ex.imag**2 + ey.real**2 + ey.imag**2 + ez.real**2 + ez.imag**2


def sphere_holograms(
    dx_um: torch.Tensor,
    dy_um: torch.Tensor,
    z_um: torch.Tensor,
    diameter_um: torch.Tensor,
    index_contrast: torch.Tensor,
    absorption: torch.Tensor,
    *,
    wavelength_um: float,
    medium_index: float,
    pixel_um: float | None = None,
    terms: int | None = None,
    radial_step_um: torch.Tensor | None = None,
) -> torch.Tensor:
    """Lorenz–Mie holograms ``|x̂ + E_s|²`` (unobstructed light = 1) of spheres at sensor points.

    Arguments as `sphere_fields`. With ``pixel_um`` each pixel integrates its square: the
    interference term is multiplied by the pixel's transfer at the fringes' local frequency
    ``k ρ / r`` (sinc per axis), the slowly varying ``|E_s|²`` is not. Without it the
    hologram is point-sampled, as pylorenzmie's.

    Returns
    -------
    (B, P) float64 tensor.
    """
    optics = {"wavelength_um": wavelength_um, "medium_index": medium_index}
    fields = sphere_fields(dx_um, dy_um, z_um, diameter_um, index_contrast, absorption, terms=terms, radial_step_um=radial_step_um, **optics)
    return holograms_from_fields(fields, dx_um, dy_um, z_um, pixel_um=pixel_um, **optics)


def weighted_coefficients(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``i E_n a_n`` and ``E_n b_n`` with ``E_n = i^n (2n+1) / (n(n+1))``: the factors of `_profile_sums`' sums."""
    n = torch.arange(1, a.shape[-1] + 1, dtype=torch.float64, device=a.device)
    phase = torch.tensor([1.0 + 0j, 1j, -1.0 + 0j, -1j], dtype=torch.complex128, device=a.device)[(torch.arange(1, a.shape[-1] + 1, device=a.device) % 4)]
    en = phase * (2.0 * n + 1.0) / (n * n + n)
    return 1j * en * a, en * b


def _profile_sums(a_eff: torch.Tensor, b_eff: torch.Tensor, k: float, z_um: torch.Tensor, rho_um: torch.Tensor, *, block: int = 1 << 21
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``A, B, C`` (module docstring) of S coefficient sets per row, at each row's radii: three (..., S, R) tensors.

    ``a_eff, b_eff``: (..., S, terms) from `weighted_coefficients`; ``z_um`` (...);
    ``rho_um`` (..., R); leading dimensions broadcast. The angular and radial functions
    (``π_n, τ_n, ξ_n, ξ_n'``) depend on a row's depth and radii only, so they are computed
    once per row and the partial-wave sums of all S sets are matrix products: a size–index
    scan costs little more than one model.
    """
    r = torch.sqrt(rho_um**2 + z_um[..., None] ** 2)
    kr, cos_t = k * r, z_um[..., None] / r
    if _in_numpy(rho_um, a_eff, b_eff, z_um):
        arrays = (t.detach().resolve_conj().numpy() for t in (a_eff, b_eff, kr, cos_t))
        s0, s1, s2 = (torch.from_numpy(s) for s in _partial_wave_sums(np, *arrays, block=block))
    else:
        s0, s1, s2 = _partial_wave_sums(torch, a_eff, b_eff, kr, cos_t, block=block)
    sin_t, cos_t, kr = (rho_um / r)[..., None, :], cos_t[..., None, :], kr[..., None, :]
    radial = s0 * sin_t / kr
    return (radial * sin_t + s1 * cos_t) / kr, -s2 / kr, (radial * cos_t - s1 * sin_t) / kr


def _partial_wave_sums(xp, a_eff, b_eff, kr, cos_t, *, block: int) -> tuple:
    """``Σ n(n+1) a_n π_n ξ_n``, ``-Σ (a_n τ_n ξ_n' + b_n π_n ξ_n)``, ``Σ (a_n π_n ξ_n' + b_n τ_n ξ_n)``: (..., S, R) each.

    ``xp``: numpy (arrays) or torch (tensors, differentiable). ``ξ_n`` (Riccati–Hankel,
    carrier removed: ``ξ_{-1} = 1``, ``ξ_0 = -i``), ``π_n`` and ``τ_n`` by upward recurrence
    (Bohren & Huffman, Ch. 4). With several sets per row the functions of ``width``
    orders are stacked and multiplied by the sets' coefficients (``block`` values at most).
    """
    stack = np.stack if xp is np else torch.stack
    # the sets' products in torch either way: its MKL rounds the same in every process
    # (`MKL_CBWR`), numpy's BLAS by the buffers' memory alignment
    product = (lambda a, b: (torch.from_numpy(a) @ torch.from_numpy(b)).numpy()) if xp is np else (lambda a, b: a @ b)
    terms = a_eff.shape[-1]
    inv_kr = 1.0 / kr
    xi_prev2, xi_prev = 1.0 + 0.0 * inv_kr + 0j, -1j + 0.0 * inv_kr
    pi_prev, pi_n = 0.0 * inv_kr, 1.0 + 0.0 * inv_kr
    s0 = s1 = s2 = 0
    width = max(1, min(terms, block // max(1, math.prod(kr.shape))))
    single = a_eff.shape[-2] == 1
    basis: list[list] = [[], [], [], []]
    first = 0
    for n in range(1, terms + 1):
        swisc = pi_n * cos_t
        twisc = swisc - pi_prev
        tau = n * twisc - pi_prev
        xi = ((2 * n - 1) * inv_kr) * xi_prev - xi_prev2
        dxi = (n * inv_kr) * xi - xi_prev
        pi_prev, pi_n, pi_now = pi_n, swisc + (1.0 + 1.0 / n) * twisc, pi_n
        xi_prev2, xi_prev = xi_prev, xi
        if single:  # one set per row: the sums directly, no basis to multiply
            a_n, b_n = a_eff[..., n - 1 : n], b_eff[..., n - 1 : n]
            p_xi = (pi_now * xi)[..., None, :]
            s0 = s0 + (a_n * (n * n + n)) * p_xi
            s1 = s1 - a_n * (tau * dxi)[..., None, :] - b_n * p_xi
            s2 = s2 + a_n * (pi_now * dxi)[..., None, :] + b_n * (tau * xi)[..., None, :]
            continue
        for store, value in zip(basis, (pi_now * xi, tau * dxi, pi_now * dxi, tau * xi), strict=True):
            store.append(value)
        if len(basis[0]) == width or n == terms:
            p_xi, t_dxi, p_dxi, t_xi = (stack(store, -2) for store in basis)  # (..., width, R)
            orders = np.arange(first + 1, n + 1, dtype=np.float64)
            weight = orders * orders + orders if xp is np else torch.as_tensor(orders * orders + orders, device=kr.device)
            a_block, b_block = a_eff[..., first:n], b_eff[..., first:n]
            s0 = s0 + product(a_block * weight, p_xi)
            s1 = s1 - product(a_block, t_dxi) - product(b_block, p_xi)
            s2 = s2 + product(a_block, p_dxi) + product(b_block, t_xi)
            basis = [[], [], [], []]
            first = n
    return s0, s1, s2


_RING_SAMPLES_PER_LOBE = 6  # as the pixel model's in the fit (`radial_step`)


def _coarse_profile_sums(a_eff: torch.Tensor, b_eff: torch.Tensor, k: float, z_um: torch.Tensor, rho_um: torch.Tensor,
                         lobe_diameter_um: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`_profile_sums` at the radii ``rho_um``, through a coarser radial grid where one suffices (`mean_intensity`)."""
    if lobe_diameter_um is None:
        return _profile_sums(a_eff, b_eff, k, z_um, rho_um)
    z = z_um.expand(rho_um.shape[:-1]) if z_um.dim() < rho_um.dim() - 1 else z_um
    step = (2.0 * math.pi / k) * z / torch.clamp(lobe_diameter_um.expand_as(z), min=1e-6) / _RING_SAMPLES_PER_LOBE  # (...)
    rho_max = float(rho_um.max())
    samples = math.ceil(rho_max / float(step.min())) + 4
    if samples >= rho_um.shape[-1]:
        return _profile_sums(a_eff, b_eff, k, z_um, rho_um)
    grid = ((torch.arange(samples, dtype=torch.float64, device=rho_um.device) - 1.0) * step[..., None]).abs()  # (..., Rc), first mirrored
    coarse = torch.stack(_profile_sums(a_eff, b_eff, k, z, grid))  # (3, ..., S, Rc)
    rows, sets = math.prod(coarse.shape[1:-2]), coarse.shape[-2]
    # every set of a row shares its radii: the sets are the channels of one interpolation
    table = torch.view_as_real(coarse.reshape(3, rows, sets, samples)).permute(1, 3, 0, 2, 4).reshape(rows, samples, 6 * sets)
    values = CatmullRom.apply(table, (rho_um / step[..., None] + 1.0).reshape(rows, -1))  # (rows, R, 3·S·2)
    out = torch.view_as_complex(values.reshape(rows, -1, 3, sets, 2).permute(2, 0, 3, 1, 4).contiguous())  # (3, rows, S, R)
    out = out.reshape(3, *coarse.shape[1:-1], rho_um.shape[-1])
    return out[0], out[1], out[2]


_AZIMUTHS = 16  # quadrature points over a quarter turn for the pixel's transfer averaged over the azimuth


def mean_intensity(a_eff: torch.Tensor, b_eff: torch.Tensor, z_um: torch.Tensor, rho_um: torch.Tensor, *, k: float, pixel_um: float | None,
                    annulus_um: float | None, lobe_diameter_um: torch.Tensor | None = None) -> torch.Tensor:
    """`azimuthal_mean_holograms` from weighted coefficients (..., S, terms), depths (...) and radii (..., R): (..., S, R, 2).

    ``lobe_diameter_um`` (shape of ``z_um``): the largest diameter of each row's sets. With
    it, ``A, B, C`` are summed on a radial grid of `_RING_SAMPLES_PER_LOBE` samples per
    scattering lobe (``λ_m z / d``) and interpolated to the radii (Catmull–Rom, as the
    pixels' are), when that grid is coarser than the radii: the carrier stays exact.
    """
    along_x, along_y, axial = _coarse_profile_sums(a_eff, b_eff, k, z_um, rho_um, lobe_diameter_um)
    p, q = 0.5 * (along_x + along_y), 0.5 * (along_x - along_y)
    z = z_um[..., None]
    rho2 = rho_um**2
    r = torch.sqrt(rho2 + z**2)
    carrier = _carrier(rho2, z, k)[..., None, :]
    # moments ⟨T⟩, ⟨T cos2φ⟩, ⟨T cos²2φ⟩ of the pixel's transfer T over the azimuth (T = 1 for point samples)
    t0, t1, t2 = 1.0, 0.0, 0.5
    if pixel_um is not None:
        half = (k * pixel_um / (2.0 * math.pi * r) * rho_um)[..., None]
        phi = (torch.arange(_AZIMUTHS, dtype=torch.float64, device=rho_um.device) + 0.5) * (0.5 * math.pi / _AZIMUTHS)
        transfer = torch.sinc(half * torch.cos(phi)) * torch.sinc(half * torch.sin(phi))
        c2 = torch.cos(2.0 * phi)
        t0, t1, t2 = (m[..., None, :] for m in (transfer.mean(dim=-1), (transfer * c2).mean(dim=-1), (transfer * c2 * c2).mean(dim=-1)))
    if annulus_um is not None:
        carrier = carrier * torch.sinc(k * rho_um / r * annulus_um / (2.0 * math.pi))[..., None, :]
    c_sq = axial.real**2 + axial.imag**2
    mean = 1.0 + 2.0 * (carrier * (p * t0 + q * t1)).real + p.real**2 + p.imag**2 + q.real**2 + q.imag**2 + 0.5 * c_sq
    second = 2.0 * (carrier * (p * t1 + q * t2)).real + (p.conj() * q).real + 0.25 * c_sq
    return torch.stack([mean, second], dim=-1)


def azimuthal_mean_holograms(
    z_um: torch.Tensor,
    diameter_um: torch.Tensor,
    index_contrast: torch.Tensor,
    absorption: torch.Tensor,
    rho_um: torch.Tensor,
    *,
    wavelength_um: float,
    medium_index: float,
    pixel_um: float | None = None,
    annulus_um: float | None = None,
    terms: int | None = None,
) -> torch.Tensor:
    """Holograms' two azimuthal moments about each sphere's centre, ``⟨I⟩`` and ``⟨I cos2φ⟩``: (N, S, R, 2).

    With ``P = (A + B)/2``, ``Q = (A - B)/2`` (module docstring), ``E_x = e^{iΦ}(P + Q cos2φ)``,
    ``E_y = e^{iΦ} Q sin2φ``, ``E_z = e^{iΦ} C cosφ``, so a sphere's hologram holds only the
    harmonics 0 and 2 of the azimuth::

        I = 1 + |P|² + |Q|² + |C|²/2 + 2 Re(e^{iΦ} P)
              + cos2φ (2 Re(e^{iΦ} Q) + 2 Re(P̄ Q) + |C|²/2)

    and its ring means ``⟨I⟩`` and ``⟨I cos2φ⟩`` (half the second harmonic) carry all of
    it: a sphere's ring profile costs radial samples, not pixels. ``pixel_um``: each pixel's
    transfer ``sinc(h x) sinc(h y)`` (as `sphere_holograms`) on the interference term,
    its moments over φ by quadrature. ``annulus_um``: the data are means over rings that
    wide, so the interference term is also averaged across the ring (``sinc`` of the fringe
    phase the ring spans).

    Parameters
    ----------
    z_um : (N,) tensor
        Depth of row n (µm, in the medium).
    diameter_um, index_contrast, absorption : (N, S) tensors
        S spheres per row, all at that row's depth.
    rho_um : (N, R) tensor
        Radii (µm) of row n.
    wavelength_um, medium_index, pixel_um, annulus_um : float
    terms : int, optional
        Partial waves (default: `term_count` of the largest sphere).

    Returns
    -------
    (N, S, R, 2) float64 tensor: ``⟨I⟩`` (unobstructed light = 1) and ``⟨I cos2φ⟩``.
    """
    k = 2.0 * math.pi * medium_index / wavelength_um
    count, sets = diameter_um.shape
    size = (k * diameter_um.to(torch.float64) / 2.0).reshape(-1)
    relative = (((medium_index + index_contrast.to(torch.float64)) + 1j * absorption.to(torch.float64)) / medium_index).reshape(-1)
    if terms is None:
        largest = int(torch.argmax(size))
        terms = term_count(float(size[largest]), complex(relative[largest]))
    a, b = mie_coefficients(size, relative, terms=terms)
    a_eff, b_eff = (t.reshape(count, sets, terms) for t in weighted_coefficients(a, b))
    return mean_intensity(a_eff, b_eff, z_um.to(torch.float64), rho_um.to(torch.float64), k=k, pixel_um=pixel_um, annulus_um=annulus_um)
