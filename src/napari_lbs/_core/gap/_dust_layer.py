"""Dust on a window beyond the volume: opaque grains fitted in what the frame's model leaves, in one plane far behind the particles.

Dust on the cell's far window (or on any optic upstream of the sample) is a second, static
in-line hologram multiplying the light: each grain throws a ring system whose spacing is set
by its distance ``z_d`` (the first Fresnel zone ``√(λ z_d)``), wide rings from a window a few
centimetres away that a Gaussian envelope or a straight fringe only partly absorb. Such a
grain is a particle like the sample's, of another size and far outside its depth range, so
it is found and fitted the same way (`find_particles`, `refine_particles`) in the frame
divided by its fitted model (the scene and the selected effects):

1. The search runs from 1.5 times the volume's farthest depth to where the first Fresnel zone
   reaches 60 pixels (the catalog's widest dust rings: 26 mm at 2.2 µm pixels and 660 nm),
   for grains of `GRAIN_PX` pixels across, in steps of four depths of focus ``d²/λ`` of the
   smallest (a larger grain's focus is deeper, and the fits' depth scan covers the rest).
2. Every find is fitted (size, index and absorption free) and kept where its fit lowers the
   cost by the refinement's own significance (`RefineSettings.min_gain`'s default).
3. A window is one plane: the kept grains within 5 % of their median depth are the **layer**.
   The frame's dust is named where the layer's grains lie on at least `LAYER_TILES` tiles
   of the held-out checkerboard (a sign test over the tiles, each holding a grain a vote: z
   = √tiles); a particle's misfit or a pair fitted as one, which also leaves rings, lies
   within the volume, and a control's residual holds no significant grain that far away.

On the development frames (independent Lorenz–Mie spheres at 1.8–4.8 mm, 512², 2.2 µm
pixels), dust of 10–60 µm on a window 10 mm away gave 9 significant grains, 8 of them in one
plane at 10.02 mm on 8 tiles; searched in the same way, two controls, an etalon and an
envelope gave none.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, ProgressCallback, Steps, StopCallback, WorkerPool
from napari_lbs._core.gap._detect import find_particles
from napari_lbs._core.gap._heldout import TileSplit
from napari_lbs._core.refine import RefineSettings, refine_particles

__all__ = ["GRAIN_PX", "LAYER_TILES", "dust_layer", "dust_record", "dust_search_range_um"]

GRAIN_PX = (4.0, 28.0)  # grains searched for, pixels across (9–62 µm at 2.2 µm: dust on windows is 5–100 µm)
LAYER_TILES = 3  # tiles holding a grain of the layer from which the frame's dust is named
_LAYER_SPREAD = 0.05  # a window's grains lie within this fraction of their median depth
_FAR_FACTOR = 1.5  # the search starts this far beyond the volume's farthest depth
_WIDEST_ZONE_PX = 60.0  # the catalog's widest dust rings: the first Fresnel zone in pixels
_MAX_GRAINS = 48  # the strongest finds fitted
_STEP_FOCI = 4.0  # the search's step in depths of focus d²/λ of the smallest grain (the fits' depth scan covers the rest)


def dust_search_range_um(config: ExperimentConfig) -> tuple[float, float] | None:
    """The depths (µm, the config's convention) searched for a dusty window, or None where the catalog's dust rings all lie within the volume's reach."""
    optics = config.optics
    wavelength = optics.wavelength_um / optics.medium_index  # distances in the config's convention
    near = _FAR_FACTOR * config.volume.z_max_um
    far = (_WIDEST_ZONE_PX * optics.pixel_um) ** 2 / wavelength
    return (near, far) if far > 2.0 * near else None


def dust_layer(ratio: np.ndarray, config: ExperimentConfig, split: TileSplit, *, settings: RefineSettings, pool: WorkerPool | None = None,
               progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> dict:
    """The grains of a dusty window in ``ratio`` (the frame over its fitted model), and whether the frame's dust is named (module docstring).

    Parameters
    ----------
    ratio : (rows, cols) array
        The frame divided by its model (the scene through the selected effects): 1 where
        the model explains it.
    config : ExperimentConfig
        Optics and the volume, beyond which the window is looked for.
    split : TileSplit
        The checkerboard whose tiles count the layer's grains.
    settings : RefineSettings
        The fits' settings (workers, device); their significance is the refinement's
        default ``min_gain``.
    pool, progress, should_stop
        As `refine_particles`; the search reports each depth it back-propagates to.

    Returns
    -------
    dict
        ``named`` (bool), ``z`` (√ of the tiles holding a layer grain), ``tiles`` (per tile,
        its layer grains: the verdict's bootstrap), ``grains`` (significant fits beyond the
        volume), ``in_layer``, ``depth_um`` (the layer's median depth), ``params`` (the
        catalog's ``dust_per_mpx`` in the frame, ``dust_zone_px`` = √(λ z)/pixel,
        ``dust_grain_px``: the median radius) with ``params_err`` (from the layer's own scatter:
        the depths' and radii's standard errors, Poisson's for the count) and ``table`` (the
        layer's grains, for their hologram), or ``searched`` False where the config leaves no depth to search.
    """
    import pandas as pd

    reach = dust_search_range_um(config)
    empty = {"named": False, "z": 0.0, "tiles": np.zeros(split.grid * split.grid), "grains": 0, "in_layer": 0, "depth_um": None, "params": {}, "params_err": {},
             "table": pd.DataFrame(columns=["x_um", "y_um", "z_um", "diameter_um"])}
    if reach is None:
        return {**empty, "searched": False}
    optics = config.optics
    wavelength = optics.wavelength_um / optics.medium_index
    pixel = optics.pixel_um
    step = _STEP_FOCI * (GRAIN_PX[0] * pixel) ** 2 / wavelength  # in the smallest grain's depths of focus
    far = dataclasses.replace(
        config, volume=dataclasses.replace(config.volume, z_min_um=reach[0], z_max_um=reach[1], z_step_um=step),
        particles=dataclasses.replace(config.particles, diameter_min_um=GRAIN_PX[0] * pixel, diameter_max_um=GRAIN_PX[1] * pixel))
    planes = Steps(len(far.volume.planes_um(step)), progress=progress, should_stop=should_stop)
    found = pd.DataFrame(find_particles(ratio, far, max_particles=_MAX_GRAINS, z_step_um=step, steps=planes))
    if found.empty:
        return {**empty, "searched": True}
    significant = dataclasses.replace(settings, min_gain=RefineSettings().min_gain, depth_window_um=0.1 * reach[1], rounds=1)
    fitted = refine_particles(ratio, found[["x_um", "y_um", "z_um", "diameter_um"]], far, settings=significant, progress=progress,
                              should_stop=should_stop, pool=pool)
    grains = fitted[fitted["refined"] & (fitted["z_um"] >= reach[0])].reset_index(drop=True)
    if grains.empty:
        return {**empty, "searched": True}
    log_depth = np.log(grains["z_um"].to_numpy(np.float64))
    layer = grains[np.abs(log_depth - np.median(log_depth)) <= _LAYER_SPREAD].reset_index(drop=True)
    rows = np.clip(np.round(layer["y_um"].to_numpy(np.float64) / pixel).astype(int), 0, ratio.shape[0] - 1)
    cols = np.clip(np.round(layer["x_um"].to_numpy(np.float64) / pixel).astype(int), 0, ratio.shape[1] - 1)
    tile = split.labels()[rows, cols]
    tiles = np.bincount(tile[tile >= 0], minlength=split.grid * split.grid).astype(np.float64)
    held = int(np.count_nonzero(tiles))
    depth = float(np.median(layer["z_um"]))
    count = len(layer)
    zone = float(np.sqrt(wavelength * depth) / pixel)
    radii = layer["diameter_um"].to_numpy(np.float64) / 2.0 / pixel
    # the layer's own scatter: the zone follows √z, so its relative error is half the depth's;
    # the density's is Poisson's
    depth_err = float(np.std(layer["z_um"], ddof=1) / np.sqrt(count)) if count > 1 else float("nan")
    return {
        "searched": True,
        "named": held >= LAYER_TILES,
        "z": float(np.sqrt(held)),
        "tiles": tiles,
        "grains": int(len(grains)),
        "in_layer": int(len(layer)),
        "depth_um": depth,
        "params": {"dust_per_mpx": float(count / (ratio.size / 1e6)), "dust_zone_px": zone, "dust_grain_px": float(np.median(radii))},
        "params_err": {"dust_per_mpx": float(np.sqrt(count) / (ratio.size / 1e6)), "dust_zone_px": 0.5 * zone * depth_err / depth,
                       "dust_grain_px": float(np.std(radii, ddof=1) / np.sqrt(count)) if count > 1 else float("nan")},
        "table": layer,
    }


def dust_record(dust: dict) -> dict:
    """The report's ``dust_layer`` of a `dust_layer` outcome: without the fitted table and the tile counts (its grains listed by place, depth, size and optics)."""
    record = {key: value for key, value in dust.items() if key not in ("table", "tiles")}
    if "tiles" in dust:
        record["tiles_with_grains"] = int(np.count_nonzero(dust["tiles"]))
    if "table" in dust:
        record["layer_grains"] = dust["table"][["x_um", "y_um", "z_um", "diameter_um", "index_contrast", "absorption"]].to_dict("list") if len(dust["table"]) else {}
    return record
