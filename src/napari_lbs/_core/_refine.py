"""Every detection refined by a Lorenz–Mie fit of its hologram patch.

For each particle of a table of starting guesses (the network's, a user's clicks, another
tool's CSV) the patch of the hologram around it is fitted with the exact Lorenz–Mie
hologram of a sphere (`napari_lbs._core._lorenz_mie`, Lee et al. 2007) for its position,
depth, diameter, index contrast ``n_p - n_m`` and absorption ``κ`` (the imaginary part of
its index), times a smooth illumination ``c0 + c1 u + c2 v`` over the patch (the beam's
envelope; ``u, v`` the patch coordinates in -1 … 1). All particles are fitted at once,
batched in torch.

1. **Patch**: a square of at most ``patch_px`` pixels, and no wider than the disc inside
   which the fringes are sampled (their frequency below the pixel's Nyquist limit).
2. **Searches**: the depth is scanned over ``±depth_window_um`` around the guess, in steps
   that move the patch's outermost fringe by one radian, so a depth wrong by 300 µm is a
   fit choice; at the best depths the size and index are scanned; the best starts are fitted
   coarsely (every other pixel).
3. **Fit**: Levenberg–Marquardt on Huber-weighted residuals (the noise scale from the
   residuals' median absolute deviation); the Jacobian by finite differences of the
   differentiable forward model, every perturbation in one batch.
4. **Valleys and ripple**: the phase delay through a transparent sphere is seen modulo 2π
   and its hologram ripples with its size; the neighbouring size–index valleys are fitted
   and compared (`_choose_valley`), and the valley itself is scanned (`_escape_ripple`).
5. **Neighbours**: after a first round, each patch with other particles in reach is fitted
   again with their summed fields (fixed at their first-round values) in its model.
6. **False detections and twins**: a particle whose best fit does not lower the robust cost
   of the particle-free model (the illumination alone) by ``min_gain`` noise variances is
   dropped, and so is one that converged onto a particle another detection fitted better.
7. **Uncertainties**: ``σ² (JᵀWJ)⁻¹`` at the optimum (Gauss–Newton), ``σ`` the residuals'
   scale, inflated by the residuals' pixel-to-pixel correlation (what model error and
   neighbours leave is not white).

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

from napari_lbs._core._config import ExperimentConfig
from napari_lbs._core._io import PARTICLE_COLUMNS, InputError
from napari_lbs._core._lorenz_mie import fields_from_profiles, holograms_from_fields, radial_profiles, radial_step, sphere_fields, term_count
from napari_lbs._core._progress import ProgressCallback, Steps, StopCallback

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
        Fitting rounds; from the second on, neighbours' holograms are in each model.
    huber : float
        Residuals beyond this many noise scales get a Huber weight below 1.
    min_gain : float
        Lowering of the robust cost (in noise variances) that the fit must achieve over
        the particle-free model to keep a detection.
    pixel_integration : bool
        Model each pixel integrating its area (True) or point-sampled (pylorenzmie's).
    batch : int
        Particles fitted together (memory).
    device : str
        ``cpu``, ``cuda`` or ``auto``.
    """

    medium_index: float = 1.33
    index_contrast: float = 0.26
    absorption: float = 0.0
    depth_window_um: float = 400.0
    depth_candidates: int = 3
    patch_px: int = 128
    iterations: int = 8
    rounds: int = 2
    huber: float = 2.5
    min_gain: float = 50.0
    pixel_integration: bool = True
    batch: int = 32
    device: str = "cpu"

    def __post_init__(self) -> None:
        for name in ("medium_index", "depth_window_um", "huber", "min_gain"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise InputError(f"refine settings: {name} must be a finite number >= 0, got {value!r}")
        for name in ("depth_candidates", "patch_px", "iterations", "rounds", "batch"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise InputError(f"refine settings: {name} must be a positive integer, got {value!r}")
        if self.patch_px < 16:
            raise InputError(f"refine settings: patch_px must be at least 16, got {self.patch_px}")


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
    return fixed


def _patch_edge(z_um: float, *, settings: RefineSettings, wavelength_um: float, pixel_um: float) -> int:
    """Patch edge (px): the disc of fringes below the Nyquist frequency, at most ``patch_px``."""
    sin_nyquist = min(wavelength_um / settings.medium_index / (2.0 * pixel_um), 0.99)
    radius_px = z_um * sin_nyquist / math.sqrt(1.0 - sin_nyquist**2) / pixel_um
    return int(max(16, min(settings.patch_px, 2 * round(radius_px))))


def _cut_patches(image: np.ndarray, x_um: np.ndarray, y_um: np.ndarray, edges: np.ndarray, *, pixel_um: float, device, stride: int = 1) -> _Patches:
    rows, cols = image.shape
    length = int((-(-int(max(edges)) // stride)) ** 2)
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
        block = image[r_lo:r_hi:stride, c_lo:c_hi:stride]
        rr, cc = np.mgrid[r_lo:r_hi:stride, c_lo:c_hi:stride]
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


_FIT_SAMPLES_PER_LOBE = 6  # radial samples per scattering lobe in the fit (see radial_step)
# Finite-difference steps of the Jacobian (x, y, z in µm, diameter µm, index, κ): far below
# every parameter's precision and far above round-off in complex128.
_JACOBIAN_STEPS = (1e-4, 1e-4, 1e-3, 1e-5, 1e-7, 1e-7)


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

    def sphere(self, params: torch.Tensor, *, step: torch.Tensor | None = None, lateral: tuple[float, float] | None = None,
               lateral_rows: int = 0) -> torch.Tensor:
        """Holograms (B, P); with ``lateral``, after them those of the first ``lateral_rows`` rows moved by ``dx`` then by ``dy`` (µm), from the same profiles."""
        x, y, z, d, dn, kappa = params[:, :_PHYSICAL].unbind(-1)
        p = self.patches
        copies = params.shape[0] // p.x_um.shape[0]  # stacked perturbations of the same patches
        dx, dy = p.x_um.repeat(copies, 1) - x[:, None], p.y_um.repeat(copies, 1) - y[:, None]
        rho_max = float(torch.sqrt(dx**2 + dy**2).max()) + (math.hypot(*lateral) if lateral else 0.0)
        if step is None:
            step = radial_step(z, d, samples_per_lobe=_FIT_SAMPLES_PER_LOBE, **self.optics)
        profiles, step = radial_profiles(z, d, dn, kappa, rho_max_um=rho_max, terms=self.terms, radial_step_um=step, **self.optics)
        if lateral:
            n = lateral_rows
            dx = torch.cat([dx, dx[:n] - lateral[0], dx[:n]], dim=0)
            dy = torch.cat([dy, dy[:n], dy[:n] - lateral[1]], dim=0)
            z = torch.cat([z, z[:n], z[:n]])
            step = torch.cat([step, step[:n], step[:n]])
            profiles = torch.cat([profiles, profiles[:, :n], profiles[:, :n]], dim=1)
        fields = fields_from_profiles(profiles, step, dx, dy, z, **self.optics)
        own = holograms_from_fields(fields, dx, dy, z, pixel_um=self.pixel_um, **self.optics)
        if self.others is None:
            return own
        others = self.others.repeat(1, copies, 1)
        if lateral:
            others = torch.cat([others, others[:, :lateral_rows], others[:, :lateral_rows]], dim=1)
        cross = sum(f * o.conj() for f, o in zip(fields, others[1:], strict=True))
        return own + others[0].real + 2.0 * cross.real

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

        The physical columns are finite differences of the differentiable model with every
        perturbation stacked in one batch: its partial-wave recurrences then run once for
        all of them (forward-mode differentiation pays their per-operation overhead once
        per parameter: measured 60 times slower), and the lateral shifts reuse the
        unshifted radial profiles.

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
        lateral = (_JACOBIAN_STEPS[0], _JACOBIAN_STEPS[1])
        # one radial grid per particle for all its perturbations: the differences see the model, not a moved grid
        step = radial_step(params[:, 2], params[:, 3], samples_per_lobe=_FIT_SAMPLES_PER_LOBE, **self.optics).repeat(1 + len(signs))
        holograms = self.sphere(stacked, step=step, lateral=lateral, lateral_rows=count)
        rows = 1 + len(signs)
        unshifted = holograms[: rows * count].reshape(rows, count, -1)
        base = unshifted[0]
        gain = self.illumination(params)
        columns = [torch.zeros_like(base)] * _PHYSICAL
        for axis in (0, 1):
            if bool(free[:, axis].any()):
                shifted = holograms[(rows + axis) * count : (rows + axis + 1) * count]
                # the pattern moves with the particle: a shift of the points by -h is one of the particle by +h
                columns[axis] = (shifted - unshifted[0]) * (gain / lateral[axis])
        for slot, (k, sign) in enumerate(signs, start=1):
            if sign < 0:
                continue
            lower = unshifted[1 + len(depth_like) + central.index(k)] if k in central else unshifted[0]
            width = steps[k] * (2.0 if k in central else 1.0)
            columns[k] = (unshifted[slot] - lower) * (gain / width[:, None])
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
    patches that rejected it only.
    """
    data, mask = model.patches.data, model.patches.mask
    count = params.shape[0]
    params = params.clone()
    damping = torch.full((count,), 1e-3, dtype=torch.float64, device=params.device)
    freef = free.to(torch.float64)
    cost = torch.zeros(count, dtype=torch.float64, device=params.device)
    for _ in range(iterations):
        if steps is not None:
            steps.check()
        prediction, jac = model.jacobian(params, free)
        residual = data - prediction
        weight, cost = _huber(residual, scale, mask, settings.huber)
        jac = jac * freef[:, None, :]
        jtw = jac.transpose(1, 2) * weight[:, None, :]
        normal = jtw @ jac
        gradient = (jtw @ residual[:, :, None])[:, :, 0]
        diagonal = torch.diagonal(normal, dim1=1, dim2=2).clamp(min=1e-30)
        # fixed parameters: a unit diagonal and no gradient keep them where they are
        normal = normal + torch.diag_embed(torch.where(free, torch.zeros_like(diagonal), torch.ones_like(diagonal)))
        rows = torch.arange(count, device=params.device)
        for _attempt in range(4):
            system = normal[rows] + torch.diag_embed(damping[rows, None] * torch.where(free[rows], diagonal[rows], torch.zeros_like(diagonal[rows])))
            delta = torch.linalg.solve(system, gradient[rows, :, None])[:, :, 0]
            trial = _clamp(params[rows] + delta * freef[rows], low[rows], high[rows])
            subset = model if rows.numel() == count else model.select(rows)
            _, trial_cost = _huber(data[rows] - subset(trial), scale[rows], mask[rows], settings.huber)
            better = trial_cost < cost[rows]
            params[rows[better]] = trial[better]
            cost[rows[better]] = trial_cost[better]
            damping[rows] = torch.where(better, damping[rows] * 0.3, damping[rows] * 10.0).clamp(1e-7, 1e7)
            rows = rows[~better]
            if rows.numel() == 0:
                break
    return params, cost


def _scan(model: _Model, trials: torch.Tensor, scale: torch.Tensor, *, settings: RefineSettings) -> torch.Tensor:
    """Robust cost (B, T) of trial physical parameters (B, T, 6), each with its best illumination (least squares on c0, c1, c2)."""
    patches = model.patches
    count, total = trials.shape[:2]
    chunk = max(1, int(2e6 // max(1, count * patches.data.shape[1])))
    mask = patches.mask
    costs = []
    for first in range(0, total, chunk):
        part = trials[:, first : first + chunk]
        n = part.shape[1]
        params = torch.zeros((n * count, _PHYSICAL + _NUISANCE), dtype=torch.float64, device=trials.device)
        params[:, :_PHYSICAL] = part.transpose(0, 1).reshape(n * count, _PHYSICAL)
        others = None if model.others is None else model.others.repeat(1, n, 1)
        batch = _Model(_expand(patches, n, interleave=False), others, pixel_um=model.pixel_um, terms=model.terms, **model.optics)
        spheres = batch.sphere(params).reshape(n, count, -1)
        basis = torch.stack([spheres, spheres * patches.u, spheres * patches.v], dim=-1) * mask[:, :, None]
        solution = torch.linalg.lstsq(basis, (patches.data * mask)[None, :, :, None].expand(n, -1, -1, -1)).solution
        residual = (patches.data - (basis @ solution)[..., 0]).reshape(n * count, -1)
        costs.append(_huber(residual, scale.repeat(n), mask.repeat(n, 1), settings.huber)[1].reshape(n, count))
    return torch.cat(costs, dim=0).T


def _best(costs: torch.Tensor, count: int, *, local: bool) -> torch.Tensor:
    """Indices (B, count) of the lowest costs, local minima along the last axis first when ``local``."""
    ranked = costs
    if local:
        padded = torch.nn.functional.pad(costs[:, None, :], (1, 1), mode="replicate")[:, 0]
        minima = (costs <= padded[:, :-2]) & (costs <= padded[:, 2:])
        ranked = torch.where(minima, costs, costs + costs.abs().max() + 1.0)
    return torch.argsort(ranked, dim=1)[:, : min(count, costs.shape[1])]


def _depth_offsets(model: _Model, params: torch.Tensor, *, window_um: float, pixel_um: float) -> torch.Tensor:
    """Depth offsets (µm) of the scan: steps that move the patch's outermost fringe (phase k ρ²/2z) by one radian at the nearest depth."""
    patches = model.patches
    k = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    rho_max = float(torch.max(torch.sqrt((patches.x_um - params[:, :1]) ** 2 + (patches.y_um - params[:, 1:2]) ** 2) * patches.mask))
    nearest = float(torch.clamp(params[:, 2] - window_um, min=0.1 * window_um).min())
    step = max(2.0 * nearest**2 / (k * max(rho_max, pixel_um) ** 2), 0.5 * pixel_um)
    return torch.arange(-window_um, window_um + 0.5 * step, step, dtype=torch.float64, device=params.device)


# The size-index scan: diameters around the start, and for each the index contrasts whose
# phase delay k0 d Δn steps through one period on each side of the start's in thirds (the
# valley itself is chosen after the fit, `_choose_valley`).
_SCAN_DIAMETER_STEPS = (-2, -1, 0, 1, 2)  # in units of _SCAN_DIAMETER_UM
_SCAN_DIAMETER_UM = 0.8
_SCAN_DELAY_STEPS = tuple(j / 3 for j in range(-3, 4))


def _search_starts(model: _Model, params: torch.Tensor, free: torch.Tensor, scale: torch.Tensor, *, window_um: float, pixel_um: float,
                   settings: RefineSettings) -> torch.Tensor:
    """Starting points (B, K, 9): the best depths of a depth scan, then the best sizes and indices of a size–index scan at each."""
    count = params.shape[0]
    physical = params[:, :_PHYSICAL]
    starts = physical[:, None, :]
    if bool(free[:, 2].any()):
        offsets = _depth_offsets(model, params, window_um=window_um, pixel_um=pixel_um)
        trials = physical[:, None, :].repeat(1, offsets.numel(), 1)
        trials[:, :, 2] = torch.where(free[:, 2:3], torch.clamp(physical[:, 2:3] + offsets, min=1.0), physical[:, 2:3])
        pick = _best(_scan(model, trials, scale, settings=settings), settings.depth_candidates, local=True)
        starts = torch.gather(trials, 1, pick[:, :, None].expand(-1, -1, _PHYSICAL))
    if bool(free[:, 3].any() or free[:, 4].any()):
        wavelength = model.optics["wavelength_um"]
        d_steps = torch.tensor(_SCAN_DIAMETER_STEPS, dtype=torch.float64, device=params.device) * _SCAN_DIAMETER_UM
        delays = torch.tensor(_SCAN_DELAY_STEPS, dtype=torch.float64, device=params.device) * wavelength
        diameters = torch.where(free[:, 3:4], torch.clamp(physical[:, 3:4] + d_steps, min=_BOUNDS["diameter_um"][0]), physical[:, 3:4])  # (B, D)
        delay0 = physical[:, 3:4] * physical[:, 4:5]
        contrasts = torch.where(free[:, 4:5, None], (delay0[:, :, None] + delays) / diameters[:, :, None], physical[:, 4:5, None])  # (B, D, N)
        grown = starts[:, :, None, None, :].repeat(1, 1, d_steps.numel(), delays.numel(), 1)
        grown[..., 3] = diameters[:, None, :, None]
        grown[..., 4] = contrasts[:, None, :, :]
        grown = grown.reshape(count, -1, _PHYSICAL)
        pick = _best(_scan(model, grown, scale, settings=settings), settings.depth_candidates, local=False)
        starts = torch.gather(grown, 1, pick[:, :, None].expand(-1, -1, _PHYSICAL))
    out = params[:, None, :].repeat(1, starts.shape[1], 1)
    out[:, :, :_PHYSICAL] = starts
    return out


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


_VALLEY_PRIOR = 16.0  # robust-cost units (half noise variances) per squared phase-delay period from the starting index
_RIPPLE_SPAN = 6.0  # the valley scan's reach on each side, in size parameter k a (±0.95 µm in diameter in water at 660 nm)
_RIPPLE_STARTS = 3  # its best minima refitted


_VALLEYS = (-1, 1)  # neighbouring size–index valleys, in phase-delay periods


def _choose_valley(model: _Model, params: torch.Tensor, free: torch.Tensor, low: torch.Tensor, high: torch.Tensor, *, start_index: torch.Tensor,
                   scale: torch.Tensor, settings: RefineSettings, steps: Steps) -> torch.Tensor:
    """The converged fit in the best of the size–index valleys around ``params`` (Δn = j λ/d).

    The phase delay through a transparent sphere, ``k0 d Δn``, is seen modulo 2π: valleys one
    period apart differ only in light refracted beyond the patch. Each valley's fit is
    converged before they are compared; where their costs are within a few noise
    variances (`_VALLEY_PRIOR` per period²) the valley nearest the starting index wins.
    """
    count = params.shape[0]
    period = model.optics["wavelength_um"] / params[:, 3]
    shifts = torch.tensor((0,) + _VALLEYS, dtype=torch.float64, device=params.device)
    k = shifts.numel()
    candidates = params[:, None, :].repeat(1, k, 1)
    candidates[:, :, 4] = params[:, 4:5] + torch.where(free[:, 4:5], period[:, None] * shifts, torch.zeros_like(period[:, None]))
    grow = lambda t: t.repeat_interleave(k, dim=0)
    wide = _Model(_expand(model.patches, k), _grow_others(model.others, k), pixel_um=model.pixel_um, terms=model.terms, **model.optics)
    fitted, cost = _levenberg_marquardt(wide, candidates.reshape(count * k, -1), grow(free), grow(low), grow(high), scale=grow(scale), settings=settings,
                                        iterations=max(3, settings.iterations // 2), steps=steps)
    valleys = (fitted[:, 4] - grow(start_index)) / (model.optics["wavelength_um"] / fitted[:, 3])
    cost = cost + _VALLEY_PRIOR * valleys**2
    best = torch.argmin(cost.reshape(count, k), dim=1)
    return fitted[torch.arange(count, device=params.device) * k + best]


def _escape_ripple(model: _Model, params: torch.Tensor, free: torch.Tensor, low: torch.Tensor, high: torch.Tensor, *, scale: torch.Tensor,
                   settings: RefineSettings, steps: Steps) -> torch.Tensor:
    """The best of fits restarted along the valley of constant phase delay ``d (n_p - n_m)``.

    A transparent sphere's hologram ripples with its size (morphology-dependent resonances):
    along the valley where the phase delay through the sphere is constant the loss has
    minima ``Δ(k a) ≈ 0.2`` apart, deep enough to stop a fit far from the deepest (measured:
    0.3 µm at d = 18 µm). The valley is scanned (``Δ(k a) = 0.25`` steps over ±`_RIPPLE_SPAN`
    in k a, each with its best illumination), and the best minima, refitted briefly, compete
    with the fit.
    """
    count = params.shape[0]
    k_m = 2.0 * math.pi * model.optics["medium_index"] / model.optics["wavelength_um"]
    shifts = torch.arange(-_RIPPLE_SPAN, _RIPPLE_SPAN + 1e-9, 0.25, dtype=torch.float64, device=params.device) * (2.0 / k_m)
    both = (free[:, 3] & free[:, 4]).to(torch.float64)
    trials = params[:, None, :_PHYSICAL].repeat(1, shifts.numel(), 1)
    diameters = torch.clamp(params[:, 3:4] + shifts[None, :] * both[:, None], min=_BOUNDS["diameter_um"][0])
    trials[:, :, 4] = params[:, 4:5] * params[:, 3:4] / diameters
    trials[:, :, 3] = diameters
    pick = _best(_scan(model, trials, scale, settings=settings), _RIPPLE_STARTS, local=True)
    starts = params[:, None, :].repeat(1, pick.shape[1], 1)
    starts[:, :, :_PHYSICAL] = torch.gather(trials, 1, pick[:, :, None].expand(-1, -1, _PHYSICAL))
    k = pick.shape[1] + 1
    candidates = torch.cat([params[:, None, :], starts], dim=1).reshape(count * k, -1)
    grow = lambda t: t.repeat_interleave(k, dim=0)
    wide = _Model(_expand(model.patches, k), _grow_others(model.others, k), pixel_um=model.pixel_um, terms=model.terms, **model.optics)
    fitted, cost = _levenberg_marquardt(wide, candidates, grow(free), grow(low), grow(high), scale=grow(scale), settings=settings, iterations=3, steps=steps)
    best = torch.argmin(cost.reshape(count, k), dim=1)
    return fitted[torch.arange(count, device=params.device) * k + best]


def _grow_others(others: torch.Tensor | None, k: int) -> torch.Tensor | None:
    """Neighbours' terms (4, B, P) repeated ``k`` times per patch, as `_expand` repeats the patches."""
    return None if others is None else others.repeat_interleave(k, dim=1)


def _expand(patches: _Patches, k: int, *, interleave: bool = True) -> _Patches:
    """Each patch repeated ``k`` times in a row (one per candidate start), or the whole batch ``k`` times."""
    grow = (lambda t: t.repeat_interleave(k, dim=0)) if interleave else (lambda t: t.repeat(k, 1))
    shapes = [s for s in patches.shape for _ in range(k)] if interleave else patches.shape * k
    return _Patches(*(grow(getattr(patches, f.name)) for f in fields(_Patches) if f.name != "shape"), shape=shapes)


def _flat_model(patches: _Patches) -> tuple[torch.Tensor, torch.Tensor]:
    """Residual of the particle-free model (illumination alone, least squares) and its noise scale."""
    basis = torch.stack([patches.mask, patches.u * patches.mask, patches.v * patches.mask], dim=-1)
    solution = torch.linalg.lstsq(basis, (patches.data * patches.mask)[:, :, None]).solution
    residual = (patches.data - (basis @ solution)[:, :, 0]) * patches.mask
    return residual, _robust_scale(residual, patches.mask)


def _fit_batch(image: np.ndarray, start: np.ndarray, free: np.ndarray, others_of, *, search: bool, settings: RefineSettings, config: ExperimentConfig,
               terms: int, device, steps: Steps) -> dict[str, np.ndarray]:
    """Fit one batch of particles from (B, 6) physical starting parameters; arrays per particle.

    With ``search``: depth scan and index-contrast candidates, each fitted coarsely on every
    other pixel, then the best fitted on every pixel. Without: the fine fit from ``start``.
    """
    optics = config.optics
    count = start.shape[0]
    edges = np.array([_patch_edge(z, settings=settings, wavelength_um=optics.wavelength_um, pixel_um=optics.pixel_um) for z in start[:, 2]])
    model_optics = {"wavelength_um": optics.wavelength_um, "medium_index": settings.medium_index,
                    "pixel_um": optics.pixel_um if settings.pixel_integration else None, "terms": terms}
    fine = _cut_patches(image, start[:, 0], start[:, 1], edges, pixel_um=optics.pixel_um, device=device)
    model = _Model(fine, others_of(fine) if others_of is not None else None, **model_optics)
    params = torch.zeros((count, _PHYSICAL + _NUISANCE), dtype=torch.float64, device=device)
    params[:, :_PHYSICAL] = torch.as_tensor(start, dtype=torch.float64, device=device)
    params[:, _PHYSICAL] = torch.sum(fine.data * fine.mask, dim=1) / torch.clamp(fine.mask.sum(dim=1), min=1.0)
    free_t = torch.ones((count, _PHYSICAL + _NUISANCE), dtype=torch.bool, device=device)
    free_t[:, :_PHYSICAL] = torch.as_tensor(free, device=device)
    low = torch.full_like(params, -math.inf)
    high = torch.full_like(params, math.inf)
    half = torch.as_tensor(edges, dtype=torch.float64, device=device) * optics.pixel_um / 4.0
    for axis in (0, 1):
        low[:, axis] = params[:, axis] - half
        high[:, axis] = params[:, axis] + half
    z_window = settings.depth_window_um * settings.medium_index / optics.medium_index
    low[:, 2] = torch.clamp(params[:, 2] - 1.5 * z_window, min=1.0)
    high[:, 2] = params[:, 2] + 1.5 * z_window
    for axis, name in ((3, "diameter_um"), (4, "index_contrast"), (5, "absorption")):
        low[:, axis], high[:, axis] = _BOUNDS[name]
    flat_residual, scale = _flat_model(fine)
    if search:
        coarse = _cut_patches(image, start[:, 0], start[:, 1], edges, pixel_um=optics.pixel_um, device=device, stride=2)
        coarse_model = _Model(coarse, others_of(coarse) if others_of is not None else None, **model_optics)
        _, coarse_scale = _flat_model(coarse)
        candidates = _search_starts(coarse_model, params, free_t, coarse_scale, window_um=z_window, pixel_um=optics.pixel_um, settings=settings)
        steps.check()
        k = candidates.shape[1]
        wide_model = _Model(_expand(coarse, k), _grow_others(coarse_model.others, k), **model_optics)
        grow = lambda t: t.repeat_interleave(k, dim=0)
        # absorption stays at its start while the valley is chosen: free, it lets a wrong
        # size–index valley mimic the right one (measured on noise-free spheres)
        searching = free_t.clone()
        searching[:, 5] = False
        fitted, cost = _levenberg_marquardt(wide_model, candidates.reshape(count * k, -1), grow(searching), grow(low), grow(high), scale=grow(coarse_scale),
                                            settings=settings, iterations=max(2, settings.iterations // 3), steps=steps)
        # Valleys one phase delay apart (Δn = λ/d) differ only in light refracted outside
        # the patch: where the data cannot tell them apart (cost within a few noise
        # variances) the valley nearest the starting index wins.
        valleys = (fitted[:, 4] - grow(params[:, 4])) / (optics.wavelength_um / grow(params[:, 3]))
        cost = cost + _VALLEY_PRIOR * valleys**2 * grow(free_t[:, 4].to(torch.float64))
        best = torch.argmin(cost.reshape(count, k), dim=1)
        params = fitted[torch.arange(count, device=device) * k + best]
    steps.check()
    coarse_fit, _ = _levenberg_marquardt(model, params, free_t, low, high, scale=scale, settings=settings, iterations=2, steps=steps)
    fit_scale = _robust_scale(fine.data - model(coarse_fit), fine.mask)
    final, _ = _levenberg_marquardt(model, coarse_fit, free_t, low, high, scale=fit_scale, settings=settings, iterations=settings.iterations, steps=steps)
    if search and bool(free_t[:, 4].any()):
        final = _choose_valley(model, final, free_t, low, high, start_index=torch.as_tensor(start[:, 4], device=device), scale=fit_scale, settings=settings,
                               steps=steps)
    if search and bool((free_t[:, 3] & free_t[:, 4]).any()):
        final = _escape_ripple(model, final, free_t, low, high, scale=fit_scale, settings=settings, steps=steps)
    prediction, jac = model.jacobian(final, free_t, envelope=True)
    residual = (fine.data - prediction) * fine.mask
    sigma = _robust_scale(residual, fine.mask)
    weight, _ = _huber(residual, sigma, fine.mask, settings.huber)
    _, free_cost = _huber(flat_residual, scale, fine.mask, settings.huber)
    _, fit_cost = _huber(residual, scale, fine.mask, settings.huber)
    jac = jac * free_t.to(torch.float64)[:, None, :]
    normal = (jac.transpose(1, 2) * weight[:, None, :]) @ jac + torch.diag_embed((~free_t).to(torch.float64))
    inflation = _residual_inflation(residual, fine.mask, fine.shape)
    covariance = torch.linalg.pinv(normal) * (sigma**2 * inflation)[:, None, None]
    errors = torch.sqrt(torch.clamp(torch.diagonal(covariance, dim1=1, dim2=2), min=0.0)) * free_t
    pixels = torch.clamp(fine.mask.sum(dim=1), min=1.0)
    residual_rms = torch.sqrt(torch.sum(residual**2, dim=1) / pixels) / torch.clamp(final[:, _PHYSICAL].abs(), min=1e-12)
    return {
        "params": final[:, :_PHYSICAL].cpu().numpy(),
        "errors": errors[:, :_PHYSICAL].cpu().numpy(),
        "gain": (free_cost - fit_cost).cpu().numpy(),
        "residual": residual_rms.cpu().numpy(),
        "ok": torch.isfinite(final).all(dim=1).cpu().numpy() & np.array([s[0] > 0 for s in fine.shape]),
    }


def _neighbour_fields(all_params: np.ndarray, index: np.ndarray, *, settings: RefineSettings, config: ExperimentConfig, terms: int, device):
    """A function giving, for the patches of particles ``index``, the other particles' terms near them (`_Model`'s ``others``)."""
    optics = config.optics
    pixel = optics.pixel_um if settings.pixel_integration else None
    reach = 1.5 * settings.patch_px * optics.pixel_um

    def others(patches: _Patches) -> torch.Tensor:
        out = torch.zeros((4,) + tuple(patches.data.shape), dtype=torch.complex128, device=device)
        for row, i in enumerate(index):
            distance = np.hypot(all_params[:, 0] - all_params[i, 0], all_params[:, 1] - all_params[i, 1])
            near = np.flatnonzero((distance < reach) & (np.arange(len(all_params)) != i))
            if near.size == 0:
                continue
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
        return out

    return others


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
        Starting guesses with at least ``x_um, y_um, z_um, diameter_um`` (CONTRACT.md);
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
        See `napari_lbs._core._progress`; one step per batch and fitting round. Raises
        `Stopped` when asked.

    Returns
    -------
    pandas.DataFrame
        ``x_um, y_um, z_um, diameter_um`` (refined), then `REFINE_COLUMNS`, then the
        table's other columns. Detections whose fit does not beat the particle-free model
        are dropped, and so is a detection whose fit converged onto a particle another
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
    steps = Steps(chunks * settings.rounds, progress=progress, should_stop=should_stop)
    current = start.copy()
    result: dict[str, np.ndarray] = {}
    size = 2.0 * math.pi * settings.medium_index / optics.wavelength_um * (np.max(start[:, 3]) if count else 1.0) / 2.0
    terms = term_count(size * 1.15, (settings.medium_index + 0.6) / settings.medium_index)
    reach = 1.5 * settings.patch_px * optics.pixel_um
    for round_index in range(settings.rounds if count else 0):
        if round_index == 0:
            todo = np.arange(count)
        else:  # only particles with a neighbour in reach change when neighbours join the model
            distance = np.hypot(current[:, None, 0] - current[None, :, 0], current[:, None, 1] - current[None, :, 1])
            todo = np.flatnonzero(((distance < reach).sum(axis=1) > 1) & result["ok"])
        snapshot = current.copy()
        outputs = []
        for first in range(0, todo.size, settings.batch):
            index = todo[first : first + settings.batch]
            steps.check()
            others = _neighbour_fields(snapshot, index, settings=settings, config=config, terms=terms, device=device) if round_index > 0 else None
            begin = snapshot[index] if round_index > 0 else start[index]
            outputs.append(_fit_batch(image, begin, free[index], others, search=round_index == 0, settings=settings, config=config, terms=terms,
                                      device=device, steps=steps))
            steps.advance()
        if outputs:
            part = {key: np.concatenate([o[key] for o in outputs]) for key in outputs[0]}
            if round_index == 0:
                result = part
            else:
                for key, values in part.items():
                    result[key][todo] = values
            current = np.where(result["ok"][:, None], result["params"], start)
        steps.advance(chunks - len(outputs))
    out = frame.copy()
    if count:
        keep = np.where(result["ok"], result["gain"] >= settings.min_gain, True) & ~_duplicates(result)
        params, errors = result["params"], result["errors"]
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
