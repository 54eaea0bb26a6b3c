"""Dust on a window outside the volume: grains fitted in what the frame's model leaves and among the scene's particles, in one plane.

Dust on a window (the cell's far wall, an optic upstream, the sensor's cover glass) is a
second, static in-line hologram multiplying the light: each grain throws a ring system whose
spacing is set by its distance ``z_d`` (the first Fresnel zone ``√(λ z_d)``), wide rings from a
window a few centimetres away that a Gaussian envelope or a straight fringe only partly
absorb. Such a grain is a particle like the sample's, of another size and outside its depth
range, so it is found and fitted the same way (`find_particles`, `refine_particles`):

1. Where the model leaves structure, the frame divided by its fitted model (the scene and the
   selected effects) is searched on both sides of the volume (`dust_search_ranges_um`): from
   where the first Fresnel zone is 6 pixels (the catalog's narrowest dust rings: 0.26 mm at
   2.2 µm pixels and 660 nm) to the volume's nearest depth over 1.2, and from its farthest
   depth times 1.2 to where the zone reaches 60 pixels (26 mm), for grains of `GRAIN_PX`
   pixels across, in steps of four depths of focus ``d²/λ`` of the smallest (a larger
   grain's focus is deeper, and the fits' depth scan covers the rest).
2. Every find is fitted (size, index and absorption free) and kept where its fit lowers the
   cost by the refinement's own significance (`RefineSettings.min_gain`'s default) and stays
   on its side's depths (a grain larger than its first Fresnel zone casts a shadow, not
   rings, and its fit runs off towards the sensor).
3. The scene's own particles fitted outside the volume by the same factor are grains too: a
   grain just outside the volume focuses within the finder's depths, and its fit takes it out
   to its own (`outside_volume`).
4. A window is one plane: the grains within 5 % of the median depth of the densest plane
   among them are the **layer**. The frame's dust is named where the layer's grains lie on
   at least `LAYER_TILES` tiles of the held-out checkerboard (a sign test over the tiles, each
   holding a grain a vote: z = √tiles); a particle's misfit or a pair fitted as one, which
   also leaves rings, lies within the volume, and a control's residual holds no significant
   grain outside it.

On the development frames (independent Lorenz–Mie spheres at 1.8–4.8 mm, 512², 2.2 µm
pixels), dust of 10–60 µm on a window 10 mm away gave 15 significant grains, 10 of them in
one plane at 10.01 mm on 10 tiles; 6.5 mm away, 11 in one plane at 6.50 mm on 8 tiles; 1.3 mm
away, in front of the volume, the scene had fitted 10 grains as particles at 1.30 mm, on 7
tiles. Grains of 10–50 µm 0.7 mm away are larger than their first Fresnel zone (26 µm): their
fits ran off to 0.1–0.2 mm, and the layer named came from three of the scene's particles at
1.35–1.43 mm.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, ProgressCallback, Steps, StopCallback, WorkerPool
from napari_lbs._core.gap._detect import find_particles
from napari_lbs._core.gap._heldout import TileSplit
from napari_lbs._core.refine import RefineSettings, refine_particles

__all__ = ["GRAIN_PX", "LAYER_TILES", "dust_layer", "dust_record", "dust_search_ranges_um", "in_window", "outside_volume"]

GRAIN_PX = (4.0, 28.0)  # grains searched for, pixels across (9–62 µm at 2.2 µm: dust on windows is 5–100 µm)
LAYER_TILES = 3  # tiles holding a grain of the layer from which the frame's dust is named
_LAYER_SPREAD = 0.05  # a window's grains lie within this fraction of their median depth
_OUTSIDE_FACTOR = 1.2  # a window lies nearer the sensor than the volume's nearest depth over this, or farther than its farthest times this
_ZONES_PX = (6.0, 60.0)  # the catalog's narrowest and widest dust rings: the first Fresnel zone in pixels
_MAX_GRAINS = 48  # the strongest finds fitted on each side of the volume
_STEP_FOCI = 4.0  # the search's step in depths of focus d²/λ of the smallest grain (the fits' depth scan covers the rest)


def dust_search_ranges_um(config: ExperimentConfig) -> tuple[tuple[float, float], ...]:
    """The depths (µm, the config's convention) searched for a dusty window: in front of the volume and behind it.

    Each side runs from the volume (its nearest depth over `_OUTSIDE_FACTOR`, its farthest
    times it) to where the catalog's dust rings reach (a first Fresnel zone of 6 to 60
    pixels), and is kept where its far end is at least twice its near one. None is searched
    where the pitch samples every angle: a microscope's sensor lies in an image plane, where a
    window's grains leave no in-line hologram of their own.
    """
    optics = config.optics
    if optics.pixel_um <= optics.wavelength_um / (2.0 * optics.medium_index):
        return ()
    wavelength = optics.wavelength_um / optics.medium_index  # distances in the config's convention
    narrowest, widest = ((zone * optics.pixel_um) ** 2 / wavelength for zone in _ZONES_PX)
    sides = ((narrowest, config.volume.z_min_um / _OUTSIDE_FACTOR), (_OUTSIDE_FACTOR * config.volume.z_max_um, widest))
    return tuple((near, far) for near, far in sides if far > 2.0 * near)


def outside_volume(table, config: ExperimentConfig) -> np.ndarray:
    """(rows,) bool: the particles of ``table`` fitted where `dust_search_ranges_um` looks for a window (outside the volume by `_OUTSIDE_FACTOR`)."""
    depths = np.asarray(table["z_um"], dtype=np.float64) if len(table) else np.zeros(0)
    if not dust_search_ranges_um(config):
        return np.zeros(depths.size, bool)
    return (depths < config.volume.z_min_um / _OUTSIDE_FACTOR) | (depths > _OUTSIDE_FACTOR * config.volume.z_max_um)


def in_window(table, dust: dict, config: ExperimentConfig) -> np.ndarray:
    """(rows,) bool: the particles of ``table`` in a named window's plane (`dust_layer`): outside the volume, within 5 % of the layer's depth."""
    if not dust.get("named") or not len(table):
        return np.zeros(len(table), bool)
    depths = np.asarray(table["z_um"], dtype=np.float64)
    return outside_volume(table, config) & (np.abs(np.log(np.maximum(depths, 1e-9) / dust["depth_um"])) <= _LAYER_SPREAD)


def _searched(ratio: np.ndarray, config: ExperimentConfig, settings: RefineSettings, pool, progress, should_stop):
    """The significant grains fitted on each side of the volume (`dust_search_ranges_um`) in ``ratio``."""
    import pandas as pd

    optics = config.optics
    wavelength = optics.wavelength_um / optics.medium_index
    pixel = optics.pixel_um
    step = _STEP_FOCI * (GRAIN_PX[0] * pixel) ** 2 / wavelength  # in the smallest grain's depths of focus
    sides = [dataclasses.replace(
        config, volume=dataclasses.replace(config.volume, z_min_um=near, z_max_um=max(far, near + step), z_step_um=step),
        particles=dataclasses.replace(config.particles, diameter_min_um=GRAIN_PX[0] * pixel, diameter_max_um=GRAIN_PX[1] * pixel))
        for near, far in dust_search_ranges_um(config)]
    planes = Steps(sum(len(side.volume.planes_um(step)) for side in sides), progress=progress, should_stop=should_stop)
    kept = []
    for side in sides:
        found = pd.DataFrame(find_particles(ratio, side, max_particles=_MAX_GRAINS, z_step_um=step, steps=planes))
        if found.empty:
            continue
        significant = dataclasses.replace(settings, min_gain=RefineSettings().min_gain, depth_window_um=0.1 * side.volume.z_max_um, rounds=1)
        fitted = refine_particles(ratio, found[["x_um", "y_um", "z_um", "diameter_um"]], side, settings=significant, progress=progress,
                                  should_stop=should_stop, pool=pool)
        # a fit that left its side's depths is not a grain there (a grain larger than its
        # first Fresnel zone casts a shadow, not rings, and its fit runs off towards the sensor)
        depth = fitted["z_um"].to_numpy(np.float64)
        kept.append(fitted[fitted["refined"].to_numpy(bool) & (depth >= side.volume.z_min_um) & (depth <= side.volume.z_max_um)])
    return pd.concat(kept, ignore_index=True) if kept else pd.DataFrame(columns=["x_um", "y_um", "z_um", "diameter_um", "index_contrast", "absorption"])


def _layer(log_depth: np.ndarray) -> np.ndarray:
    """(grains,) bool: the densest plane, the grains within `_LAYER_SPREAD` of the median log-depth of those about the grain with the most neighbours."""
    neighbours = (np.abs(log_depth[:, None] - log_depth[None, :]) <= _LAYER_SPREAD).sum(axis=1)
    members = np.abs(log_depth - log_depth[int(np.argmax(neighbours))]) <= _LAYER_SPREAD
    return np.abs(log_depth - np.median(log_depth[members])) <= _LAYER_SPREAD


def dust_layer(ratio: np.ndarray, config: ExperimentConfig, split: TileSplit, *, settings: RefineSettings, scene=None, search: bool = True,
               pool: WorkerPool | None = None, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> dict:
    """The grains of a dusty window in ``ratio`` (the frame over its fitted model) and in the scene, and whether the frame's dust is named (module docstring).

    Parameters
    ----------
    ratio : (rows, cols) array
        The frame divided by its model (the scene through the selected effects): 1 where
        the model explains it.
    config : ExperimentConfig
        Optics and the volume, outside which the window is looked for.
    split : TileSplit
        The checkerboard whose tiles count the layer's grains.
    settings : RefineSettings
        The fits' settings (workers, device); their significance is the refinement's
        default ``min_gain``.
    scene : pandas.DataFrame, optional
        The scene's fitted particles: those fitted outside the volume (`outside_volume`) are
        grains too (a grain near the volume focuses within the finder's depths and its fit
        takes it out to its own).
    search : bool
        Whether ``ratio`` is searched (not where the model leaves no structure to search).
    pool, progress, should_stop
        As `refine_particles`; the search reports each depth it back-propagates to.

    Returns
    -------
    dict
        ``named`` (bool), ``z`` (√ of the tiles holding a layer grain), ``tiles`` (per tile,
        its layer grains: the verdict's bootstrap), ``grains`` (significant fits outside the
        volume, the scene's among them), ``in_layer``, ``depth_um`` (the layer's median
        depth), ``params`` (the catalog's ``dust_per_mpx`` in the frame, ``dust_zone_px`` =
        √(λ z)/pixel, ``dust_grain_px``: the median radius) with ``params_err`` (from the
        layer's own scatter: the depths' and radii's standard errors, Poisson's for the
        count), ``table`` (the layer's grains, for their hologram; ``in_scene`` marks those
        the scene holds: `in_window` finds them in a table), and ``searched``: whether the
        residual was searched (not where the config leaves no depth to search).
    """
    import pandas as pd

    columns = ["x_um", "y_um", "z_um", "diameter_um", "index_contrast", "absorption"]
    empty = {"named": False, "z": 0.0, "tiles": np.zeros(split.grid * split.grid), "grains": 0, "in_layer": 0, "depth_um": None, "params": {}, "params_err": {},
             "table": pd.DataFrame(columns=[*columns, "in_scene"])}
    searched = bool(search and dust_search_ranges_um(config))
    found = _searched(ratio, config, settings, pool, progress, should_stop) if searched else pd.DataFrame(columns=columns)
    parts = [found.reindex(columns=columns).assign(in_scene=False)]
    if scene is not None and len(scene):
        parts.append(scene[outside_volume(scene, config)].reindex(columns=columns).assign(in_scene=True))
    parts = [part for part in parts if len(part)]
    if not parts:
        return {**empty, "searched": searched}
    grains = pd.concat(parts, ignore_index=True)
    layer = grains[_layer(np.log(grains["z_um"].to_numpy(np.float64)))].reset_index(drop=True)
    optics = config.optics
    wavelength = optics.wavelength_um / optics.medium_index
    pixel = optics.pixel_um
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
        "searched": searched,
        "named": held >= LAYER_TILES,
        "z": float(np.sqrt(held)),
        "tiles": tiles,
        "grains": int(len(grains)),
        "in_layer": int(count),
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
        record["layer_grains"] = dust["table"][["x_um", "y_um", "z_um", "diameter_um", "index_contrast", "absorption", "in_scene"]].to_dict("list") if len(dust["table"]) else {}
    return record
