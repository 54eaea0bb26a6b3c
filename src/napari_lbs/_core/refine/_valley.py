"""The valley profile about a fit: a restart in a deeper valley, and the diameter's and index's intervals.

**Valleys and ripple**: the phase delay through a transparent sphere is seen modulo 2π and
its hologram ripples with its size; the ring cost along the line of constant phase delay
and in the neighbouring valleys (`_ring_profile`) restarts the fit at a deeper point
(`valley_profile`), and bounds the diameter's and index's intervals (`interval_threshold`,
`profile_spread`): their uncertainties are at least half the profile's
two-standard-deviation interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from napari_lbs._core.foundation import Steps
from napari_lbs._core.refine._levenberg_marquardt import clamp, levenberg_marquardt
from napari_lbs._core.refine._model import Model
from napari_lbs._core.refine._patches import Patches
from napari_lbs._core.refine._rings import VALLEY_PRIOR, Rings, cut_rings, depth_prior, ring_costs, ring_depth_step, ring_dof
from napari_lbs._core.refine._settings import BOUNDS, RefineSettings

# the valley profile: size parameter k a along the line of constant phase delay, the
# neighbouring valleys, and the delay and depth offsets each point is minimised over
_PROFILE_SPAN = 4.0
_PROFILE_STEP = 0.25
_PROFILE_VALLEYS = (-1, 0, 1)
_PROFILE_DELAY = 0.03  # periods
_INTERVAL = 2.0  # half-variances: Δχ² = 4, the two-standard-deviation interval of one parameter


@dataclass
class _Profile:
    """The valley profile of each patch (`_ring_profile`)."""

    diameter_um: torch.Tensor  # (B, T) along the valley
    contrast: torch.Tensor  # (B, T, J) at each valley's minimum
    depth_um: torch.Tensor  # (B, T, J)
    cost: torch.Tensor  # (B, T, J) minimised over depth and delay, half-variances
    scale: torch.Tensor  # (B,) noise scale the costs are in
    dof: torch.Tensor  # (B,) ring means less the fitted parameters (c0, depth, delay, size)


def _ring_profile(rings: Rings, z_um: torch.Tensor, diameter_um: torch.Tensor, contrast: torch.Tensor, kappa: torch.Tensor, free: torch.Tensor,
                  scale: torch.Tensor, *, model: Model, depth_step_um: float) -> _Profile:
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
    diameters = torch.clamp(diameter_um[:, None] + both * t * (2.0 / k), min=BOUNDS["diameter_um"][0])  # (B, T)
    valleys = torch.tensor(_PROFILE_VALLEYS, dtype=torch.float64, device=device)
    shifts = torch.tensor((-1.0, 0.0, 1.0), dtype=torch.float64, device=device)
    delay = (diameter_um * contrast)[:, None, None, None] + index_free[:, :, None, None] * (valleys[:, None] + _PROFILE_DELAY * shifts) * wavelength  # (B,1,J,Q)
    contrasts = delay / diameters[:, :, None, None]  # (B, T, J, Q)
    spheres = torch.stack([diameters[:, :, None, None].expand_as(contrasts), contrasts, kappa[:, None, None, None].expand_as(contrasts)], dim=-1)
    sizes = contrasts.shape[1:]
    depths = torch.clamp(z_um[:, None] + shifts * depth_step_um, min=1.0)  # (B, 3)
    costs = ring_costs(rings, depths, spheres.reshape(count, -1, 3), scale, model=model)  # (B, 3 depths, T*J*Q)
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
    dof = ring_dof(rings)
    return _Profile(diameters, best_delay / diameters[:, :, None], z_um[:, None, None] + uu * depth_step_um, profile, scale, dof)


def interval_threshold(profile: _Profile, inflation: torch.Tensor) -> torch.Tensor:
    """(B,) cost above the profile's minimum (half-variances, its units) that bounds the two-standard-deviation interval.

    Δχ² = 4 times ``inflation`` (the residuals' correlation, and the fit's noise scale over
    the profile's, squared), plus the rings' excess χ² at the minimum (its cost less half
    its degrees of freedom): a model error ``δ`` of χ² ``|δ|²`` moves the minimum of a
    least-squares cost by at most that much, and what the best point leaves unexplained
    estimates it.
    """
    excess = torch.clamp(profile.cost.amin(dim=(1, 2)) - 0.5 * profile.dof, min=0.0)
    return _INTERVAL * inflation + excess


def profile_spread(profile: _Profile, diameter_um: torch.Tensor, contrast: torch.Tensor, threshold: torch.Tensor) -> torch.Tensor:
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


def valley_profile(fine: Patches, model: Model, final: torch.Tensor, cost: torch.Tensor, free: torch.Tensor, low: torch.Tensor, high: torch.Tensor,
                    scale: torch.Tensor, *, pixel_um: float, start_index: torch.Tensor, start_depth: torch.Tensor, depth_prior_um: float, settings: RefineSettings,
                    steps: Steps) -> tuple[torch.Tensor, torch.Tensor, _Profile]:
    """The valley profile (`_ring_profile`) about each fit, and the fit moved to its deepest point where that lies elsewhere.

    Where the profile's best point (the valley prior included) is another ripple minimum
    (more than a profile step away) or another valley, the fit is restarted there and the
    better of the two fits (robust cost plus the valley prior and `depth_prior` about
    ``start_depth``) is kept. ``model``: the
    patches' model on every other pixel, where the restarts run.
    """
    optics = model.optics
    count = final.shape[0]
    device = final.device
    k_m = 2.0 * math.pi * optics["medium_index"] / optics["wavelength_um"]
    rings = cut_rings(fine, final[:, 0], final[:, 1], pixel_um=pixel_um)
    depth_step = ring_depth_step(rings, final[:, 2], window_um=0.0, k=k_m, pixel_um=pixel_um) / 4.0
    profile = _ring_profile(rings, final[:, 2], final[:, 3], final[:, 4], final[:, 5], free, scale, model=model, depth_step_um=depth_step)
    period = lambda d: optics["wavelength_um"] / d
    prior = lambda n, d, z, rows: VALLEY_PRIOR * ((n - start_index[rows]) / period(d)) ** 2 * free[rows, 4].to(torch.float64) \
        + depth_prior(z, start_depth[rows], depth_prior_um) * free[rows, 2].to(torch.float64)
    ranked = profile.cost + VALLEY_PRIOR * ((profile.contrast - start_index[:, None, None]) / period(profile.diameter_um)[:, :, None]) ** 2 \
        * free[:, 4:5, None].to(torch.float64) + depth_prior(profile.depth_um, start_depth, depth_prior_um) * free[:, 2:3, None].to(torch.float64)
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
        refit, refit_cost = levenberg_marquardt(model.select(todo), clamp(moved[todo], low[todo], high[todo]), free[todo], low[todo], high[todo],
                                                 scale=scale[todo], settings=settings, iterations=settings.iterations, steps=steps)
        better = refit_cost + prior(refit[:, 4], refit[:, 3], refit[:, 2], todo) < cost[todo] + prior(final[todo, 4], final[todo, 3], final[todo, 2], todo)
        final = final.clone()
        cost = cost.clone()
        final[todo[better]] = refit[better]
        cost[todo[better]] = refit_cost[better]
    return final, cost, profile

