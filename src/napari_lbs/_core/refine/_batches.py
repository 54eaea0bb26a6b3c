"""One batch's fit, the neighbours in its model, and the batches run in a `WorkerPool` (in this process or in workers).

A batch is fitted from its patches: the searches (`napari_lbs._core.refine._rings`), the
robust fit on every other pixel and then on all (`levenberg_marquardt`), the valley profile
(`napari_lbs._core.refine._valley`) and the uncertainties, ``σ² (JᵀWJ)⁻¹`` at the optimum
(Gauss–Newton), ``σ`` the residuals' scale, inflated by their correlation.

**Neighbours**: each patch's model holds the summed fields of the other detections in
reach (1.5 patches; every other detection where the pitch samples every propagating angle,
`samples_every_angle`), fixed at their guesses (in later rounds, at the previous round's fits); two
detections a quarter diameter apart laterally may be one particle twice and stay out of
each other's model. **False detections**: the fit's ``gain`` is how much it lowers the
robust cost of the model without the particle (its neighbours and the illumination).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from napari_lbs._core.foundation import CHECK_S, ExperimentConfig, Steps, WorkerPool
from napari_lbs._core.physics import fields_from_profiles, holograms_from_fields, radial_profiles
from napari_lbs._core.refine._levenberg_marquardt import clamp, flat_model, huber, levenberg_marquardt, residual_inflation, robust_scale
from napari_lbs._core.refine._model import Model, scattered_terms
from napari_lbs._core.refine._patches import Patches, cut_patches, every_other_pixel, patch_edge, samples_every_angle
from napari_lbs._core.refine._rings import cut_rings, ring_search, symmetric_centres
from napari_lbs._core.refine._settings import BOUNDS, NUISANCE, PHYSICAL, RefineSettings
from napari_lbs._core.refine._valley import interval_threshold, profile_spread, valley_profile

# One Levenberg–Marquardt step on every pixel after the fit on every other pixel: from the
# quarter-data optimum (within ~2σ of the full one) a Gauss–Newton step lands on the full
# optimum, whose curvature the reported uncertainties describe.
_FINE_ITERATIONS = 1


def _fit_batch(image: np.ndarray, start: np.ndarray, free: np.ndarray, others_of, *, anchor: np.ndarray, search: bool, settings: RefineSettings,
               config: ExperimentConfig, terms: int, device, steps: Steps, valid: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Fit one batch of particles from (B, 6) physical starting parameters; arrays per particle.

    Positions and depths are bounded about ``anchor`` (B, 6), the table's guesses, in every
    round: a later round starts from the earlier fit but may not wander further from the
    detection than the first could. A fit that ends on a bound of a free parameter (other than
    zero absorption) found no minimum inside the model's range: not ``ok``.

    With ``search``: symmetric centre and ring-profile searches (`ring_search`) on the
    data less the neighbours' hologram, then the fit. Without: the fit from ``start``. Either
    way the valley profile about the fit (`valley_profile`) may restart it in a deeper valley
    and widens the diameter's and index's uncertainties (``spread``). ``gain``: how much the
    particle lowers the robust cost of the model without it (its neighbours and the
    illumination). ``valid``: the pixels compared (`cut_patches`).
    """
    optics = config.optics
    count = start.shape[0]
    edges = np.array([patch_edge(z, settings=settings, wavelength_um=optics.wavelength_um, pixel_um=optics.pixel_um) for z in start[:, 2]])
    model_optics = {"wavelength_um": optics.wavelength_um, "medium_index": settings.medium_index,
                    "pixel_um": optics.pixel_um if settings.pixel_integration else None, "terms": terms}
    fine = cut_patches(image, start[:, 0], start[:, 1], edges, pixel_um=optics.pixel_um, device=device, valid=valid)
    model = Model(fine, others_of(fine) if others_of is not None else None, **model_optics)
    steps.check()
    params = torch.zeros((count, PHYSICAL + NUISANCE), dtype=torch.float64, device=device)
    params[:, :PHYSICAL] = torch.as_tensor(start, dtype=torch.float64, device=device)
    params[:, PHYSICAL] = torch.sum(fine.data * fine.mask, dim=1) / torch.clamp(fine.mask.sum(dim=1), min=1.0)
    free_t = torch.ones((count, PHYSICAL + NUISANCE), dtype=torch.bool, device=device)
    free_t[:, :PHYSICAL] = torch.as_tensor(free, device=device)
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
        low[:, axis], high[:, axis] = BOUNDS[name]
    flat = flat_model(fine)
    scale = flat[1]
    alone_residual, _, alone_light = flat if model.others is None else flat_model(fine, model.others)  # the model without this particle
    start_index = torch.as_tensor(anchor[:, 4], dtype=torch.float64, device=device)
    start_depth = torch.as_tensor(anchor[:, 2], dtype=torch.float64, device=device)
    depth_prior_um = settings.depth_prior_um * settings.medium_index / optics.medium_index
    if search:
        # the rings of the data less the neighbours' hologram: theirs would pull the depth scan
        seen = fine if model.others is None else Patches(torch.where(fine.mask > 0, alone_light + alone_residual, fine.data), fine.mask, fine.x_um,
                                                           fine.y_um, fine.u, fine.v, fine.shape)
        centre_x, centre_y = symmetric_centres(alone_residual, seen, start[:, 0], start[:, 1], pixel_um=optics.pixel_um)
        params[:, 0] = torch.where(free_t[:, 0], torch.as_tensor(centre_x, device=device), params[:, 0])
        params[:, 1] = torch.where(free_t[:, 1], torch.as_tensor(centre_y, device=device), params[:, 1])
        rings = cut_rings(seen, params[:, 0], params[:, 1], pixel_um=optics.pixel_um)
        params[:, 2:5] = ring_search(rings, params, free_t, scale, model=model, window_um=z_window, start_index=start_index, start_depth=start_depth,
                                      depth_prior_um=depth_prior_um, settings=settings, steps=steps)
        params = clamp(params, low, high)
        # a size search beyond the largest start (a size the network never saw) needs more partial waves
        model = model.with_terms(scattered_terms(float(params[:, 3].max()), wavelength_um=optics.wavelength_um, medium_index=settings.medium_index))
        model_optics["terms"] = model.terms
    steps.check()
    # absorption stays at its start for the first step: free early, it lets a wrong
    # size–index valley mimic the right one (measured on noise-free spheres)
    early = free_t.clone()
    early[:, 5] = False
    # most iterations on every other pixel (a quarter of the work), the last ones on all
    coarse, picked = every_other_pixel(fine)
    others = None if model.others is None else torch.gather(model.others, 2, picked[None].expand(model.others.shape[0], -1, -1))
    coarse_model = Model(coarse, others, **model_optics)
    coarse_fit, _ = levenberg_marquardt(coarse_model, params, early, low, high, scale=scale, settings=settings, iterations=1, steps=steps)
    fit_scale = robust_scale(coarse.data - coarse_model(coarse_fit), coarse.mask)
    final, final_cost = levenberg_marquardt(coarse_model, coarse_fit, free_t, low, high, scale=fit_scale, settings=settings, iterations=settings.iterations,
                                             steps=steps)
    profile = None
    if bool((free_t[:, 3] | free_t[:, 4]).any()):
        # the rings see the neighbours' holograms (at their guesses, or the previous round's fits) taken out of the data
        # (and their interference with this particle, at its fit), and the data divided by the
        # illumination's slope, which the rings' means do not fit (only its level)
        gain = model.illumination(final)
        data = fine.data
        if model.others is not None:
            data = data - gain * (model.sphere(final) - Model(fine, None, **model_optics).sphere(final))
        level = final[:, PHYSICAL : PHYSICAL + 1]
        data = torch.where(fine.mask > 0, data * (level / torch.where(gain.abs() > 1e-12, gain, level)), fine.data)
        cleaned = Patches(data, fine.mask, fine.x_um, fine.y_um, fine.u, fine.v, fine.shape)
        final, final_cost, profile = valley_profile(cleaned, coarse_model, final, final_cost, free_t, low, high, fit_scale, pixel_um=optics.pixel_um,
                                                     start_index=start_index, start_depth=start_depth, depth_prior_um=depth_prior_um, settings=settings,
                                                     steps=steps)
    final, _ = levenberg_marquardt(model, final, free_t, low, high, scale=fit_scale, settings=settings, iterations=_FINE_ITERATIONS, steps=steps)
    prediction, jac = model.jacobian(final, free_t, envelope=True)
    steps.check()
    residual = (fine.data - prediction) * fine.mask
    sigma = robust_scale(residual, fine.mask)
    weight, _ = huber(residual, sigma, fine.mask, settings.huber)
    _, free_cost = huber(alone_residual, scale, fine.mask, settings.huber)
    _, fit_cost = huber(residual, scale, fine.mask, settings.huber)
    jac = jac * free_t.to(torch.float64)[:, None, :]
    normal = (jac.transpose(1, 2) * weight[:, None, :]) @ jac + torch.diag_embed((~free_t).to(torch.float64))
    # a fit whose neighbourhood holds no finite hologram (a sphere of 0.05 µm, the size bound,
    # whose secants reach below zero) has no curvature: not a fit, and no error bars
    curved = torch.isfinite(normal).all(dim=2).all(dim=1)
    normal = torch.where(curved[:, None, None], normal, torch.eye(normal.shape[1], dtype=normal.dtype, device=device))
    inflation = residual_inflation(residual, fine.mask, fine.shape)
    covariance = torch.linalg.pinv(normal) * torch.where(curved, sigma**2 * inflation, math.nan)[:, None, None]
    errors = torch.sqrt(torch.clamp(torch.diagonal(covariance, dim1=1, dim2=2), min=0.0)) * free_t
    spread = torch.full((count, 2), math.nan, dtype=torch.float64, device=device)
    if profile is not None:
        threshold = interval_threshold(profile, inflation * (sigma / profile.scale) ** 2)
        spread = profile_spread(profile, final[:, 3], final[:, 4], threshold) * free_t[:, 3:5].to(torch.float64)
    pixels = torch.clamp(fine.mask.sum(dim=1), min=1.0)
    residual_rms = torch.sqrt(torch.sum(residual**2, dim=1) / pixels) / torch.clamp(final[:, PHYSICAL].abs(), min=1e-12)
    return {
        "params": final[:, :PHYSICAL].cpu().numpy(),
        "errors": errors[:, :PHYSICAL].cpu().numpy(),
        "spread": spread.cpu().numpy(),
        "gain": (free_cost - fit_cost).cpu().numpy(),
        "residual": residual_rms.cpu().numpy(),
        "ok": (torch.isfinite(final).all(dim=1) & curved).cpu().numpy() & np.array([s[0] > 0 for s in fine.shape]) & ~_on_bound(final, free_t, low, high).cpu().numpy(),
    }


def _on_bound(params: torch.Tensor, free: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """(B,) whether a free physical parameter ended on its bound (zero absorption, a transparent sphere, excepted)."""
    p, lo, hi = params[:, :PHYSICAL], low[:, :PHYSICAL], high[:, :PHYSICAL]
    tolerance = 1e-6 * (1.0 + p.abs())
    at = ((p - lo).abs() <= tolerance) | ((hi - p).abs() <= tolerance)
    at[:, 5] = (hi[:, 5] - p[:, 5]).abs() <= tolerance[:, 5]
    return (at & free[:, :PHYSICAL]).any(dim=1)


def _neighbour_fields(all_params: np.ndarray, index: np.ndarray, *, present: np.ndarray, settings: RefineSettings, config: ExperimentConfig, terms: int,
                      device):
    """A function giving, for the patches of particles ``index``, the ``present`` other particles' terms near them (`Model`'s ``others``; None when none has any)."""
    optics = config.optics
    pixel = optics.pixel_um if settings.pixel_integration else None
    # a neighbour's fringes are sampled out to its Nyquist disc, about 1.5 patches at a
    # lensless pitch; at a pitch that samples every angle they reach the whole frame
    fine = samples_every_angle(wavelength_um=optics.wavelength_um, medium_index=settings.medium_index, pixel_um=optics.pixel_um)
    reach = math.inf if fine else 1.5 * settings.patch_px * optics.pixel_um

    def others(patches: Patches) -> torch.Tensor | None:
        rows, near = [], []
        for row, i in enumerate(index):
            distance = np.hypot(all_params[:, 0] - all_params[i, 0], all_params[:, 1] - all_params[i, 1])
            # detections nearer than a quarter diameter laterally may be one particle twice (a
            # network's depth-shifted twin): neither is in the other's model (`_duplicates` settles them)
            same_line = distance < 0.25 * np.minimum(all_params[:, 3], all_params[i, 3])
            found = np.flatnonzero((distance < reach) & present & ~same_line)
            rows.append(np.full(found.size, row))
            near.append(found)
        rows, near = np.concatenate(rows).astype(np.int64), np.concatenate(near).astype(np.int64)
        if rows.size == 0:
            return None  # a batch of particles alone: no cross terms to carry
        # every (patch, neighbour) pair in one batch of fields, summed per patch; each neighbour's
        # radial profiles once, however many patches it reaches (at a pitch that samples every
        # angle every particle reaches every patch), interpolated to each pair's points
        row_t = torch.as_tensor(rows, device=device)
        p = torch.as_tensor(all_params[near], dtype=torch.float64, device=device)
        dx = patches.x_um[row_t] - p[:, :1]
        dy = patches.y_um[row_t] - p[:, 1:2]
        optics_kw = {"wavelength_um": optics.wavelength_um, "medium_index": settings.medium_index}
        distinct, pair_of = np.unique(near, return_inverse=True)
        q = torch.as_tensor(all_params[distinct], dtype=torch.float64, device=device)
        profiles, step = radial_profiles(q[:, 2], q[:, 3], q[:, 4], q[:, 5], rho_max_um=float(torch.sqrt(dx**2 + dy**2).max()), terms=terms, **optics_kw)
        pair_t = torch.as_tensor(pair_of.reshape(-1), device=device)
        fields = fields_from_profiles(profiles[:, pair_t], step[pair_t], dx, dy, p[:, 2], **optics_kw)
        shape = tuple(patches.data.shape)
        summed = [torch.zeros(shape, dtype=torch.complex128, device=device).index_add_(0, row_t, f) for f in fields]
        # the neighbours' own hologram: each one's interference with the plane wave through
        # its pixel transfer, plus the intensity of their summed field
        single = holograms_from_fields(fields, dx, dy, p[:, 2], pixel_um=pixel, **optics_kw)
        own_sq = sum(f.real**2 + f.imag**2 for f in fields)
        total = torch.zeros(shape, dtype=torch.float64, device=device).index_add_(0, row_t, single - 1.0 - own_sq) + sum(f.real**2 + f.imag**2 for f in summed)
        return torch.stack([total.to(torch.complex128)] + summed) * patches.mask[None]

    return others


@dataclass(frozen=True, eq=False)
class FitTask:
    """One batch's fit: what `run_tasks` hands to this process or to a worker (pickled whole).

    Attributes
    ----------
    image : (rows, cols) float64 array
        The checked hologram.
    start : (B, 6) array
        The batch's physical starting parameters (`FIT_PARAMETERS`, depths in the medium, µm).
    free : (B, 6) bool array
        Which of them are fitted.
    anchor : (B, 6) array
        The table's guesses, about which positions and depths are bounded in every round.
    neighbours : (N, 6) array
        Every particle's current parameters (its guess, or the previous round's fit).
    present : (N,) bool array
        Which of them are kept, so in the batch's models.
    index : (B,) int array
        The batch's rows of ``neighbours``.
    settings : RefineSettings
    config : ExperimentConfig
    terms : int
        Partial waves of the models (more where a size search goes beyond them).
    device : str
        Torch device type (``cpu``, ``cuda``).
    search : bool
        The centre and ring-profile searches before the fit (the first round).
    valid : (rows, cols) bool array, optional
        The pixels the fits compare (`refine_particles`); default all.
    """

    image: np.ndarray
    start: np.ndarray
    free: np.ndarray
    anchor: np.ndarray
    neighbours: np.ndarray
    present: np.ndarray
    index: np.ndarray
    settings: RefineSettings
    config: ExperimentConfig
    terms: int
    device: str
    search: bool
    valid: np.ndarray | None = None


def _fit_task(task: FitTask, steps: Steps | None = None) -> dict[str, np.ndarray]:
    """`_fit_batch` of the particles ``task.index`` with the ``present`` rows of ``neighbours`` in their models (a worker's task too)."""
    others = _neighbour_fields(task.neighbours, task.index, present=task.present, settings=task.settings, config=task.config, terms=task.terms,
                               device=task.device)
    return _fit_batch(task.image, task.start, task.free, others, anchor=task.anchor, search=task.search, settings=task.settings, config=task.config,
                      terms=task.terms, device=torch.device(task.device), steps=steps or Steps(1, progress=None, should_stop=None), valid=task.valid)


# Steps' heartbeat while a batch fits in this process: as often as the pool checks its workers.
HEARTBEAT_S = CHECK_S


def run_tasks(tasks: list[FitTask], pool: WorkerPool, steps: Steps) -> list[dict[str, np.ndarray]]:
    """`_fit_task` of every task, in order, in ``pool`` (in this process the fits check ``steps`` themselves)."""
    return pool.run(_fit_task, tasks, steps=steps, share_steps=True)
