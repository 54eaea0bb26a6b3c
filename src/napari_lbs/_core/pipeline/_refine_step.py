"""The refine step: the particles of one hologram found and fitted by Lorenz–Mie theory, with no network.

The classical detector (`find_particles`: the back-propagated field's energy, peak by peak)
gives each particle's position and depth; `refine_particles` then fits its patch of the
hologram, binned first where its pitch is finer than the fringes need (`fringe_binning`).
The detector then looks again in what the fitted particles leave (`_residual_rounds`): in a
crowded field the strong scatterers hide the weak ones. Nothing is trained, so a setup of any scale — a microscope's sub-wavelength pixels
as well as a lensless sensor's — is refined from its config alone (docs/microscopy.md).
"""

from __future__ import annotations

import time
from dataclasses import KW_ONLY, asdict, dataclass, field
from pathlib import Path

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, InputError, ProgressCallback, StopCallback, WorkerPool, write_json
from napari_lbs._core.pipeline._binning import binned_hologram, binned_valid, default_depth_window_um, fringe_binning
from napari_lbs._core.pipeline._common import Log, StepResult, _background, _hologram, _quiet, _source, explained_by_fits, provenance

__all__ = ["DETECTION_ROUNDS", "RefineRequest", "refine", "refine_hologram"]

# Looks for particles by default: the hologram, then the residual twice. The built-in
# example with the default patches needs all three: the second look finds the 1.5 µm sphere
# and the 3 µm one whose first fit failed, the third the 0.8 µm one (docs/microscopy.md).
DETECTION_ROUNDS = 3
# The column in which a table being refined carries each particle's starting index contrast
# through the looks in its residual (`_residual_rounds`).
_START_INDEX = "start_index_contrast"


@dataclass(frozen=True)
class RefineRequest:
    """What `refine` finds and fits, and where the table goes.

    Attributes
    ----------
    inputs : path or (rows, cols) array
        The hologram.
    out_path : path
        The particle table (CSV, or Parquet by its name); its provenance JSON beside it.
    config : ExperimentConfig
        Optics (the pixel pitch at the sample), the depths searched (``volume``) and the
        expected diameters (``particles``: their mean is every first guess's).
    background_path, dark_path : path, optional
        A frame without particles, and one without light (the camera's dark counts):
        the hologram becomes ``(hologram - dark) / (background - dark)``.
    index_contrast : float
        ``n_p - n_m`` where every fit starts (the sample's material; polystyrene in water 0.26).
    medium_index : float
        Refractive index of the liquid the particles are in (water 1.33).
    max_particles : int
        The most particles the table holds: the strongest detections, then the residual's.
    detection_rounds : int
        Looks for particles: the first in the hologram, each later one in the residual the
        fitted particles leave, until one finds nothing new (`refine_hologram`); 1 fits the
        first look's detections alone.
    depth_window_um : float, optional
        Depths each fit scans on both sides of its guess (µm, the config's convention);
        default a quarter of the config's depth range, at most `RefineSettings`'s.
    patch_um : float, optional
        Largest patch edge (µm); default `RefineSettings.patch_px` pixels of the pitch the fit
        sees (the binned one, `fringe_binning`): the same count of pixels, each sampling the
        fringes as finely as they need.
    workers : int
        Fitting processes (`RefineSettings.workers`).
    replace : bool
        Replace the table and its provenance where they exist.
    source : str, optional
        The hologram's name in the provenance when ``inputs`` is an array.
    """

    inputs: object
    out_path: str | Path
    config: ExperimentConfig = field(default_factory=ExperimentConfig)
    _: KW_ONLY  # the data above, the options below
    background_path: str | Path | None = None
    dark_path: str | Path | None = None
    index_contrast: float = 0.26
    medium_index: float = 1.33
    max_particles: int = 64
    detection_rounds: int = DETECTION_ROUNDS
    depth_window_um: float | None = None
    patch_um: float | None = None
    workers: int = 1
    replace: bool = False
    source: str | None = None

    def outputs(self) -> tuple[Path, Path]:
        """The files the step writes: the table and its provenance beside it."""
        return Path(self.out_path), Path(self.out_path).with_suffix(".json")


def _normalised(hologram: np.ndarray, background: np.ndarray | None, dark: np.ndarray | None) -> np.ndarray:
    """``(hologram - dark) / (background - dark)``, or the dark-corrected hologram over its mean, float64."""
    image = np.asarray(hologram, dtype=np.float64) - (0.0 if dark is None else dark)
    if background is None:
        level = float(image.mean())
        if not level > 0.0:
            raise InputError(f"hologram: expected a positive mean intensity{' above the dark frame' if dark is not None else ''}, got {level:g}")
        return image / level
    light = np.asarray(background, dtype=np.float64) - (0.0 if dark is None else dark)
    if not np.all(light > 0.0):
        raise InputError(f"background: expected values above the dark frame everywhere, got {int(np.sum(~(light > 0.0)))} pixels at or below it")
    return image / light


def _residual_detector(config: ExperimentConfig, *, max_particles: int, progress: ProgressCallback | None, should_stop: StopCallback | None):
    """``propose(image)`` for `residual_particles`: `find_particles`' peaks in a residual, each started at several diameters, and the peaks counted.

    The detector measures no size. A particle the strong ones hid is often weaker than
    they are, and a sub-micrometre sphere started at the config's mean diameter falls
    between the fit's size steps (0.4 µm) onto the wrong side of its size–index ridge (the
    built-in example's 0.8 µm sphere, residual fit from 1.75 µm: 0.95 µm, index contrast
    1.44, 2 µm off in depth). So every peak starts at the config's smallest, mean and
    largest diameter; the column ``peak`` says which peak each start is of.
    """
    from napari_lbs._core.foundation import Steps
    from napari_lbs._core.gap import find_particles

    particles = config.particles
    diameters = np.unique([particles.diameter_min_um, 0.5 * (particles.diameter_min_um + particles.diameter_max_um), particles.diameter_max_um])
    planes = len(config.volume.planes_um(2.0 * config.volume.z_step_um))
    peaks: list[int] = []

    def propose(image: np.ndarray) -> dict[str, np.ndarray]:
        found = find_particles(image, config, max_particles=max_particles, steps=Steps(planes, progress=progress, should_stop=should_stop))
        count = len(found["x_um"])
        peaks.append(count)
        starts = {name: np.tile(found[name], diameters.size) for name in ("x_um", "y_um", "z_um")}
        return {**starts, "diameter_um": np.repeat(diameters, count), "peak": np.tile(np.arange(count), diameters.size)}

    return propose, peaks


def _residual_rounds(image: np.ndarray, table, config: ExperimentConfig, settings, *, rounds: int, max_particles: int, valid: np.ndarray | None,
                     progress: ProgressCallback | None, should_stop: StopCallback | None, pool: WorkerPool) -> tuple[object, list[dict]]:
    """The refined ``table`` after up to ``rounds`` looks in its residual, every fit in ``pool``; each look's record.

    Each look renders the refined particles (`particle_hologram`), looks for peaks in what
    they leave (`residual_particles` with `_residual_detector`: the detector's peaks fitted
    on the residual, the best-fitting start of each kept where the fit measures the
    sample's material and no particle of the table), and refits every particle with the
    new ones on the hologram (`refine_particles`, two rounds: the second holds each
    patch's neighbours at their refits). Each particle restarts at its fitted position,
    depth and diameter and at its first start's index contrast (the table's
    `_START_INDEX`): a fit its missed neighbours pulled into another index valley (the
    built-in example's 2.2 µm sphere: 0.54 for 0.26) would otherwise anchor the refit's
    valley search there. The looks stop when one finds nothing new or the table holds
    ``max_particles``. Rows the fit did not refine stay out of the residual's model and of
    the refits, and out of the table once a refined particle lies on them (`explained_by_fits`).
    """
    from dataclasses import replace

    import pandas as pd

    from napari_lbs._core.foundation import begin_phase
    from napari_lbs._core.refine import refine_particles, residual_particles

    records = []
    for look in range(2, rounds + 1):
        room = max_particles - len(table)
        if room < 1:
            break
        started = time.perf_counter()
        begin_phase(progress, f"look {look} in the residual")
        propose, peaks = _residual_detector(config, max_particles=room, progress=progress, should_stop=should_stop)
        refined = table["refined"].astype(bool).to_numpy()
        fitted, pending = table[refined], table[~refined]
        found = residual_particles(image, fitted, config, propose=propose, settings=settings, background=np.ones(image.shape), valid=valid, progress=progress,
                                   should_stop=should_stop, pool=pool)
        if found.empty:
            records.append({"peaks": peaks[0], "found": 0, "kept": len(table), "seconds": time.perf_counter() - started})
            break
        # one particle per peak: the start that fitted it best
        found = found.sort_values("fit_residual", kind="stable").drop_duplicates("peak").sort_values("peak").drop(columns="peak").head(room)
        restart = pd.concat([fitted, found], ignore_index=True)
        restart["index_contrast"] = restart[_START_INDEX].fillna(settings.index_contrast)
        begin_phase(progress, f"fit {len(restart)} particles")
        refit = refine_particles(image, restart, config, settings=replace(settings, rounds=max(settings.rounds, 2)), valid=valid, progress=progress,
                                 should_stop=should_stop, pool=pool)
        table = pd.concat([refit, pending[~explained_by_fits(pending, refit)]], ignore_index=True)
        records.append({"peaks": peaks[0], "found": len(found), "kept": len(table), "seconds": time.perf_counter() - started})
    return table, records


def refine_hologram(hologram: np.ndarray, config: ExperimentConfig, *, guesses=None, index_contrast: float = 0.26, medium_index: float = 1.33,
                    max_particles: int = 64, detection_rounds: int = DETECTION_ROUNDS, depth_window_um: float | None = None, patch_um: float | None = None,
                    workers: int = 1, valid: np.ndarray | None = None, progress: ProgressCallback | None = None,
                    should_stop: StopCallback | None = None) -> tuple[dict, dict]:
    """The particles of a normalised hologram: `find_particles`' guesses (or ``guesses``) fitted by `refine_particles`, then those their residual holds.

    Where the pitch is finer than half the medium wavelength, the hologram is first binned
    (`fringe_binning`): the fit sees every propagating fringe on a fraction of the pixels,
    each binned pixel integrating its area as the model's pixels do, and its patches of
    `RefineSettings.patch_px` pixels reach as many times farther. Positions are reported in the
    hologram's own coordinates (pixel ``(r, c)`` at ``(c, r) × pixel_um``).

    A sphere's fringes reach tens of micrometres: in a crowded field the strong scatterers
    hide the weak ones from the detector, and each fit's patch holds the fringes of the
    particles missed. So, after the first fits, the detector looks again in the residual
    the fitted particles leave (the hologram less their modelled scattering, unobstructed
    light 1), the new particles are fitted there, and every particle is refitted with its
    neighbours' fitted fringes in its model; up to ``detection_rounds`` looks in all, until
    one finds nothing new (`_residual_rounds`).

    Parameters
    ----------
    hologram : (rows, cols) array
        Intensity with unobstructed light near 1 (divided by its background).
    config : ExperimentConfig
    guesses : pandas.DataFrame or dict of arrays, optional
        Starting guesses (``x_um, y_um, z_um, diameter_um`` at least; ``index_contrast``
        where known); default `find_particles`' in the (binned) hologram. Later looks
        search the residual with `find_particles` either way.
    index_contrast, medium_index, max_particles, detection_rounds, depth_window_um, patch_um, workers
        As `RefineRequest`'s.
    valid : (rows, cols) bool array, optional
        The pixels the fits compare (`refine_particles`; `unsaturated_pixels` of the raw
        frame); the detector sees every pixel.
    progress, should_stop
        One step per depth searched (without ``guesses``), then one per fitted batch; in
        each later look, one per particle rendered, per depth searched and per fitted batch,
        each phase named as it begins (`begin_phase`). `Stopped` when asked.

    Returns
    -------
    (table, record): the refined table as a dict of arrays (docs/formats.md, the columns of
    ``predict --refine``) and what the provenance records of the search and the fit
    (detector, binning, settings, detections, kept, the later looks' ``rounds``, seconds).
    """
    import pandas as pd

    from napari_lbs._core.foundation import Steps, begin_phase
    from napari_lbs._core.gap import find_particles
    from napari_lbs._core.refine import RefineSettings, refine_particles

    if not (isinstance(detection_rounds, int) and detection_rounds >= 1):
        raise InputError(f"detection_rounds: expected a positive integer, got {detection_rounds!r}")
    volume = config.volume
    window = depth_window_um if depth_window_um is not None else default_depth_window_um(config)
    factor = fringe_binning(config, medium_index=medium_index)
    patch_px = RefineSettings().patch_px if patch_um is None else int(round(patch_um / (factor * config.optics.pixel_um)))
    if patch_px < 16:
        raise InputError(f"patch_um: expected a patch of at least 16 pixels of {factor * config.optics.pixel_um:g} µm, got {patch_um!r} µm")
    settings = RefineSettings(medium_index=medium_index, index_contrast=index_contrast, depth_window_um=window, patch_px=patch_px, workers=workers)
    image, fit_config, shift_um = binned_hologram(hologram, config, medium_index=medium_index)
    valid = binned_valid(valid, config, medium_index=medium_index)
    started = time.perf_counter()
    if guesses is None:
        begin_phase(progress, "find particles")
        planes = len(volume.planes_um(2.0 * volume.z_step_um))
        found = find_particles(image, fit_config, max_particles=max_particles, steps=Steps(planes, progress=progress, should_stop=should_stop))
        starts = pd.DataFrame({name: found[name] for name in ("x_um", "y_um", "z_um", "diameter_um")})
        detector = "find_particles"
    else:
        starts = pd.DataFrame(guesses).reset_index(drop=True)
        starts[["x_um", "y_um"]] = starts[["x_um", "y_um"]].astype(np.float64) - shift_um
        detector = "given"
    searched = time.perf_counter() - started
    begin_phase(progress, f"fit {len(starts)} particles")
    start_index = pd.to_numeric(starts["index_contrast"], errors="coerce").fillna(index_contrast) if "index_contrast" in starts else index_contrast
    with WorkerPool(workers) as pool:  # started once for the fits and the looks' fits
        table = refine_particles(image, starts.assign(**{_START_INDEX: start_index}), fit_config, settings=settings, valid=valid, progress=progress,
                                 should_stop=should_stop, pool=pool)
        fit_s = time.perf_counter() - started - searched
        table, rounds = _residual_rounds(image, table, fit_config, settings, rounds=detection_rounds, max_particles=max_particles, valid=valid, progress=progress,
                                         should_stop=should_stop, pool=pool)
    table = table.drop(columns=_START_INDEX)
    table[["x_um", "y_um"]] += shift_um
    record = {"detector": detector, "binning": factor, "settings": asdict(settings), "detections": len(starts), "kept": len(table),
              "detection_rounds": detection_rounds, "rounds": rounds,
              "seconds": {"search": searched, "fit": fit_s, "rounds": time.perf_counter() - started - searched - fit_s}}
    return {name: table[name].to_numpy() for name in table.columns}, record


def _refine_outputs(request: RefineRequest) -> tuple[Path, Path]:
    """The table and its provenance, refused before any work where they exist (unless replaced) or would overwrite another file."""
    from napari_lbs._core.pipeline._predict import prediction_outputs

    return prediction_outputs(request.outputs()[0], replace=request.replace, marker="find")


def refine(request: RefineRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Find and fit the particles of one hologram (`refine_hologram`); write the table and its provenance."""
    from napari_lbs._core.foundation import write_particles

    out, record_path = _refine_outputs(request)
    source = str(request.inputs) if isinstance(request.inputs, (str, Path)) else _source("array", request.source)
    from napari_lbs._core.refine import unsaturated_pixels

    hologram = _hologram(request.inputs, log=log)
    at_top = int(np.count_nonzero(hologram >= np.max(hologram)))
    valid = unsaturated_pixels(hologram)
    if valid is not None:
        log(f"{source}: {at_top} pixels at the frame's maximum ({float(np.max(hologram)):g}), a saturated camera's: left out of the fits")
    background = _background(request.background_path, hologram.shape, log=log)
    dark = _background(request.dark_path, hologram.shape, log=log)
    normalised = _normalised(hologram, background, dark)
    started = time.perf_counter()
    table, find = refine_hologram(normalised, request.config, index_contrast=request.index_contrast, medium_index=request.medium_index,
                                  max_particles=request.max_particles, detection_rounds=request.detection_rounds, depth_window_um=request.depth_window_um,
                                  patch_um=request.patch_um, workers=request.workers, valid=valid, progress=progress, should_stop=should_stop)
    seconds = time.perf_counter() - started
    record = {**provenance(request.config, source=source, background_file=request.background_path and str(request.background_path),
                           dark_file=request.dark_path and str(request.dark_path)), "find": find, "pixels_at_maximum": at_top,
                           "pixels_left_out": 0 if valid is None else at_top, "seconds": seconds, "particles": str(out)}
    write_particles(out, table, metadata=record, force=request.replace)
    write_json(record_path, record, force=request.replace)
    more = sum(look["found"] for look in find["rounds"])
    what = (f"{find['kept']} particles ({find['detections']} detections, {more} more found in the residual)" if more
            else f"{find['kept']} of {find['detections']} detections")
    return StepResult(f"refined {what} in {source} in {seconds:.1f} s -> {out} (provenance: {record_path})",
                      table, (out, record_path))
