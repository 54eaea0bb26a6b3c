"""Every detection refined by a Lorenz–Mie fit of its hologram patch.

For each particle of a table of starting guesses (the network's, a user's clicks, another
tool's CSV) the patch of the hologram around it is fitted with the exact Lorenz–Mie
hologram of a sphere (`napari_lbs._core.physics._lorenz_mie`, Lee et al. 2007) for its position,
depth, diameter, index contrast ``n_p - n_m`` and absorption ``κ`` (the imaginary part of
its index), times a smooth illumination ``c0 + c1 u + c2 v`` over the patch (the beam's
envelope; ``u, v`` the patch coordinates in -1 … 1). All particles are fitted at once,
batched in torch.

1. **Patch**: a square of at most ``patch_px`` pixels, and no wider than the disc inside
   which the fringes are sampled (their frequency below the pixel's Nyquist limit).
2. **Searches on ring profiles**: about the patch's centre of symmetry, the ring means of
   ``I`` and ``I cos2φ`` (of the data less the neighbours' hologram, 5.) are exact functions of the sphere's radial profiles
   (`azimuthal_mean_holograms`), so the depth is scanned over ``±depth_window_um`` (steps
   that move the outermost fringe by one radian), the size and index on a grid at the best
   depths, and each start followed down its valley, at the cost of rings, not pixels.
3. **Fit**: Levenberg–Marquardt on Huber-weighted residuals (the noise scale from the
   residuals' median absolute deviation), on every other pixel and then on all; the
   Jacobian by finite differences of the differentiable forward model, every perturbation
   in one batch.
4. **Valleys and ripple**: the phase delay through a transparent sphere is seen modulo 2π
   and its hologram ripples with its size; the ring cost along the line of constant phase
   delay and in the neighbouring valleys (`_ring_profile`) restarts the fit at a deeper
   point, and bounds the diameter's and index's intervals (`_interval_threshold`).
5. **Neighbours**: each patch's model holds the summed fields of the other detections in
   reach, fixed at their guesses (in later rounds, at the previous round's fits); two
   detections a quarter diameter apart laterally may be one particle twice and stay out of
   each other's model.
6. **False detections and twins**: a particle whose best fit does not lower the robust cost
   of the model without it (its neighbours and the illumination) by ``min_gain`` noise
   variances is dropped, and so is one that converged onto a particle another detection
   fitted better.
7. **Uncertainties**: ``σ² (JᵀWJ)⁻¹`` at the optimum (Gauss–Newton), ``σ`` the residuals'
   scale, inflated by the residuals' pixel-to-pixel correlation (what model error and
   neighbours leave is not white); for the diameter and index, at least half the valley
   profile's two-standard-deviation interval.

Depths in the table keep the config's convention (``optics.medium_index``: with the
default 1, air-equivalent distances); the scattering happens in the sample's medium,
``RefineSettings.medium_index`` (water by default), so the physical depth is
``z_um * medium_index / optics.medium_index``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np
import torch

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import PARTICLE_COLUMNS, InputError
from napari_lbs._core.physics import (
    mean_intensity,
    weighted_coefficients,
    fields_from_profiles,
    holograms_from_fields,
    lateral_derivatives,
    mie_coefficients,
    radial_profiles,
    radial_step,
    sphere_fields,
    term_count,
)
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback
from napari_lbs._core.foundation import size_threads

__all__ = ["FIT_PARAMETERS", "REFINE_COLUMNS", "RefineSettings", "refine_particles"]

FIT_PARAMETERS = ("x_um", "y_um", "z_um", "diameter_um", "index_contrast", "absorption")
REFINE_COLUMNS = ("index_contrast", "absorption", "z_err_um", "diameter_err_um", "index_err", "fit_residual", "refined", "outside_training")
_PHYSICAL = len(FIT_PARAMETERS)
_NUISANCE = 3  # illumination c0 + c1 u + c2 v
_BOUNDS = {  # (low, high) of each physical parameter in fit units; positions are bounded by the patch
    "diameter_um": (0.05, 500.0),
    "index_contrast": (-0.9, 2.5),
    "absorption": (0.0, 5.0),
}


@dataclass(frozen=True)
class RefineSettings:
    """How `refine_particles` fits.

    Attributes
    ----------
    medium_index : float
        Refractive index of the medium the particles are in (water: 1.33). The Lorenz–Mie
        scattering happens there; the table's depths stay in the config's convention.
    index_contrast, absorption : float
        Starting ``n_p - n_m`` (polystyrene in water: 0.26) and ``κ`` when the table has no
        such column.
    depth_window_um : float
        Depths scanned on each side of the guess (µm, the table's convention).
    depth_candidates : int
        Best local minima of the scan that start a fit.
    patch_px : int
        Largest patch edge (pixels).
    iterations : int
        Levenberg–Marquardt steps per round.
    rounds : int
        Fitting rounds. In the first, each particle's model holds the holograms of the
        other detections in reach at their guesses; each later one refits the particles with
        neighbours, holding them at the previous round's fits (more precise in crowded
        fields: two rounds halved the median depth error at four times the seed's density,
        at about 1.8 times the time).
    huber : float
        Residuals beyond this many noise scales get a Huber weight below 1.
    min_gain : float
        Lowering of the robust cost (in noise variances) that the fit must achieve over
        the model without the particle (its neighbours and the illumination) to keep a
        detection.
    pixel_integration : bool
        Model each pixel integrating its area (True) or point-sampled (pylorenzmie's).
    batch : int
        Most particles fitted together (memory); a round's particles are split into the
        fewest batches of at most this many, of equal sizes.
    device : str
        ``cpu``, ``cuda`` or ``auto``.
    workers : int
        Processes fitting batches side by side on the CPU, one thread each (the batches
        are independent: the table is the one a single process on one thread gives, bit
        for bit). More than 1 spawns processes, so a script must start
        its work under ``if __name__ == "__main__":``; ``napari-lbs predict --refine`` uses
        one per available core.
    """

    medium_index: float = 1.33
    index_contrast: float = 0.26
    absorption: float = 0.0
    depth_window_um: float = 400.0
    depth_candidates: int = 3
    patch_px: int = 128
    iterations: int = 8
    rounds: int = 1
    huber: float = 2.5
    min_gain: float = 50.0
    pixel_integration: bool = True
    batch: int = 8
    device: str = "cpu"
    workers: int = 1

    def __post_init__(self) -> None:
        for name in ("medium_index", "depth_window_um", "huber", "min_gain"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise InputError(f"refine settings: {name} must be a finite number >= 0, got {value!r}")
        for name in ("depth_candidates", "patch_px", "iterations", "rounds", "batch", "workers"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise InputError(f"refine settings: {name} must be a positive integer, got {value!r}")
        if self.patch_px < 16:
            raise InputError(f"refine settings: patch_px must be at least 16, got {self.patch_px}")
        for name in ("index_contrast", "absorption"):
            _check_bounded(f"refine settings: {name}", name, getattr(self, name))


def _check_bounded(label: str, name: str, value) -> None:
    """A start or fixed value of a bounded parameter (`_BOUNDS`) inside the fit's range."""
    low, high = _BOUNDS[name]
    if not (isinstance(value, int | float) and math.isfinite(value) and low <= value <= high):
        raise InputError(f"{label} must be a number from {low:g} to {high:g} (the fit's range), got {value!r}")


@dataclass
class _Patches:
    """Hologram patches of a batch of particles, flattened and padded to one length."""

    data: torch.Tensor  # (B, P) intensities
    mask: torch.Tensor  # (B, P) 1 where a real pixel
    x_um: torch.Tensor  # (B, P) pixel positions
    y_um: torch.Tensor
    u: torch.Tensor  # (B, P) patch coordinates in -1 … 1
    v: torch.Tensor
    shape: list[tuple[int, int]]  # each patch's (rows, cols)


def _check_hologram(hologram) -> np.ndarray:
    image = np.asarray(hologram)
    if image.ndim != 2:
        raise InputError(f"hologram: expected a 2-D image, got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.number):
        raise InputError(f"hologram: expected numbers, got dtype {image.dtype}")
    image = image.astype(np.float64)
    if not np.all(np.isfinite(image)):
        raise InputError("hologram: contains NaN or infinite values")
    if not np.any(image > 0):
        raise InputError("hologram: no positive intensity (all zero?); expected a hologram normalised by its background")
    return image


def _check_table(table):
    import pandas as pd

    frame = pd.DataFrame(table).reset_index(drop=True)
    missing = [c for c in PARTICLE_COLUMNS if c not in frame.columns]
    if missing:
        raise InputError(f"particle table: missing column {missing[0]}")
    for name in PARTICLE_COLUMNS:
        values = pd.to_numeric(frame[name], errors="coerce").to_numpy(dtype=np.float64)
        if not np.all(np.isfinite(values)):
            raise InputError(f"particle table: column {name} holds NaN, infinite or non-numeric values")
        frame[name] = values
    if np.any(frame["z_um"] <= 0):
        raise InputError("particle table: column z_um must be positive (distance to the sensor)")
    if np.any(frame["diameter_um"] <= 0):
        raise InputError("particle table: column diameter_um must be positive")
    return frame


def _check_fixed(fixed: Mapping[str, float] | None) -> dict[str, float]:
    fixed = dict(fixed or {})
    for name, value in fixed.items():
        if name not in FIT_PARAMETERS:
            raise InputError(f"fixed: unknown parameter {name!r} (expected one of {', '.join(FIT_PARAMETERS)})")
        if not (isinstance(value, int | float) and math.isfinite(value)):
            raise InputError(f"fixed: {name} must be a finite number, got {value!r}")
        if name in _BOUNDS:
            _check_bounded(f"fixed: {name}", name, value)
    return fixed


def _patch_edge(z_um: float, *, settings: RefineSettings, wavelength_um: float, pixel_um: float) -> int:
    """Patch edge (px): the disc of fringes below the Nyquist frequency, at most ``patch_px``."""
    sin_nyquist = min(wavelength_um / settings.medium_index / (2.0 * pixel_um), 0.99)
    radius_px = z_um * sin_nyquist / math.sqrt(1.0 - sin_nyquist**2) / pixel_um
    return int(max(16, min(settings.patch_px, 2 * round(radius_px))))


def _cut_patches(image: np.ndarray, x_um: np.ndarray, y_um: np.ndarray, edges: np.ndarray, *, pixel_um: float, device) -> _Patches:
    rows, cols = image.shape
    length = int(max(edges)) ** 2
    count = len(x_um)
    data = np.ones((count, length))
    mask = np.zeros((count, length))
    xs = np.zeros((count, length))
    ys = np.zeros((count, length))
    us = np.zeros((count, length))
    vs = np.zeros((count, length))
    shapes = []
    for i, (x, y, edge) in enumerate(zip(x_um, y_um, edges, strict=True)):
        half = edge // 2
        c0, r0 = round(x / pixel_um) - half, round(y / pixel_um) - half
        r_lo, r_hi = max(r0, 0), min(r0 + edge, rows)
        c_lo, c_hi = max(c0, 0), min(c0 + edge, cols)
        if r_lo >= r_hi or c_lo >= c_hi:
            shapes.append((0, 0))
            continue
        block = image[r_lo:r_hi, c_lo:c_hi]
        rr, cc = np.mgrid[r_lo:r_hi, c_lo:c_hi]
        n = block.size
        data[i, :n] = block.ravel()
        mask[i, :n] = 1.0
        # padding sits on the patch's first pixel: the models' radial range stays the patch's
        xs[i] = cc.ravel()[0] * pixel_um
        ys[i] = rr.ravel()[0] * pixel_um
        xs[i, :n] = cc.ravel() * pixel_um
        ys[i, :n] = rr.ravel() * pixel_um
        us[i, :n] = (cc.ravel() - (c0 + half)) / max(half, 1)
        vs[i, :n] = (rr.ravel() - (r0 + half)) / max(half, 1)
        shapes.append(block.shape)
    as_tensor = lambda a: torch.as_tensor(a, dtype=torch.float64, device=device)
    return _Patches(as_tensor(data), as_tensor(mask), as_tensor(xs), as_tensor(ys), as_tensor(us), as_tensor(vs), shapes)


def _every_other_pixel(patches: _Patches) -> tuple[_Patches, torch.Tensor]:
    """The patches' every other row and column (padded as `_cut_patches` pads) and their indices (B, P') in ``patches``' pixels."""
    length = max((-(-rows // 2)) * (-(-cols // 2)) for rows, cols in patches.shape) if patches.shape else 0
    count = len(patches.shape)
    index = torch.zeros((count, max(length, 1)), dtype=torch.long, device=patches.data.device)
    real = torch.zeros(index.shape, dtype=torch.bool, device=patches.data.device)
    shapes = []
    for i, (rows, cols) in enumerate(patches.shape):
        picked = (torch.arange(0, rows, 2, device=index.device)[:, None] * cols + torch.arange(0, cols, 2, device=index.device)).reshape(-1)
        index[i, : picked.numel()] = picked
        real[i, : picked.numel()] = True
        shapes.append((-(-rows // 2), -(-cols // 2)))
    take = lambda t, padding: torch.where(real, torch.gather(t, 1, index), torch.full_like(index, padding, dtype=t.dtype))
    coarse = _Patches(take(patches.data, 1.0), take(patches.mask, 0.0), torch.gather(patches.x_um, 1, index), torch.gather(patches.y_um, 1, index),
                      take(patches.u, 0.0), take(patches.v, 0.0), shapes)
    return coarse, index


_FIT_SAMPLES_PER_LOBE = 6  # radial samples per scattering lobe in the fit (see radial_step)
# Finite-difference steps of the Jacobian's depth-like columns (z µm, diameter µm, index, κ):
# far below every parameter's precision and far above round-off in complex128.
_JACOBIAN_STEPS = {2: 1e-3, 3: 1e-5, 4: 1e-7, 5: 1e-7}


class _Model:
    """The patch model ``(c0 + c1 u + c2 v) · |x̂ + E(θ) + E_others|²`` of a batch, and its Jacobian.

    ``others``: None, or (4, B, P) complex: the neighbours' hologram minus 1 (real part of
    row 0) and their summed fields ``E_x, E_y, E_z`` (rows 1-3), fixed; the particle's own
    field adds to theirs (``2 Re(E · E_others*)``), so overlapping particles shadow and
    interfere as fields do.
    """

    def __init__(self, patches: _Patches, others: torch.Tensor | None, *, wavelength_um: float, medium_index: float, pixel_um: float | None, terms: int) -> None:
        self.patches = patches
        self.others = others
        self.optics = {"wavelength_um": wavelength_um, "medium_index": medium_index}
        self.pixel_um = pixel_um
        self.terms = terms

    def _profiles(self, params: torch.Tensor, *, step: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """``(profiles, step, dx, dy, z)`` of K stacked copies of the batch's parameters (K·B rows), which share the first copy's centre."""
        x, y, z, d, dn, kappa = params[:, :_PHYSICAL].unbind(-1)
        p = self.patches
        count = p.x_um.shape[0]
        copies = params.shape[0] // count
        dx, dy = p.x_um - x[:count, None], p.y_um - y[:count, None]
        rho_max = float(torch.sqrt(dx**2 + dy**2).max())
        if step is None:
            step = radial_step(z[:count], d[:count], samples_per_lobe=_FIT_SAMPLES_PER_LOBE, **self.optics)
        # copies at the same depths share the partial-wave sums' angular and radial functions
        depths = z.reshape(copies, count)
        groups: list[list[int]] = []
        for copy in range(copies):
            group = next((g for g in groups if torch.equal(depths[g[0]], depths[copy])), None)
            if group is None:
                groups.append([copy])
            else:
                group.append(copy)
        parts = {}
        for group in groups:
            spheres = [t.reshape(copies, count)[group] for t in (d, dn, kappa)]
            profiles, _ = radial_profiles(depths[group[0]], *spheres, rho_max_um=rho_max, terms=self.terms, radial_step_um=step, **self.optics)
            parts.update({copy: profiles[:, j * count : (j + 1) * count] for j, copy in enumerate(group)})
        return torch.cat([parts[copy] for copy in range(copies)], dim=1), step, dx, dy, z

    def _holograms(self, profiles: torch.Tensor, step: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        fields = fields_from_profiles(profiles, step, dx, dy, z, **self.optics)
        own = holograms_from_fields(fields, dx, dy, z, pixel_um=self.pixel_um, **self.optics)
        if self.others is None:
            return own
        others = self.others.repeat(1, z.shape[0] // dx.shape[0], 1)
        cross = sum(f * o.conj() for f, o in zip(fields, others[1:], strict=True))
        return own + others[0].real + 2.0 * cross.real

    def sphere(self, params: torch.Tensor, *, step: torch.Tensor | None = None) -> torch.Tensor:
        """Holograms (K·B, P) of K stacked copies of the batch's parameters (K·B rows); the copies share the first one's centre."""
        return self._holograms(*self._profiles(params, step=step))

    def with_terms(self, terms: int) -> _Model:
        """The same model summing at least ``terms`` partial waves (for larger spheres than it was made for)."""
        return self if terms <= self.terms else _Model(self.patches, self.others, pixel_um=self.pixel_um, terms=terms, **self.optics)

    def select(self, rows: torch.Tensor) -> _Model:
        """The model of some of the batch's patches (their rows)."""
        p = self.patches
        patches = _Patches(*(getattr(p, f.name)[rows] for f in fields(_Patches) if f.name != "shape"), shape=[p.shape[i] for i in rows.tolist()])
        others = None if self.others is None else self.others[:, rows]
        return _Model(patches, others, pixel_um=self.pixel_um, terms=self.terms, **self.optics)

    def illumination(self, params: torch.Tensor) -> torch.Tensor:
        c = params[:, _PHYSICAL:]
        return c[:, :1] + c[:, 1:2] * self.patches.u + c[:, 2:3] * self.patches.v

    def __call__(self, params: torch.Tensor) -> torch.Tensor:
        return self.illumination(params) * self.sphere(params)

    def jacobian(self, params: torch.Tensor, free: torch.Tensor, *, envelope: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """``(model, J)``: (B, P) and (B, P, 9); columns of parameters fixed everywhere are zero.

        The depth, size, index and absorption columns are finite differences of the
        differentiable model with every perturbation stacked in one batch: its partial-wave
        recurrences then run once for all of them (forward-mode differentiation pays their
        per-operation overhead once per parameter: measured 60 times slower), and the
        perturbed copies share the pixels' interpolation weights. The lateral columns are
        analytic (`lateral_derivatives`).

        With ``envelope`` the diameter and index columns are central differences over a
        size parameter (``Δ(k a) = ±0.5``, ``Δ(m x) = ±0.5``): a transparent sphere's
        hologram ripples with its size and index (morphology-dependent resonances, spaced
        ``Δ(k a) ≈ 0.2`` at k a ≈ 150, measured), so the local curvature promises a
        precision that only the ripple supports; the secant over the ripple measures the
        envelope's.
        """
        count = params.shape[0]
        k_m = 2.0 * math.pi * self.optics["medium_index"] / self.optics["wavelength_um"]
        depth_like = [k for k in range(2, _PHYSICAL) if bool(free[:, k].any())]
        steps = {k: torch.full((count,), _JACOBIAN_STEPS[k], dtype=torch.float64, device=params.device) for k in depth_like}
        central = [k for k in (3, 4) if envelope and k in depth_like]
        if 3 in central:
            steps[3] = torch.full_like(steps[3], 1.0 / k_m)  # Δ(k a) = 0.5 each way
        if 4 in central:
            steps[4] = 0.5 * self.optics["medium_index"] / (k_m * params[:, 3] / 2.0)  # Δ(m x) = 0.5 each way
        signs = [(k, 1.0) for k in depth_like] + [(k, -1.0) for k in central]
        stacked = params.repeat(1 + len(signs), 1)
        for slot, (k, sign) in enumerate(signs, start=1):
            stacked[slot * count : (slot + 1) * count, k] += sign * steps[k]
        # one radial grid per particle for all its perturbations: the differences see the model, not a moved grid
        step = radial_step(params[:, 2], params[:, 3], samples_per_lobe=_FIT_SAMPLES_PER_LOBE, **self.optics)
        profiles, step, dx, dy, z = self._profiles(stacked, step=step)
        holograms = self._holograms(profiles, step, dx, dy, z).reshape(1 + len(signs), count, -1)
        base = holograms[0]
        gain = self.illumination(params)
        columns = [torch.zeros_like(base)] * _PHYSICAL
        if bool(free[:, :2].any()):
            others = None if self.others is None else tuple(self.others[1:])
            along_x, along_y = lateral_derivatives(profiles[:, :count], step, dx, dy, z[:count], others=others, pixel_um=self.pixel_um, **self.optics)
            # the pattern moves with the particle: moving the points by +h is moving the particle by -h
            columns[0], columns[1] = -along_x * gain, -along_y * gain
        for slot, (k, sign) in enumerate(signs, start=1):
            if sign < 0:
                continue
            lower = holograms[1 + len(depth_like) + central.index(k)] if k in central else base
            width = steps[k] * (2.0 if k in central else 1.0)
            columns[k] = (holograms[slot] - lower) * (gain / width[:, None])
        p = self.patches
        return gain * base, torch.stack(columns + [base, base * p.u, base * p.v], dim=-1)


def _robust_scale(residual: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-patch noise scale: 1.4826 × median absolute residual over real pixels."""
    absolute = torch.where(mask > 0, residual.abs(), torch.full_like(residual, float("nan")))
    return torch.clamp(1.4826 * torch.nanmedian(absolute, dim=1).values, min=1e-6)


def _huber(residual: torch.Tensor, scale: torch.Tensor, mask: torch.Tensor, threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Huber weights and robust cost (in units of the scale², per patch)."""
    t = residual.abs() / scale[:, None]
    weight = torch.where(t <= threshold, torch.ones_like(t), threshold / torch.clamp(t, min=1e-12)) * mask
    rho = torch.where(t <= threshold, 0.5 * t**2, threshold * t - 0.5 * threshold**2) * mask
    return weight, rho.sum(dim=1)


def _clamp(params: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    return torch.maximum(torch.minimum(params, high), low)


def _levenberg_marquardt(model: _Model, params: torch.Tensor, free: torch.Tensor, low: torch.Tensor, high: torch.Tensor, *, scale: torch.Tensor,
                         settings: RefineSettings, iterations: int, steps: Steps | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Robust Levenberg–Marquardt on every patch at once; returns the parameters and their robust cost.

    Each patch keeps its own damping; a rejected step is retried, more damped, on the
    patches that rejected it only, and a patch whose cost fell by less than
    `_LM_TOLERANCE` (or `_LM_RELATIVE` of itself) in an iteration has converged and leaves the batch.
    """
    count = params.shape[0]
    params = params.clone()
    damping = torch.full((count,), 1e-3, dtype=torch.float64, device=params.device)
    cost = torch.zeros(count, dtype=torch.float64, device=params.device)
    active = torch.arange(count, device=params.device)
    for _ in range(iterations):
        if steps is not None:
            steps.check()
        sub = model if active.numel() == count else model.select(active)
        data, mask = sub.patches.data, sub.patches.mask
        p, f, s = params[active], free[active], scale[active]
        freef = f.to(torch.float64)
        prediction, jac = sub.jacobian(p, f)
        residual = data - prediction
        weight, current = _huber(residual, s, mask, settings.huber)
        before = current.clone()
        jac = jac * freef[:, None, :]
        jtw = jac.transpose(1, 2) * weight[:, None, :]
        normal = jtw @ jac
        gradient = (jtw @ residual[:, :, None])[:, :, 0]
        diagonal = torch.diagonal(normal, dim1=1, dim2=2).clamp(min=1e-30)
        # fixed parameters: a unit diagonal and no gradient keep them where they are
        normal = normal + torch.diag_embed(torch.where(f, torch.zeros_like(diagonal), torch.ones_like(diagonal)))
        rows = torch.arange(active.numel(), device=params.device)
        lam = damping[active]
        for _attempt in range(4):
            system = normal[rows] + torch.diag_embed(lam[rows, None] * torch.where(f[rows], diagonal[rows], torch.zeros_like(diagonal[rows])))
            delta = torch.linalg.solve(system, gradient[rows, :, None])[:, :, 0]
            trial = _clamp(p[rows] + delta * freef[rows], low[active][rows], high[active][rows])
            subset = sub if rows.numel() == active.numel() else sub.select(rows)
            _, trial_cost = _huber(data[rows] - subset(trial), s[rows], mask[rows], settings.huber)
            better = trial_cost < current[rows]
            p[rows[better]] = trial[better]
            current[rows[better]] = trial_cost[better]
            lam[rows] = torch.where(better, lam[rows] * 0.3, lam[rows] * 10.0).clamp(1e-7, 1e7)
            rows = rows[~better]
            if rows.numel() == 0:
                break
        params[active] = p
        cost[active] = current
        damping[active] = lam
        # converged: the cost fell by less than a tenth of a noise variance, or 1e-4 of itself
        active = active[before - current >= torch.clamp(_LM_RELATIVE * before, min=_LM_TOLERANCE)]
        if active.numel() == 0:
            break
    return params, cost


_LM_TOLERANCE = 0.05  # half noise variances (Δχ² = 0.1)
_LM_RELATIVE = 1e-4


def _best(costs: torch.Tensor, count: int, *, local: bool) -> torch.Tensor:
    """Indices (B, count) of the lowest costs, local minima along the last axis first when ``local``."""
    ranked = costs
    if local:
        padded = torch.nn.functional.pad(costs[:, None, :], (1, 1), mode="replicate")[:, 0]
        minima = (costs <= padded[:, :-2]) & (costs <= padded[:, 2:])
        ranked = torch.where(minima, costs, costs + costs.abs().max() + 1.0)
    return torch.argsort(ranked, dim=1)[:, : min(count, costs.shape[1])]


def _residual_inflation(residual: torch.Tensor, mask: torch.Tensor, shapes: list[tuple[int, int]]) -> torch.Tensor:
    """Variance inflation ``(1+ρx)/(1-ρx) · (1+ρy)/(1-ρy)`` from the residuals' lag-1 correlations (≥ 1)."""
    out = []
    for i, (rows, cols) in enumerate(shapes):
        if rows < 3 or cols < 3:
            out.append(1.0)
            continue
        r = residual[i, : rows * cols].reshape(rows, cols)
        r = r - r.mean()
        var = float((r * r).mean())
        if var <= 0:
            out.append(1.0)
            continue
        factor = 1.0
        for a, b in ((r[:, 1:], r[:, :-1]), (r[1:, :], r[:-1, :])):
            rho = min(max(float((a * b).mean()) / var, 0.0), 0.9)
            factor *= (1 + rho) / (1 - rho)
        out.append(factor)
    return torch.tensor(out, dtype=torch.float64, device=residual.device)


# ---------------------------------------------------------------------------------------
# Searches on ring profiles. A sphere's hologram averaged over the azimuth about its centre
# is exact from its radial profiles (`azimuthal_mean_holograms`), and the data's ring means
# are one scatter-add: a depth or size–index trial costs the rings (about half the patch
# edge), not the patch's pixels. The illumination's linear terms average out over a ring.

_CENTRE_REACH_PX = 3.0  # the symmetric centre is looked for this far around the guess
_VALLEY_PRIOR = 16.0  # robust-cost units (half noise variances) per squared phase-delay period from the starting index
# size–index grid at each candidate depth: diameters around the start, and for each the
# index contrasts whose phase delay k0 d Δn steps through one period on each side
_GRID_DIAMETER_UM = tuple(0.4 * j for j in range(-9, 10))
_GRID_OUTER_DIAMETER_UM = tuple(0.4 * j for j in (*range(-20, -9), *range(10, 21)))  # where a best size lies on the grid's edge
_GRID_DELAY_PERIODS = tuple(j / 4 for j in range(-4, 5))
# the valley profile: size parameter k a along the line of constant phase delay, the
# neighbouring valleys, and the delay and depth offsets each point is minimised over
_PROFILE_SPAN = 4.0
_PROFILE_STEP = 0.25
_PROFILE_VALLEYS = (-1, 0, 1)
_PROFILE_DELAY = 0.03  # periods
_INTERVAL = 2.0  # half-variances: Δχ² = 4, the two-standard-deviation interval of one parameter


@dataclass
class _Rings:
    """Ring means of a batch's patches about centres (rings one pixel wide, out to the patch's corners)."""

    data: torch.Tensor  # (B, R, 2) mean intensity and mean intensity × cos2φ
    weight: torch.Tensor  # (B, R) pixels per ring
    rho_um: torch.Tensor  # (B, R) their mean radius
    cos2: torch.Tensor  # (B, R) their mean cos2φ (0 on a whole ring)
    cos2_sq: torch.Tensor  # (B, R) their mean cos²2φ (1/2 on a whole ring)
    width_um: float

    def map(self, change) -> _Rings:
        """The rings with ``change`` applied to every per-patch tensor (repeat, select)."""
        return _Rings(change(self.data), change(self.weight), change(self.rho_um), change(self.cos2), change(self.cos2_sq), self.width_um)

    def model(self, moments: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Expected ring means (..., R) of ``I`` and ``I cos2φ`` from the model's moments (..., R, 2) (`azimuthal_mean_holograms`).

        The hologram is ``h0 + h2 cos2φ`` (``h2 = 2 ⟨I cos2φ⟩``), so over a ring's pixels, a
        whole ring or the arcs of a patch's corners, its means are ``h0 + h2 ⟨cos2φ⟩`` and
        ``h0 ⟨cos2φ⟩ + h2 ⟨cos²2φ⟩``.
        """
        h0, h2 = moments[..., 0], 2.0 * moments[..., 1]
        return h0 + h2 * self.cos2_like(h0), h0 * self.cos2_like(h0) + h2 * self.cos2_sq_like(h0)

    def cos2_like(self, like: torch.Tensor) -> torch.Tensor:
        return self.cos2.reshape(self.cos2.shape[0], *([1] * (like.dim() - 2)), -1)

    def cos2_sq_like(self, like: torch.Tensor) -> torch.Tensor:
        return self.cos2_sq.reshape(self.cos2_sq.shape[0], *([1] * (like.dim() - 2)), -1)


def _symmetric_centres(residual: torch.Tensor, patches: _Patches, guess_x: np.ndarray, guess_y: np.ndarray, *, pixel_um: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (µm) about which each patch is point-symmetric, near the guesses.

    A sphere's hologram is symmetric under ``(x, y) → (2c - x, 2c - y)`` (every term of the
    module docstring of `_lorenz_mie` is even in the azimuth), so the self-convolution of the
    patch peaks at ``2c`` (Cauchy–Schwarz). The patch is tapered about the current centre
    (neighbours and the border weigh less) and the peak found with sub-pixel parabolas,
    twice.
    """
    out_x, out_y = guess_x.copy(), guess_y.copy()
    for i, (rows, cols) in enumerate(patches.shape):
        if rows < 8 or cols < 8:
            continue
        image = residual[i, : rows * cols].reshape(rows, cols).cpu().numpy()
        x0, y0 = float(patches.x_um[i, 0]) / pixel_um, float(patches.y_um[i, 0]) / pixel_um
        guess = np.array([guess_x[i] / pixel_um - x0, guess_y[i] / pixel_um - y0])
        centre = guess.copy()
        yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
        radius = 0.5 * min(rows, cols)
        for _ in range(2):
            rho = np.hypot(xx - centre[0], yy - centre[1]) / radius
            tapered = image * np.cos(0.5 * np.pi * np.minimum(rho, 1.0)) ** 2
            spectrum = np.fft.rfft2(tapered, s=(2 * rows, 2 * cols))
            conv = np.fft.irfft2(spectrum * spectrum, s=(2 * rows, 2 * cols))
            lo = np.floor(2 * (guess - _CENTRE_REACH_PX)).astype(int)
            hi = np.ceil(2 * (guess + _CENTRE_REACH_PX)).astype(int)
            lo = np.maximum(lo, 1)
            hi = np.minimum(hi, np.array([2 * cols - 2, 2 * rows - 2]))
            if np.any(hi < lo):
                break
            region = conv[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
            my, mx = np.unravel_index(int(np.argmax(region)), region.shape)
            my, mx = my + lo[1], mx + lo[0]
            peak = np.array([mx, my], dtype=float)
            for axis, (minus, mid, plus) in enumerate(((conv[my, mx - 1], conv[my, mx], conv[my, mx + 1]), (conv[my - 1, mx], conv[my, mx], conv[my + 1, mx]))):
                curvature = minus - 2.0 * mid + plus
                if curvature < 0:
                    peak[axis] += float(np.clip(0.5 * (minus - plus) / curvature, -0.5, 0.5))
            centre = peak / 2.0
        out_x[i] = (centre[0] + x0) * pixel_um
        out_y[i] = (centre[1] + y0) * pixel_um
    return out_x, out_y


def _cut_rings(patches: _Patches, centre_x: torch.Tensor, centre_y: torch.Tensor, *, pixel_um: float) -> _Rings:
    """Ring means (`_Rings`) of each patch about its centre, every pixel of the patch in one ring."""
    dx = patches.x_um - centre_x[:, None]
    dy = patches.y_um - centre_y[:, None]
    rho2 = dx**2 + dy**2
    rho = torch.sqrt(rho2)
    cos2 = torch.where(rho2 > 0, (dx**2 - dy**2) / torch.clamp(rho2, min=1e-30), torch.zeros_like(rho2))
    keep = patches.mask
    width = pixel_um
    count = max(1, math.ceil(float((rho * keep).max()) / width) + 1)
    ring = torch.clamp((rho / width).long(), max=count - 1)
    zeros = torch.zeros((rho.shape[0], count), dtype=torch.float64, device=rho.device)
    sums = [zeros.scatter_add(1, ring, keep * values) for values in (torch.ones_like(rho), patches.data, patches.data * cos2, rho, cos2, cos2 * cos2)]
    weight = sums[0]
    safe = torch.clamp(weight, min=1.0)
    centres = (torch.arange(count, dtype=torch.float64, device=rho.device) + 0.5) * width
    rho_mean = torch.where(weight > 0, sums[3] / safe, centres.expand_as(weight))
    cos2_sq = torch.where(weight > 0, sums[5] / safe, torch.full_like(weight, 0.5))
    return _Rings(torch.stack([sums[1] / safe, sums[2] / safe], dim=-1), weight, torch.clamp(rho_mean, min=1e-3), sums[4] / safe,
                  torch.clamp(cos2_sq, min=1e-3), width)


def _ring_fit_terms(rings: _Rings, moments: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted data and model of the rings: ``(√w0 D0, √w2 D2, √w0 M0, √w2 M2)``, each (..., R), ``w`` their inverse variances over σ²."""
    m0, m2 = rings.model(moments)
    shape = (rings.weight.shape[0], *([1] * (m0.dim() - 2)), -1)
    w0 = torch.sqrt(rings.weight).reshape(shape)
    w2 = torch.sqrt(rings.weight / rings.cos2_sq).reshape(shape)
    d0 = rings.data[..., 0].reshape(shape)
    d2 = rings.data[..., 1].reshape(shape)
    return w0 * d0, w2 * d2, w0 * m0, w2 * m2


def _ring_costs(rings: _Rings, z_um: torch.Tensor, spheres: torch.Tensor, scale: torch.Tensor, *, model: _Model) -> torch.Tensor:
    """Cost (B, Z, S), in half noise variances, of S spheres (diameter, index contrast, κ) at each of Z depths per patch.

    Each with its best brightness ``c0`` (least squares): ``½ Σ_rings w (D - c0 M)² / σ²``
    over both ring means (`_Rings.model`), ``w`` their inverse variances in units of the
    pixel noise σ², so differences are χ² differences of the patch.
    """
    k = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    medium = model.optics["medium_index"]
    count, depths = z_um.shape
    sets = spheres.shape[1]
    radii = rings.rho_um.shape[1]
    size = (k * spheres[..., 0] / 2.0).reshape(-1)
    relative = ((medium + spheres[..., 1]) + 1j * spheres[..., 2]).reshape(-1) / medium
    a, b = mie_coefficients(size, relative, terms=model.terms)
    a_eff, b_eff = (t.reshape(count, 1, sets, model.terms) for t in weighted_coefficients(a, b))
    per = max(1, int(_RING_BLOCK // max(1, depths * sets * radii)))
    out = []
    for first in range(0, count, per):
        part = slice(first, first + per)
        moments = mean_intensity(a_eff[part], b_eff[part], z_um[part], rings.rho_um[part, None, :].expand(-1, depths, -1), k=k,
                                  pixel_um=model.pixel_um, annulus_um=rings.width_um,
                                  lobe_diameter_um=spheres[part, :, 0].amax(dim=1)[:, None])  # (b, Z, S, R, 2)
        sub = rings.map(lambda t, part=part: t[part])
        d0, d2, m0, m2 = _ring_fit_terms(sub, moments)
        cross = (d0 * m0 + d2 * m2).sum(dim=-1)
        square = torch.clamp((m0 * m0 + m2 * m2).sum(dim=-1), min=1e-30)
        total = (d0 * d0 + d2 * d2).sum(dim=-1)
        out.append(0.5 * torch.clamp(total - cross**2 / square, min=0.0) / scale[part, None, None] ** 2)
    return torch.cat(out, dim=0)


_RING_BLOCK = 1.5e6  # ring samples per chunk of `_ring_costs` (memory)


def _ring_residuals(rings: _Rings, z_um: torch.Tensor, spheres: torch.Tensor, scale: torch.Tensor, *, model: _Model) -> torch.Tensor:
    """Whitened ring residuals (B, R) of one sphere (diameter, index contrast, κ) per patch at its depth (B,), its brightness fitted."""
    k = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    medium = model.optics["medium_index"]
    count = z_um.shape[0]
    a, b = mie_coefficients(k * spheres[:, 0] / 2.0, ((medium + spheres[:, 1]) + 1j * spheres[:, 2]) / medium, terms=model.terms)
    a_eff, b_eff = (t.reshape(count, 1, model.terms) for t in weighted_coefficients(a, b))
    moments = mean_intensity(a_eff, b_eff, z_um, rings.rho_um, k=k, pixel_um=model.pixel_um, annulus_um=rings.width_um,
                              lobe_diameter_um=spheres[:, 0])[:, 0]  # (B, R, 2)
    d0, d2, m0, m2 = _ring_fit_terms(rings, moments)
    c0 = (d0 * m0 + d2 * m2).sum(dim=1) / torch.clamp((m0 * m0 + m2 * m2).sum(dim=1), min=1e-30)
    return torch.cat([d0 - c0[:, None] * m0, d2 - c0[:, None] * m2], dim=1) / scale[:, None]


def _ring_fit(rings: _Rings, start: torch.Tensor, free: torch.Tensor, kappa: torch.Tensor, scale: torch.Tensor, low: torch.Tensor, high: torch.Tensor, *,
              model: _Model, iterations: int, depth_reach_um: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss–Newton of (z, d, Δn) (B, 3) on the ring residuals; returns them and their cost (half-variances).

    The depth and size trade off along a diagonal valley of the ring cost (a larger sphere
    farther away), which a grid cut along the axes misses: the fit follows it. The
    derivatives are secants over the ripple (`_Model.jacobian`'s envelope: ``Δ(k a) = ±0.5``,
    ``Δ(m x) = ±0.5``; depth ±0.5 µm), so the fit follows the valley's envelope and the
    valley profile then picks among its ripples.
    """
    count = start.shape[0]
    params = start.clone()
    freef = free.to(torch.float64)
    k_m = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]

    def residuals(p: torch.Tensor, rows: int) -> torch.Tensor:
        grow = lambda t: t.repeat(rows // count, *([1] * (t.dim() - 1)))
        ring_rows = rings.map(grow)
        return _ring_residuals(ring_rows, p[:, 0], torch.stack([p[:, 1], p[:, 2], grow(kappa)], dim=-1), grow(scale), model=model)

    best = params.clone()
    best_cost = torch.full((count,), math.inf, dtype=torch.float64, device=start.device)
    for _ in range(iterations):
        steps = torch.stack([torch.full_like(params[:, 0], 0.5), torch.full_like(params[:, 0], 1.0 / k_m),
                             0.5 * model.optics["medium_index"] / (k_m * params[:, 1] / 2.0)], dim=-1)  # (B, 3), each way
        stacked = params.repeat(7, 1)
        for axis in range(3):
            stacked[(2 * axis + 1) * count : (2 * axis + 2) * count, axis] += steps[:, axis]
            stacked[(2 * axis + 2) * count : (2 * axis + 3) * count, axis] -= steps[:, axis]
        res = residuals(stacked, 7 * count).reshape(7, count, -1)
        # the stencil's mean residual and cost: the envelope, the ripple averaged out
        base = res.mean(dim=0)
        cost = 0.5 * (res**2).sum(dim=2).mean(dim=0)
        jac = torch.stack([(res[2 * axis + 1] - res[2 * axis + 2]) / (2.0 * steps[:, axis:axis + 1]) for axis in range(3)], dim=-1) * freef[:, None, :]
        better = cost < best_cost
        best_cost = torch.where(better, cost, best_cost)
        best = torch.where(better[:, None], params, best)
        normal = jac.transpose(1, 2) @ jac
        gradient = -(jac.transpose(1, 2) @ base[:, :, None])[:, :, 0]
        diagonal = torch.diagonal(normal, dim1=1, dim2=2).clamp(min=1e-30)
        normal = normal + torch.diag_embed(torch.where(free, _RING_DAMPING * diagonal, torch.ones_like(diagonal)))
        # Gauss–Newton on the envelope, every step taken (the ripple would reject good ones),
        # each at most a few secant widths; the best point visited is kept
        delta = torch.linalg.solve(normal, gradient[:, :, None])[:, :, 0] * freef
        reach = _RING_REACH * steps
        reach[:, 0] = depth_reach_um
        delta = torch.maximum(torch.minimum(delta, reach), -reach)
        params = torch.maximum(torch.minimum(params + delta, high), low)
    return best, best_cost


_RING_DAMPING = 1e-4
_RING_REACH = 4.0  # largest Gauss–Newton step of size and index, in secant widths (Δ(k a) = 2)


def _ring_depth_step(rings: _Rings, z_um: torch.Tensor, *, window_um: float, k: float, pixel_um: float) -> float:
    """Depth step (µm) that moves the outermost ring's fringe (phase k ρ²/2z) by one radian at the nearest depth scanned."""
    rho_max = float(torch.max(torch.where(rings.weight > 0, rings.rho_um, torch.zeros_like(rings.rho_um))))
    nearest = float(torch.clamp(z_um - window_um, min=0.1 * max(window_um, 1.0)).min())
    return max(2.0 * nearest**2 / (k * max(rho_max, pixel_um) ** 2), 0.5 * pixel_um)


def _parabola_vertex(costs: torch.Tensor, best: torch.Tensor) -> torch.Tensor:
    """Sub-sample offset (-0.5 … 0.5) of the minimum of (B, T) costs near their samples ``best`` (B,)."""
    last = costs.shape[1] - 1
    rows = torch.arange(costs.shape[0], device=costs.device)
    inner = torch.clamp(best, 1, max(last - 1, 1))
    if last < 2:
        return torch.zeros_like(costs[:, 0])
    minus, mid, plus = costs[rows, inner - 1], costs[rows, inner], costs[rows, inner + 1]
    curvature = minus - 2.0 * mid + plus
    vertex = torch.where(curvature > 0, 0.5 * (minus - plus) / torch.clamp(curvature, min=1e-30), torch.zeros_like(mid))
    return torch.clamp(vertex + (inner - best), -0.5, 0.5)


def _ring_search(rings: _Rings, params: torch.Tensor, free: torch.Tensor, scale: torch.Tensor, *, model: _Model, window_um: float,
                 start_index: torch.Tensor, settings: RefineSettings, steps: Steps) -> torch.Tensor:
    """Depth, diameter and index contrast (B, 3) from the ring profiles: depth scan, size–index grid, fine depth scan.

    The depth is scanned over ``±window_um`` in steps that move the outermost ring's fringe
    by one radian; its ``depth_candidates`` best local minima are refined by a scan a
    quarter step apart; at each, diameters ±3.6 µm (±8 µm where the best lies on that
    grid's edge) and index contrasts one phase-delay period on each side (quarter periods)
    are compared, the valleys away from the starting index paying `_VALLEY_PRIOR` per
    period²; at the best, the depth is scanned finely again.
    """
    k = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    wavelength = model.optics["wavelength_um"]
    count = params.shape[0]
    device = params.device
    z, d, n, kappa = params[:, 2].clone(), params[:, 3].clone(), params[:, 4].clone(), params[:, 5]
    step = _ring_depth_step(rings, z, window_um=window_um, k=k, pixel_um=model.pixel_um or 1.0)
    fine = torch.arange(-6, 7, dtype=torch.float64, device=device) * (step / 4.0)

    def refine_depth(depths: torch.Tensor, spheres: torch.Tensor) -> torch.Tensor:  # (B, K) depths, (B, K, 3) spheres
        kk = depths.shape[1]
        trials = torch.clamp(depths[:, :, None] + fine, min=1.0).reshape(count * kk, -1)
        rows = lambda t: t.repeat_interleave(kk, dim=0)
        ring_rows = rings.map(rows)
        costs = _ring_costs(ring_rows, trials, spheres.reshape(count * kk, 1, 3), rows(scale), model=model)[:, :, 0]
        best = torch.argmin(costs, dim=1)
        offset = _parabola_vertex(costs, best)
        chosen = trials[torch.arange(trials.shape[0], device=device), best] + offset * (step / 4.0)
        return torch.where(free[:, 2:3], chosen.reshape(count, kk), depths)

    here = torch.stack([d, n, kappa], dim=-1)[:, None, :]
    depths = z[:, None]
    if bool(free[:, 2].any()):
        offsets = torch.arange(-window_um, window_um + 0.5 * step, step, dtype=torch.float64, device=device)
        trials = torch.where(free[:, 2:3], torch.clamp(z[:, None] + offsets, min=1.0), z[:, None])
        costs = _ring_costs(rings, trials, here, scale, model=model)[:, :, 0]
        steps.check()
        pick = _best(costs, settings.depth_candidates, local=True)
        depths = refine_depth(torch.gather(trials, 1, pick), here.expand(-1, pick.shape[1], -1))
    kk = depths.shape[1]
    candidates = torch.stack([depths, d[:, None].expand(-1, kk), n[:, None].expand(-1, kk)], dim=-1)  # (B, K, 3)
    if bool(free[:, 3].any() or free[:, 4].any()):
        delays = torch.tensor(_GRID_DELAY_PERIODS, dtype=torch.float64, device=device) * wavelength

        def grid(offsets_um) -> tuple[torch.Tensor, torch.Tensor]:
            """The spheres (B, S, 3) of the size–index grid at diameter offsets ``offsets_um`` and their costs (B, K, S), valley prior included."""
            d_steps = torch.tensor(offsets_um, dtype=torch.float64, device=device)
            diameters = torch.where(free[:, 3:4], torch.clamp(d[:, None] + d_steps, min=_BOUNDS["diameter_um"][0]), d[:, None])  # (B, D)
            contrasts = torch.where(free[:, 4:5, None], ((d * n)[:, None, None] + delays) / diameters[:, :, None], n[:, None, None])  # (B, D, N)
            spheres = torch.stack([diameters[:, :, None].expand_as(contrasts), contrasts, kappa[:, None, None].expand_as(contrasts)], dim=-1).reshape(count, -1, 3)
            steps.check()
            costs = _ring_costs(rings, depths, spheres, scale, model=model)  # (B, K, S)
            valleys = (spheres[:, :, 1] - start_index[:, None]) / (wavelength / spheres[:, :, 0])
            return spheres, costs + _VALLEY_PRIOR * (valleys**2 * free[:, 4:5].to(torch.float64))[:, None, :]

        spheres, costs = grid(_GRID_DIAMETER_UM)
        best = torch.argmin(costs, dim=2)  # (B, K)
        chosen = torch.gather(spheres, 1, best[:, :, None].expand(-1, -1, 3))
        # a best size on the grid's edge lies beyond it (a network's guess for a size it never
        # saw is up to 8 µm off): the outer grid too, for the batch
        edge = free[:, 3:4] & ((chosen[:, :, 0] - d[:, None]).abs() >= max(_GRID_DIAMETER_UM) - 1e-9)
        if bool(edge.any()):
            model = model.with_terms(_scattered_terms(float(d.max()) + max(_GRID_OUTER_DIAMETER_UM), **model.optics))
            outer_spheres, outer_costs = grid(_GRID_OUTER_DIAMETER_UM)
            outer_best = torch.argmin(outer_costs, dim=2)
            # only a candidate whose best size lay on the edge moves: a fit does not depend on its batch-mates
            better = edge & (torch.gather(outer_costs, 2, outer_best[:, :, None])[:, :, 0] < torch.gather(costs, 2, best[:, :, None])[:, :, 0])
            chosen = torch.where(better[:, :, None], torch.gather(outer_spheres, 1, outer_best[:, :, None].expand(-1, -1, 3)), chosen)
        candidates = torch.stack([depths, chosen[:, :, 0], chosen[:, :, 1]], dim=-1)
    # every candidate followed down its valley, then the best (the valley prior as above)
    grow = lambda t: t.repeat_interleave(kk, dim=0)
    flat_free = grow(free[:, 2:5])
    low = grow(torch.stack([torch.clamp(z - 1.5 * window_um, min=1.0), torch.full_like(z, _BOUNDS["diameter_um"][0]),
                            torch.full_like(z, _BOUNDS["index_contrast"][0])], dim=-1))
    high = grow(torch.stack([z + 1.5 * window_um, torch.full_like(z, _BOUNDS["diameter_um"][1]), torch.full_like(z, _BOUNDS["index_contrast"][1])], dim=-1))
    ring_rows = rings.map(grow)
    steps.check()
    fitted, cost = _ring_fit(ring_rows, candidates.reshape(count * kk, 3), flat_free, grow(kappa), grow(scale), low, high, model=model,
                             iterations=_RING_ITERATIONS, depth_reach_um=step / 2.0)
    valleys = (fitted[:, 2] - grow(start_index)) / (wavelength / fitted[:, 1])
    cost = cost + _VALLEY_PRIOR * valleys**2 * flat_free[:, 2].to(torch.float64)
    best = torch.argmin(cost.reshape(count, kk), dim=1)
    return fitted[torch.arange(count, device=device) * kk + best]


_RING_ITERATIONS = 8


@dataclass
class _Profile:
    """The valley profile of each patch (`_ring_profile`)."""

    diameter_um: torch.Tensor  # (B, T) along the valley
    contrast: torch.Tensor  # (B, T, J) at each valley's minimum
    depth_um: torch.Tensor  # (B, T, J)
    cost: torch.Tensor  # (B, T, J) minimised over depth and delay, half-variances
    scale: torch.Tensor  # (B,) noise scale the costs are in
    dof: torch.Tensor  # (B,) ring means less the fitted parameters (c0, depth, delay, size)


def _ring_profile(rings: _Rings, z_um: torch.Tensor, diameter_um: torch.Tensor, contrast: torch.Tensor, kappa: torch.Tensor, free: torch.Tensor,
                  scale: torch.Tensor, *, model: _Model, depth_step_um: float) -> _Profile:
    """The cost along the valley of constant phase delay ``d (n_p - n_m)`` and its neighbours, minimised over depth and delay.

    A transparent sphere's hologram ripples with its size (morphology-dependent resonances,
    minima ``Δ(k a) ≈ 0.2`` apart at k a ≈ 150) and its phase delay is seen modulo 2π, so
    along the valley the loss is flat to within the noise over several ripples, and the
    neighbouring valleys (Δn = λ/d) may be as deep. Each point (``Δ(k a)`` in
    `_PROFILE_STEP` steps over ±`_PROFILE_SPAN`, valley j in `_PROFILE_VALLEYS`) is
    minimised over the depth (±``depth_step_um``) and the delay (±`_PROFILE_DELAY` periods)
    by a quadratic through 3 × 3 samples: a profile likelihood.
    """
    k = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    wavelength = model.optics["wavelength_um"]
    device = z_um.device
    count = z_um.shape[0]
    both = (free[:, 3] & free[:, 4]).to(torch.float64)[:, None]
    index_free = free[:, 4].to(torch.float64)[:, None]
    t = torch.arange(-_PROFILE_SPAN, _PROFILE_SPAN + 1e-9, _PROFILE_STEP, dtype=torch.float64, device=device)
    diameters = torch.clamp(diameter_um[:, None] + both * t * (2.0 / k), min=_BOUNDS["diameter_um"][0])  # (B, T)
    valleys = torch.tensor(_PROFILE_VALLEYS, dtype=torch.float64, device=device)
    shifts = torch.tensor((-1.0, 0.0, 1.0), dtype=torch.float64, device=device)
    delay = (diameter_um * contrast)[:, None, None, None] + index_free[:, :, None, None] * (valleys[:, None] + _PROFILE_DELAY * shifts) * wavelength  # (B,1,J,Q)
    contrasts = delay / diameters[:, :, None, None]  # (B, T, J, Q)
    spheres = torch.stack([diameters[:, :, None, None].expand_as(contrasts), contrasts, kappa[:, None, None, None].expand_as(contrasts)], dim=-1)
    sizes = contrasts.shape[1:]
    depths = torch.clamp(z_um[:, None] + shifts * depth_step_um, min=1.0)  # (B, 3)
    costs = _ring_costs(rings, depths, spheres.reshape(count, -1, 3), scale, model=model)  # (B, 3 depths, T*J*Q)
    samples = costs.reshape(count, 3, *sizes).permute(0, 2, 3, 1, 4).reshape(count, sizes[0], sizes[1], 9)  # (B, T, J, depth × delay)
    u, v = torch.meshgrid(shifts, shifts, indexing="ij")  # depth, delay
    u, v = u.reshape(-1), v.reshape(-1)
    design = torch.stack([torch.ones_like(u), u, v, u * u, v * v, u * v], dim=-1)
    c = samples @ torch.linalg.pinv(design).T  # (B, T, J, 6)
    det = 4.0 * c[..., 3] * c[..., 4] - c[..., 5] ** 2
    safe = torch.where(det.abs() > 1e-12, det, torch.ones_like(det))
    uu = (-2.0 * c[..., 4] * c[..., 1] + c[..., 5] * c[..., 2]) / safe
    vv = (-2.0 * c[..., 3] * c[..., 2] + c[..., 5] * c[..., 1]) / safe
    value = c[..., 0] + c[..., 1] * uu + c[..., 2] * vv + c[..., 3] * uu**2 + c[..., 4] * vv**2 + c[..., 5] * uu * vv
    ok = (c[..., 3] > 0) & (det > 0) & (uu.abs() <= 1.5) & (vv.abs() <= 1.5)
    lowest, at = samples.min(dim=-1)
    use = ok & (value < lowest)
    profile = torch.where(use, value, lowest)
    uu = torch.where(use, uu, u[at])
    vv = torch.where(use, vv, v[at])
    best_delay = (diameter_um * contrast)[:, None, None] + index_free[:, :, None] * (valleys + _PROFILE_DELAY * vv) * wavelength
    dof = torch.clamp(2.0 * (rings.weight > 0).sum(dim=1).to(torch.float64) - 4.0, min=1.0)
    return _Profile(diameters, best_delay / diameters[:, :, None], z_um[:, None, None] + uu * depth_step_um, profile, scale, dof)


def _interval_threshold(profile: _Profile, inflation: torch.Tensor) -> torch.Tensor:
    """(B,) cost above the profile's minimum (half-variances, its units) that bounds the two-standard-deviation interval.

    Δχ² = 4 times ``inflation`` (the residuals' correlation, and the fit's noise scale over
    the profile's, squared), plus the rings' excess χ² at the minimum (its cost less half
    its degrees of freedom): a model error ``δ`` of χ² ``|δ|²`` moves the minimum of a
    least-squares cost by at most that much, and what the best point leaves unexplained
    estimates it.
    """
    excess = torch.clamp(profile.cost.amin(dim=(1, 2)) - 0.5 * profile.dof, min=0.0)
    return _INTERVAL * inflation + excess


def _profile_spread(profile: _Profile, diameter_um: torch.Tensor, contrast: torch.Tensor, threshold: torch.Tensor) -> torch.Tensor:
    """(B, 2) one-standard-deviation widths of diameter and index from the profile: the farthest point within ``threshold`` of its minimum, halved.

    ``threshold`` (B,): half-variances in the profile's units (Δχ² = 4, times the residuals'
    correlation inflation, rescaled to the profile's noise scale). Half a grid step is added
    to the diameter's reach (the grid's resolution).
    """
    inside = profile.cost <= (profile.cost.amin(dim=(1, 2)) + threshold)[:, None, None]
    d_reach = torch.where(inside, (profile.diameter_um[:, :, None] - diameter_um[:, None, None]).abs(), torch.zeros_like(profile.cost)).amax(dim=(1, 2))
    step = (profile.diameter_um[:, 1:] - profile.diameter_um[:, :-1]).abs().amax(dim=1) if profile.diameter_um.shape[1] > 1 else torch.zeros_like(d_reach)
    n_reach = torch.where(inside, (profile.contrast - contrast[:, None, None]).abs(), torch.zeros_like(profile.cost)).amax(dim=(1, 2))
    return torch.stack([(d_reach + 0.5 * step) / 2.0, n_reach / 2.0], dim=-1)


def _flat_model(patches: _Patches, others: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The model without the particle, least squares: its residual, noise scale and illumination (B, P).

    Without ``others`` the illumination alone; with them (`_Model`'s, (4, B, P)) the
    illumination times the neighbours' hologram ``1 + Re others[0]``.
    """
    plane = torch.stack([patches.mask, patches.u * patches.mask, patches.v * patches.mask], dim=-1)
    basis = plane if others is None else plane * (1.0 + others[0].real)[:, :, None]
    # the normal equations, not `torch.linalg.lstsq`: LAPACK's least squares rounds by the
    # buffers' memory alignment, so one patch would fit differently from call to call
    normal = basis.transpose(1, 2) @ basis
    empty = torch.diagonal(normal, dim1=1, dim2=2) == 0.0  # a column no pixel reaches: held at 0
    normal = normal + torch.diag_embed(empty.to(normal.dtype))
    solution = torch.linalg.solve(normal, basis.transpose(1, 2) @ (patches.data * patches.mask)[:, :, None])
    residual = (patches.data - (basis @ solution)[:, :, 0]) * patches.mask
    return residual, _robust_scale(residual, patches.mask), (plane @ solution)[:, :, 0]


# One Levenberg–Marquardt step on every pixel after the fit on every other pixel: from the
# quarter-data optimum (within ~2σ of the full one) a Gauss–Newton step lands on the full
# optimum, whose curvature the reported uncertainties describe.
_FINE_ITERATIONS = 1


def _valley_profile(fine: _Patches, model: _Model, final: torch.Tensor, cost: torch.Tensor, free: torch.Tensor, low: torch.Tensor, high: torch.Tensor,
                    scale: torch.Tensor, *, pixel_um: float, start_index: torch.Tensor, settings: RefineSettings, steps: Steps) -> tuple[torch.Tensor, torch.Tensor, _Profile]:
    """The valley profile (`_ring_profile`) about each fit, and the fit moved to its deepest point where that lies elsewhere.

    Where the profile's best point (the valley prior included) is another ripple minimum
    (more than a profile step away) or another valley, the fit is restarted there and the
    better of the two fits (robust cost plus the valley prior) is kept. ``model``: the
    patches' model on every other pixel, where the restarts run.
    """
    optics = model.optics
    count = final.shape[0]
    device = final.device
    k_m = 2.0 * math.pi * optics["medium_index"] / optics["wavelength_um"]
    rings = _cut_rings(fine, final[:, 0], final[:, 1], pixel_um=pixel_um)
    depth_step = _ring_depth_step(rings, final[:, 2], window_um=0.0, k=k_m, pixel_um=pixel_um) / 4.0
    profile = _ring_profile(rings, final[:, 2], final[:, 3], final[:, 4], final[:, 5], free, scale, model=model, depth_step_um=depth_step)
    period = lambda d: optics["wavelength_um"] / d
    prior = lambda n, d, rows: _VALLEY_PRIOR * ((n - start_index[rows]) / period(d)) ** 2 * free[rows, 4].to(torch.float64)
    ranked = profile.cost + _VALLEY_PRIOR * ((profile.contrast - start_index[:, None, None]) / period(profile.diameter_um)[:, :, None]) ** 2 \
        * free[:, 4:5, None].to(torch.float64)
    flat = torch.argmin(ranked.reshape(count, -1), dim=1)
    rows = torch.arange(count, device=device)
    valleys = profile.cost.shape[2]
    moved = final.clone()
    moved[:, 2] = profile.depth_um.reshape(count, -1)[rows, flat]
    moved[:, 3] = profile.diameter_um[rows, flat // valleys]
    moved[:, 4] = profile.contrast.reshape(count, -1)[rows, flat]
    elsewhere = ((moved[:, 3] - final[:, 3]).abs() > 1.5 * _PROFILE_STEP * 2.0 / k_m) | ((moved[:, 4] - final[:, 4]).abs() > 0.5 * period(final[:, 3]))
    todo = torch.nonzero(elsewhere).flatten()
    if todo.numel():
        steps.check()
        refit, refit_cost = _levenberg_marquardt(model.select(todo), _clamp(moved[todo], low[todo], high[todo]), free[todo], low[todo], high[todo],
                                                 scale=scale[todo], settings=settings, iterations=settings.iterations, steps=steps)
        better = refit_cost + prior(refit[:, 4], refit[:, 3], todo) < cost[todo] + prior(final[todo, 4], final[todo, 3], todo)
        final = final.clone()
        cost = cost.clone()
        final[todo[better]] = refit[better]
        cost[todo[better]] = refit_cost[better]
    return final, cost, profile


def _scattered_terms(diameter_um: float, *, wavelength_um: float, medium_index: float) -> int:
    """Partial waves for spheres up to ``diameter_um``: Wiscombe's count for one 15 % larger.

    A fit moves a sphere's size by a few per cent past its start; at the count's own size the
    coefficients left out change the hologram by less than 2e-9, 2 µm beyond it by up to 4e-3
    (measured, 30-44 µm polystyrene in water). The |m x| floor of `term_count` concerns the
    internal field, not the scattered one.
    """
    return term_count(math.pi * medium_index / wavelength_um * diameter_um * 1.15, 1.0)


def _fit_batch(image: np.ndarray, start: np.ndarray, free: np.ndarray, others_of, *, anchor: np.ndarray, search: bool, settings: RefineSettings,
               config: ExperimentConfig, terms: int, device, steps: Steps) -> dict[str, np.ndarray]:
    """Fit one batch of particles from (B, 6) physical starting parameters; arrays per particle.

    Positions and depths are bounded about ``anchor`` (B, 6), the table's guesses, in every
    round: a later round starts from the earlier fit but may not wander further from the
    detection than the first could. A fit that ends on a bound of a free parameter (other than
    zero absorption) found no minimum inside the model's range: not ``ok``.

    With ``search``: symmetric centre and ring-profile searches (`_ring_search`) on the
    data less the neighbours' hologram, then the fit. Without: the fit from ``start``. Either
    way the valley profile about the fit (`_ring_profile`) may restart it in a deeper valley
    and widens the diameter's and index's uncertainties (``spread``). ``gain``: how much the
    particle lowers the robust cost of the model without it (its neighbours and the
    illumination).
    """
    optics = config.optics
    count = start.shape[0]
    edges = np.array([_patch_edge(z, settings=settings, wavelength_um=optics.wavelength_um, pixel_um=optics.pixel_um) for z in start[:, 2]])
    model_optics = {"wavelength_um": optics.wavelength_um, "medium_index": settings.medium_index,
                    "pixel_um": optics.pixel_um if settings.pixel_integration else None, "terms": terms}
    fine = _cut_patches(image, start[:, 0], start[:, 1], edges, pixel_um=optics.pixel_um, device=device)
    model = _Model(fine, others_of(fine) if others_of is not None else None, **model_optics)
    steps.check()
    params = torch.zeros((count, _PHYSICAL + _NUISANCE), dtype=torch.float64, device=device)
    params[:, :_PHYSICAL] = torch.as_tensor(start, dtype=torch.float64, device=device)
    params[:, _PHYSICAL] = torch.sum(fine.data * fine.mask, dim=1) / torch.clamp(fine.mask.sum(dim=1), min=1.0)
    free_t = torch.ones((count, _PHYSICAL + _NUISANCE), dtype=torch.bool, device=device)
    free_t[:, :_PHYSICAL] = torch.as_tensor(free, device=device)
    low = torch.full_like(params, -math.inf)
    high = torch.full_like(params, math.inf)
    half = torch.as_tensor(edges, dtype=torch.float64, device=device) * optics.pixel_um / 4.0
    centre = torch.as_tensor(anchor, dtype=torch.float64, device=device)
    for axis in (0, 1):
        low[:, axis] = centre[:, axis] - half
        high[:, axis] = centre[:, axis] + half
    z_window = settings.depth_window_um * settings.medium_index / optics.medium_index
    low[:, 2] = torch.clamp(centre[:, 2] - 1.5 * z_window, min=1.0)
    high[:, 2] = centre[:, 2] + 1.5 * z_window
    for axis, name in ((3, "diameter_um"), (4, "index_contrast"), (5, "absorption")):
        low[:, axis], high[:, axis] = _BOUNDS[name]
    flat = _flat_model(fine)
    scale = flat[1]
    alone_residual, _, alone_light = flat if model.others is None else _flat_model(fine, model.others)  # the model without this particle
    start_index = torch.as_tensor(anchor[:, 4], dtype=torch.float64, device=device)
    if search:
        # the rings of the data less the neighbours' hologram: theirs would pull the depth scan
        seen = fine if model.others is None else _Patches(torch.where(fine.mask > 0, alone_light + alone_residual, fine.data), fine.mask, fine.x_um,
                                                           fine.y_um, fine.u, fine.v, fine.shape)
        centre_x, centre_y = _symmetric_centres(alone_residual, seen, start[:, 0], start[:, 1], pixel_um=optics.pixel_um)
        params[:, 0] = torch.where(free_t[:, 0], torch.as_tensor(centre_x, device=device), params[:, 0])
        params[:, 1] = torch.where(free_t[:, 1], torch.as_tensor(centre_y, device=device), params[:, 1])
        rings = _cut_rings(seen, params[:, 0], params[:, 1], pixel_um=optics.pixel_um)
        params[:, 2:5] = _ring_search(rings, params, free_t, scale, model=model, window_um=z_window, start_index=start_index, settings=settings,
                                      steps=steps)
        params = _clamp(params, low, high)
        # a size search beyond the largest start (a size the network never saw) needs more partial waves
        model = model.with_terms(_scattered_terms(float(params[:, 3].max()), wavelength_um=optics.wavelength_um, medium_index=settings.medium_index))
        model_optics["terms"] = model.terms
    steps.check()
    # absorption stays at its start for the first step: free early, it lets a wrong
    # size–index valley mimic the right one (measured on noise-free spheres)
    early = free_t.clone()
    early[:, 5] = False
    # most iterations on every other pixel (a quarter of the work), the last ones on all
    coarse, picked = _every_other_pixel(fine)
    others = None if model.others is None else torch.gather(model.others, 2, picked[None].expand(model.others.shape[0], -1, -1))
    coarse_model = _Model(coarse, others, **model_optics)
    coarse_fit, _ = _levenberg_marquardt(coarse_model, params, early, low, high, scale=scale, settings=settings, iterations=1, steps=steps)
    fit_scale = _robust_scale(coarse.data - coarse_model(coarse_fit), coarse.mask)
    final, final_cost = _levenberg_marquardt(coarse_model, coarse_fit, free_t, low, high, scale=fit_scale, settings=settings, iterations=settings.iterations,
                                             steps=steps)
    profile = None
    if bool((free_t[:, 3] | free_t[:, 4]).any()):
        # the rings see the neighbours' holograms (at their guesses, or the previous round's fits) taken out of the data
        # (and their interference with this particle, at its fit), and the data divided by the
        # illumination's slope, which the rings' means do not fit (only its level)
        gain = model.illumination(final)
        data = fine.data
        if model.others is not None:
            data = data - gain * (model.sphere(final) - _Model(fine, None, **model_optics).sphere(final))
        level = final[:, _PHYSICAL : _PHYSICAL + 1]
        data = torch.where(fine.mask > 0, data * (level / torch.where(gain.abs() > 1e-12, gain, level)), fine.data)
        cleaned = _Patches(data, fine.mask, fine.x_um, fine.y_um, fine.u, fine.v, fine.shape)
        final, final_cost, profile = _valley_profile(cleaned, coarse_model, final, final_cost, free_t, low, high, fit_scale, pixel_um=optics.pixel_um,
                                                     start_index=start_index, settings=settings, steps=steps)
    final, _ = _levenberg_marquardt(model, final, free_t, low, high, scale=fit_scale, settings=settings, iterations=_FINE_ITERATIONS, steps=steps)
    prediction, jac = model.jacobian(final, free_t, envelope=True)
    steps.check()
    residual = (fine.data - prediction) * fine.mask
    sigma = _robust_scale(residual, fine.mask)
    weight, _ = _huber(residual, sigma, fine.mask, settings.huber)
    _, free_cost = _huber(alone_residual, scale, fine.mask, settings.huber)
    _, fit_cost = _huber(residual, scale, fine.mask, settings.huber)
    jac = jac * free_t.to(torch.float64)[:, None, :]
    normal = (jac.transpose(1, 2) * weight[:, None, :]) @ jac + torch.diag_embed((~free_t).to(torch.float64))
    inflation = _residual_inflation(residual, fine.mask, fine.shape)
    covariance = torch.linalg.pinv(normal) * (sigma**2 * inflation)[:, None, None]
    errors = torch.sqrt(torch.clamp(torch.diagonal(covariance, dim1=1, dim2=2), min=0.0)) * free_t
    spread = torch.full((count, 2), math.nan, dtype=torch.float64, device=device)
    if profile is not None:
        threshold = _interval_threshold(profile, inflation * (sigma / profile.scale) ** 2)
        spread = _profile_spread(profile, final[:, 3], final[:, 4], threshold) * free_t[:, 3:5].to(torch.float64)
    pixels = torch.clamp(fine.mask.sum(dim=1), min=1.0)
    residual_rms = torch.sqrt(torch.sum(residual**2, dim=1) / pixels) / torch.clamp(final[:, _PHYSICAL].abs(), min=1e-12)
    return {
        "params": final[:, :_PHYSICAL].cpu().numpy(),
        "errors": errors[:, :_PHYSICAL].cpu().numpy(),
        "spread": spread.cpu().numpy(),
        "gain": (free_cost - fit_cost).cpu().numpy(),
        "residual": residual_rms.cpu().numpy(),
        "ok": torch.isfinite(final).all(dim=1).cpu().numpy() & np.array([s[0] > 0 for s in fine.shape]) & ~_on_bound(final, free_t, low, high).cpu().numpy(),
    }


def _on_bound(params: torch.Tensor, free: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """(B,) whether a free physical parameter ended on its bound (zero absorption, a transparent sphere, excepted)."""
    p, lo, hi = params[:, :_PHYSICAL], low[:, :_PHYSICAL], high[:, :_PHYSICAL]
    tolerance = 1e-6 * (1.0 + p.abs())
    at = ((p - lo).abs() <= tolerance) | ((hi - p).abs() <= tolerance)
    at[:, 5] = (hi[:, 5] - p[:, 5]).abs() <= tolerance[:, 5]
    return (at & free[:, :_PHYSICAL]).any(dim=1)


def _neighbour_fields(all_params: np.ndarray, index: np.ndarray, *, present: np.ndarray, settings: RefineSettings, config: ExperimentConfig, terms: int,
                      device):
    """A function giving, for the patches of particles ``index``, the ``present`` other particles' terms near them (`_Model`'s ``others``; None when none has any)."""
    optics = config.optics
    pixel = optics.pixel_um if settings.pixel_integration else None
    reach = 1.5 * settings.patch_px * optics.pixel_um

    def others(patches: _Patches) -> torch.Tensor:
        out = torch.zeros((4,) + tuple(patches.data.shape), dtype=torch.complex128, device=device)
        crowded = False
        for row, i in enumerate(index):
            distance = np.hypot(all_params[:, 0] - all_params[i, 0], all_params[:, 1] - all_params[i, 1])
            # detections nearer than a quarter diameter laterally may be one particle twice (a
            # network's depth-shifted twin): neither is in the other's model (`_duplicates` settles them)
            same_line = distance < 0.25 * np.minimum(all_params[:, 3], all_params[i, 3])
            near = np.flatnonzero((distance < reach) & present & ~same_line)
            if near.size == 0:
                continue
            crowded = True
            p = torch.as_tensor(all_params[near], dtype=torch.float64, device=device)
            dx = patches.x_um[row : row + 1] - p[:, :1]
            dy = patches.y_um[row : row + 1] - p[:, 1:2]
            optics_kw = {"wavelength_um": optics.wavelength_um, "medium_index": settings.medium_index}
            fields = sphere_fields(dx, dy, p[:, 2], p[:, 3], p[:, 4], p[:, 5], terms=terms, **optics_kw)
            summed = tuple(f.sum(dim=0, keepdim=True) for f in fields)
            # the neighbours' own hologram: each one's interference with the plane wave through
            # its pixel transfer, plus the intensity of their summed field
            single = holograms_from_fields(fields, dx, dy, p[:, 2], pixel_um=pixel, **optics_kw)
            own_sq = sum(f.real**2 + f.imag**2 for f in fields)
            total = (single - 1.0 - own_sq).sum(dim=0) + sum(f.real**2 + f.imag**2 for f in summed)[0]
            out[0, row] = total * patches.mask[row]
            for axis in range(3):
                out[1 + axis, row] = summed[axis][0] * patches.mask[row]
        return out if crowded else None  # a batch of particles alone: no cross terms to carry

    return others


def _fit_task(image: np.ndarray, begin: np.ndarray, free: np.ndarray, anchor: np.ndarray, neighbours: np.ndarray, present: np.ndarray, index: np.ndarray,
              settings: RefineSettings, config: ExperimentConfig, terms: int, device: str, search: bool, steps: Steps | None = None) -> dict[str, np.ndarray]:
    """`_fit_batch` of the particles ``index`` with the ``present`` rows of ``neighbours`` in their models (a worker's task too)."""
    others = _neighbour_fields(neighbours, index, present=present, settings=settings, config=config, terms=terms, device=device)
    return _fit_batch(image, begin, free, others, anchor=anchor, search=search, settings=settings, config=config, terms=terms,
                      device=torch.device(device), steps=steps or Steps(1, progress=None, should_stop=None))


_HEARTBEAT_S = 0.5


def _run_tasks(tasks: list[tuple], pool, steps: Steps) -> list[dict[str, np.ndarray]]:
    """`_fit_task` of every task, in order: in this process, or in ``pool``'s workers (``steps`` repeats its count at the fits' checks once `_HEARTBEAT_S` has passed)."""
    if pool is None:
        outputs = []
        for task in tasks:
            steps.check()
            outputs.append(_fit_task(*task, steps=steps))
            steps.advance()
        return outputs
    import multiprocessing

    pending = [pool.apply_async(_fit_task, task) for task in tasks]
    outputs = []
    for job in pending:
        while True:
            steps.check()
            try:
                outputs.append(job.get(timeout=_HEARTBEAT_S))
                break
            except multiprocessing.TimeoutError:
                continue  # the fits go on: `check` reports the same count again
        steps.advance()
    return outputs


def _duplicates(result: dict[str, np.ndarray]) -> np.ndarray:
    """Fits that converged onto a particle another detection fitted better (a network's depth-shifted twin, a double click).

    Two fits are one particle when their centres lie within a quarter of the smaller
    diameter of each other laterally and within two diameters in depth (a fit stopped in a
    neighbouring depth minimum, 16 µm off, was measured); the one with the smaller residual
    keeps it.
    """
    params, ok = result["params"], result["ok"]
    order = np.argsort(np.where(ok, result["residual"], np.inf))
    duplicate = np.zeros(len(params), dtype=bool)
    for rank, i in enumerate(order):
        if not ok[i] or duplicate[i]:
            continue
        for j in order[rank + 1 :]:
            smaller = min(params[i, 3], params[j, 3])
            lateral = np.hypot(params[i, 0] - params[j, 0], params[i, 1] - params[j, 1])
            if ok[j] and not duplicate[j] and lateral < 0.25 * smaller and abs(params[i, 2] - params[j, 2]) < 2.0 * smaller:
                duplicate[j] = True
    return duplicate


def _kept(result: dict[str, np.ndarray], *, settings: RefineSettings) -> np.ndarray:
    """Detections kept: a fit that lowers the cost of the model without it by ``min_gain`` and is no other's duplicate; an unfitted one as it is."""
    return np.where(result["ok"], result["gain"] >= settings.min_gain, True) & ~_duplicates(result)


def refine_particles(
    hologram: np.ndarray,
    table,
    config: ExperimentConfig,
    *,
    fixed: Mapping[str, float] | None = None,
    settings: RefineSettings | None = None,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
):
    """Refine every particle of ``table`` by a Lorenz–Mie fit of its patch of ``hologram`` (module docstring).

    Parameters
    ----------
    hologram : (rows, cols) array
        Intensity, usually normalised by its background (unobstructed light ≈ 1); a smooth
        illumination is fitted per patch, so a raw frame works too.
    table : pandas.DataFrame or dict of arrays
        Starting guesses with at least ``x_um, y_um, z_um, diameter_um`` (docs/formats.md);
        ``index_contrast`` and ``absorption`` columns, when present, are starts too. Other
        columns are kept.
    config : ExperimentConfig
        Optics (wavelength, the effective pixel size: through an objective, the sensor
        pitch divided by the magnification) and the depth convention (``optics.medium_index``).
    fixed : dict, optional
        Parameters held at a value for every particle, e.g. ``{"index_contrast": 0.26}``
        (names: `FIT_PARAMETERS`; ``z_um`` in the table's convention).
    settings : RefineSettings, optional
    progress, should_stop
        See `napari_lbs._core.foundation._progress`; one step per batch and fitting round. Raises
        `Stopped` when asked.

    Returns
    -------
    pandas.DataFrame
        ``x_um, y_um, z_um, diameter_um`` (refined), then `REFINE_COLUMNS`, then the
        table's other columns. Detections whose fit does not beat the model without them
        (their neighbours and the illumination) are dropped, and so is a detection whose fit converged onto a particle another
        fitted better (`_duplicates`); a particle whose patch lies outside the hologram keeps its guesses
        with ``refined`` False. Errors are one standard deviation (µm; ``index_err`` for
        ``index_contrast``); ``fit_residual`` is the residual's rms relative to the
        fitted illumination; ``outside_training`` is True where the diameter lies outside
        the config's ``particles`` range.

    References
    ----------
    S.-H. Lee et al., Opt. Express 15, 18275 (2007); C. F. Bohren and D. R. Huffman (1983).
    """
    import pandas as pd

    settings = settings or RefineSettings()
    image = _check_hologram(hologram)
    frame = _check_table(table)
    fixed = _check_fixed(fixed)
    device = torch.device("cuda" if settings.device in ("cuda", "auto") and torch.cuda.is_available() else "cpu")
    if settings.device == "cuda" and device.type != "cuda":
        raise InputError("refine settings: device cuda requested but no CUDA GPU is available")
    optics = config.optics
    to_physical = settings.medium_index / optics.medium_index
    count = len(frame)
    start = np.empty((count, _PHYSICAL))
    start[:, 0] = frame["x_um"]
    start[:, 1] = frame["y_um"]
    start[:, 2] = frame["z_um"] * to_physical
    start[:, 3] = frame["diameter_um"]
    start[:, 4] = pd.to_numeric(frame["index_contrast"], errors="coerce").fillna(settings.index_contrast) if "index_contrast" in frame else settings.index_contrast
    start[:, 5] = pd.to_numeric(frame["absorption"], errors="coerce").fillna(settings.absorption) if "absorption" in frame else settings.absorption
    free = np.ones((count, _PHYSICAL), dtype=bool)
    for name, value in fixed.items():
        axis = FIT_PARAMETERS.index(name)
        start[:, axis] = value * to_physical if name == "z_um" else value
        free[:, axis] = False
    chunks = max(1, -(-count // settings.batch))
    steps = Steps(chunks * settings.rounds, progress=progress, should_stop=should_stop, heartbeat_s=_HEARTBEAT_S)
    current = start.copy()
    result: dict[str, np.ndarray] = {}
    reach = 1.5 * settings.patch_px * optics.pixel_um
    pool = None
    if settings.workers > 1 and device.type == "cpu" and chunks > 1:
        import multiprocessing

        # spawned, not forked: a forked child inherits torch's and the BLAS's thread pools mid-use
        pool = multiprocessing.get_context("spawn").Pool(min(settings.workers, chunks), initializer=size_threads, initargs=(1,))
    try:
        present = np.ones(count, dtype=bool)
        for round_index in range(settings.rounds if count else 0):
            if round_index == 0:
                todo = np.arange(count)
            else:  # only particles with a neighbour in reach change when their neighbours' fits join the model
                distance = np.hypot(current[:, None, 0] - current[None, :, 0], current[:, None, 1] - current[None, :, 1])
                crowded = ((distance < reach) & present[None, :]).sum(axis=1) > 1
                todo = np.flatnonzero(crowded & present & result["ok"])
            snapshot = current.copy()
            # enough for the largest sphere of the round's starts (a later round's fits may be larger
            # than any guess); a batch whose size search goes further sums more (`_scattered_terms`)
            terms = _scattered_terms(float(np.max(snapshot[:, 3])), wavelength_um=optics.wavelength_um, medium_index=settings.medium_index)
            parts = -(-todo.size // settings.batch)
            tasks = [(image, snapshot[index], free[index], start[index], snapshot, present, index, settings, config, terms, device.type, round_index == 0)
                     for index in (np.array_split(todo, parts) if parts else [])]
            outputs = _run_tasks(tasks, pool, steps)
            if outputs:
                part = {key: np.concatenate([o[key] for o in outputs]) for key in outputs[0]}
                if round_index == 0:
                    result = {key: np.empty_like(values) for key, values in part.items()}
                for key, values in part.items():
                    result[key][todo] = values
                current = np.where(result["ok"][:, None], result["params"], start)
                present = _kept(result, settings=settings)
            steps.advance(chunks - len(outputs))
    finally:
        if pool is not None:
            pool.terminate()  # a stop ends the running fits at once; nothing they wrote is kept
            pool.join()
    out = frame.copy()
    if count:
        keep = _kept(result, settings=settings)
        params, errors = result["params"], result["errors"].copy()
        # the diameter and index: the larger of the curvature's and the valley profile's standard deviation
        errors[:, 3:5] = np.maximum(errors[:, 3:5], np.nan_to_num(result["spread"], nan=0.0))
        refined = result["ok"]
        out["x_um"] = np.where(refined, params[:, 0], frame["x_um"])
        out["y_um"] = np.where(refined, params[:, 1], frame["y_um"])
        out["z_um"] = np.where(refined, params[:, 2] / to_physical, frame["z_um"])
        out["diameter_um"] = np.where(refined, params[:, 3], frame["diameter_um"])
        values = {
            "index_contrast": np.where(refined, params[:, 4], np.nan),
            "absorption": np.where(refined, params[:, 5], np.nan),
            "z_err_um": np.where(refined & free[:, 2], errors[:, 2] / to_physical, np.where(refined, 0.0, np.nan)),
            "diameter_err_um": np.where(refined, errors[:, 3], np.nan),
            "index_err": np.where(refined, errors[:, 4], np.nan),
            "fit_residual": np.where(refined, result["residual"], np.nan),
            "refined": refined.astype(bool),
        }
        low, high = config.particles.diameter_min_um, config.particles.diameter_max_um
        values["outside_training"] = (out["diameter_um"].to_numpy() < low) | (out["diameter_um"].to_numpy() > high)
        out = out.loc[:, [c for c in out.columns if c not in REFINE_COLUMNS]]
        for position, name in enumerate(REFINE_COLUMNS):
            out.insert(len(PARTICLE_COLUMNS) + position, name, values[name])
        out = out[keep].reset_index(drop=True)
    else:
        for position, name in enumerate(REFINE_COLUMNS):
            out.insert(len(PARTICLE_COLUMNS) + position, name, pd.Series(dtype=bool if name in ("refined", "outside_training") else float))
    return out
