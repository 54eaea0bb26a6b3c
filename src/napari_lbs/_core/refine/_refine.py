"""Every detection refined by a Lorenz–Mie fit of its hologram patch.

For each particle of a table of starting guesses (the network's, a user's clicks, another
tool's CSV) the patch of the hologram around it is fitted with the exact Lorenz–Mie
hologram of a sphere (`napari_lbs._core.physics._lorenz_mie`, Lee et al. 2007) for its position,
depth, diameter, index contrast ``n_p - n_m`` and absorption ``κ`` (the imaginary part of
its index), times a smooth illumination ``c0 + c1 u + c2 v`` over the patch (the beam's
envelope; ``u, v`` the patch coordinates in -1 … 1). All particles are fitted at once,
batched in torch.

1. **Patch** (`_patches`): a square of at most ``patch_px`` pixels, and no wider than the disc inside
   which the fringes are sampled (their frequency below the pixel's Nyquist limit).
2. **Searches on ring profiles** (`_rings`): about the patch's centre of symmetry, the ring means of
   ``I`` and ``I cos2φ`` (of the data less the neighbours' hologram, 5.) are exact functions of the sphere's radial profiles
   (`azimuthal_mean_holograms`), so the depth is scanned over ``±depth_window_um`` (steps
   that move the outermost fringe by one radian), the size and index on a grid at the best
   depths, and each start followed down its valley, at the cost of rings, not pixels.
3. **Fit** (`_model`, `_levenberg_marquardt`): Levenberg–Marquardt on Huber-weighted residuals (the noise scale from the
   residuals' median absolute deviation), on every other pixel and then on all; the
   Jacobian by finite differences of the differentiable forward model, every perturbation
   in one batch.
4. **Valleys and ripple** (`_valley`): the phase delay through a transparent sphere is seen modulo 2π
   and its hologram ripples with its size; the ring cost along the line of constant phase
   delay and in the neighbouring valleys (`_valley`) restarts the fit at a deeper
   point, and bounds the diameter's and index's intervals (`interval_threshold`).
5. **Neighbours** (`_batches`): each patch's model holds the summed fields of the other detections in
   reach, fixed at their guesses (in later rounds, at the previous round's fits); two
   detections a quarter diameter apart laterally may be one particle twice and stay out of
   each other's model.
6. **False detections and twins** (`_duplicates`, `_kept`): a particle whose best fit does not lower the robust cost
   of the model without it (its neighbours and the illumination) by ``min_gain`` noise
   variances is dropped, and so is one that converged onto a particle another detection
   fitted better.
7. **Uncertainties** (`_batches`, `_valley`): ``σ² (JᵀWJ)⁻¹`` at the optimum (Gauss–Newton), ``σ`` the residuals'
   scale, inflated by the residuals' pixel-to-pixel correlation (what model error and
   neighbours leave is not white); for the diameter and index, at least half the valley
   profile's two-standard-deviation interval.

Depths in the table keep the config's convention (``optics.medium_index``: with the
default 1, air-equivalent distances); the scattering happens in the sample's medium,
``RefineSettings.medium_index`` (water by default), so the physical depth is
``z_um * medium_index / optics.medium_index``.

The steps' modules, each of the ``napari_lbs._core.refine`` package: `_settings` (the
parameters, their bounds, `RefineSettings`), `_patches` (inputs checked, patches cut),
`_model` (the forward model and its Jacobian), `_levenberg_marquardt` (robust least
squares), `_rings` (the searches on ring profiles), `_valley` (the valley profile),
`_batches` (one batch's fit, its neighbours, the pool of workers); this module runs the
rounds over the batches and writes the table.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from napari_lbs._core.foundation import PARTICLE_COLUMNS, ExperimentConfig, InputError, ProgressCallback, Steps, StopCallback, WorkerPool
from napari_lbs._core.refine._batches import HEARTBEAT_S, FitTask, run_tasks
from napari_lbs._core.refine._model import scattered_terms
from napari_lbs._core.refine._patches import check_fixed, check_hologram, check_table, check_valid
from napari_lbs._core.refine._settings import FIT_PARAMETERS, PHYSICAL, RefineSettings

__all__ = ["FIT_PARAMETERS", "REFINE_COLUMNS", "RefineSettings", "refine_particles"]

REFINE_COLUMNS = ("index_contrast", "absorption", "z_err_um", "diameter_err_um", "index_err", "fit_residual", "refined", "outside_training")

def _duplicates(result: dict[str, np.ndarray]) -> np.ndarray:
    """Fits that converged onto a particle another detection fitted better (a network's depth-shifted twin, a double click).

    Two fits are one particle when their centres lie within a quarter of the smaller
    diameter of each other laterally, at any depth: such detections stay out of each other's
    model (`_batches`), so each explains the same fringes and a second one is never judged
    against the first. Twins were measured a neighbouring depth minimum away: 16 µm for a
    lensless 25 µm sphere, 4–12 µm (2–8 diameters) for a microscope's 1.5–3 µm ones. The one
    with the smaller residual keeps it.
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
            if ok[j] and not duplicate[j] and lateral < 0.25 * smaller:
                duplicate[j] = True
    return duplicate


def fit_batch(settings: RefineSettings, device: torch.device) -> int:
    """Particles fitted together: ``settings.batch`` on the CPU, at least `DEVICE_BATCH` on a GPU.

    A batch costs the same number of kernel launches and waits for the device whatever its
    size, and a GPU runs one batch at a time, so there the particles go in as few batches as
    fit; on the CPU, small batches split over worker processes keep every core busy.
    """
    return settings.batch if device.type == "cpu" else max(settings.batch, DEVICE_BATCH)


# Particles per batch on a GPU: 128 patches of 128² pixels with the Jacobian's perturbed copies
# hold a few GiB of complex128 fields.
DEVICE_BATCH = 128


# size parameter k a (k the medium's wavenumber, a the radius) below which a fit that fails with its index
# free is retried with it held: 1.6 µm across at 660 nm in water, a lensless sample's 20 µm spheres far above
_SMALL_SIZE_PARAMETER = 10.0


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
    valid: np.ndarray | None = None,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
    pool: WorkerPool | None = None,
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
    valid : (rows, cols) bool array, optional
        The pixels the fits compare; the others are left out of every fit. A saturated
        camera's clipped pixels are the use: the model knows no clipping, and a clipped focal
        spot pulls the depth and size (`unsaturated_pixels`). Default: every pixel.
    progress, should_stop
        See `napari_lbs._core.foundation._progress`; one step per batch and fitting round. Raises
        `Stopped` when asked.
    pool : WorkerPool, optional
        Processes to fit the batches in, kept open by the caller across several calls, so
        that they start once (`diagnose_scene` fits three or four tables in a row). Default:
        ``settings.workers`` processes started for this call and ended after it. Ignored on a
        GPU.

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

    if not isinstance(config, ExperimentConfig):
        raise InputError(f"config: expected an ExperimentConfig (load_config), got {type(config).__name__}")
    if settings is not None and not isinstance(settings, RefineSettings):
        raise InputError(f"settings: expected RefineSettings, got {type(settings).__name__}")
    settings = settings or RefineSettings()
    image = check_hologram(hologram)
    valid = check_valid(valid, image.shape)
    frame = check_table(table)
    fixed = check_fixed(fixed)
    device = torch.device("cuda" if settings.device in ("cuda", "auto") and torch.cuda.is_available() else "cpu")
    if settings.device == "cuda" and device.type != "cuda":
        raise InputError("refine settings: device cuda requested but no CUDA GPU is available")
    optics = config.optics
    to_physical = settings.medium_index / optics.medium_index
    count = len(frame)
    start = np.empty((count, PHYSICAL))
    start[:, 0] = frame["x_um"]
    start[:, 1] = frame["y_um"]
    start[:, 2] = frame["z_um"] * to_physical
    start[:, 3] = frame["diameter_um"]
    start[:, 4] = pd.to_numeric(frame["index_contrast"], errors="coerce").fillna(settings.index_contrast) if "index_contrast" in frame else settings.index_contrast
    start[:, 5] = pd.to_numeric(frame["absorption"], errors="coerce").fillna(settings.absorption) if "absorption" in frame else settings.absorption
    free = np.ones((count, PHYSICAL), dtype=bool)
    for name, value in fixed.items():
        axis = FIT_PARAMETERS.index(name)
        start[:, axis] = value * to_physical if name == "z_um" else value
        free[:, axis] = False
    batch = fit_batch(settings, device)
    chunks = max(1, -(-count // batch))
    steps = Steps(chunks * (settings.rounds + 1), progress=progress, should_stop=should_stop, heartbeat_s=HEARTBEAT_S)
    current = start.copy()
    result: dict[str, np.ndarray] = {}
    reach = 1.5 * settings.patch_px * optics.pixel_um
    # workers on the CPU only: on a GPU the batches share the one device
    own_pool = pool is None or device.type != "cpu"
    if own_pool:
        pool = WorkerPool(settings.workers if device.type == "cpu" else 1)
    try:
        present = np.ones(count, dtype=bool)

        def fit(todo: np.ndarray, starts: np.ndarray, fitted: np.ndarray, *, search: bool) -> dict[str, np.ndarray] | None:
            """The fits of rows ``todo`` from ``starts`` (every row's), ``fitted`` (every row's free parameters), the others at ``current``; one step per batch."""
            # enough for the largest sphere of the current fits, the neighbours (a later round's fits may
            # be larger than any guess); a batch whose size search goes further sums more (`scattered_terms`)
            terms = scattered_terms(float(np.max(current[:, 3])), wavelength_um=optics.wavelength_um, medium_index=settings.medium_index)
            parts = -(-todo.size // batch)
            tasks = [FitTask(image=image, start=starts[index], free=fitted[index], anchor=start[index], neighbours=current, present=present, index=index,
                             settings=settings, config=config, terms=terms, device=device.type, search=search, valid=valid)
                     for index in (np.array_split(todo, parts) if parts else [])]
            outputs = run_tasks(tasks, pool, steps)
            steps.advance(chunks - len(outputs))
            return {key: np.concatenate([o[key] for o in outputs]) for key in outputs[0]} if outputs else None

        for round_index in range(settings.rounds if count else 0):
            if round_index == 0:
                todo = np.arange(count)
            else:  # only particles with a neighbour in reach change when their neighbours' fits join the model
                distance = np.hypot(current[:, None, 0] - current[None, :, 0], current[:, None, 1] - current[None, :, 1])
                crowded = ((distance < reach) & present[None, :]).sum(axis=1) > 1
                todo = np.flatnonzero(crowded & present & result["ok"])
            part = fit(todo, current.copy(), free, search=round_index == 0)
            if part is not None:
                if round_index == 0:
                    result = {key: np.empty_like(values) for key, values in part.items()}
                for key, values in part.items():
                    result[key][todo] = values
                current = np.where(result["ok"][:, None], result["params"], start)
                present = _kept(result, settings=settings)
        if count:
            # a small sphere's fit that found no sphere inside the model's range (a parameter on its
            # bound) is tried once more with the index and absorption held at their starts: below a
            # size parameter k a of `_SMALL_SIZE_PARAMETER` no ripple of its hologram tells its size
            # from its index (only its polarisability shows), and the free index runs to a bound
            size_parameter = np.pi * settings.medium_index / optics.wavelength_um * start[:, 3]
            retry = np.flatnonzero(~result["ok"] & free[:, 4] & (size_parameter <= _SMALL_SIZE_PARAMETER))
            held = free.copy()
            held[:, 4:6] = False
            part = fit(retry, start, held, search=True)
            if part is not None:
                converged = retry[part["ok"]]
                for key, values in part.items():
                    result[key][converged] = values[part["ok"]]
                free[converged, 4:6] = False
        else:
            steps.advance(steps.total - steps.done)  # nothing to fit: every round done
    finally:
        if own_pool:
            pool.close()  # a stop or a failure has already ended the running fits; nothing they did is kept
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
