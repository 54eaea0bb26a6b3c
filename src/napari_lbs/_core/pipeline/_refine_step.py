"""The refine step: the particles of one hologram found and fitted by Lorenz–Mie theory, with no network.

The classical detector (`find_particles`: the back-propagated field's energy, peak by peak)
gives each particle's position and depth; `refine_particles` then fits its patch of the
hologram, binned first where its pitch is finer than the fringes need (`fringe_binning`). Nothing is trained, so a setup of any scale — a microscope's sub-wavelength pixels
as well as a lensless sensor's — is refined from its config alone (docs/microscopy.md).
"""

from __future__ import annotations

import time
from dataclasses import KW_ONLY, asdict, dataclass, field
from pathlib import Path

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, InputError, ProgressCallback, StopCallback, write_json
from napari_lbs._core.pipeline._common import Log, StepResult, _background, _hologram, _quiet, _source, provenance

__all__ = ["RefineRequest", "fringe_binning", "refine", "refine_hologram"]

# A camera's clipped focal spot shows as a plateau at the frame's maximum; a measured frame's
# maximum is otherwise reached by a pixel or two. Clipping biases the fit (docs/microscopy.md).
_SATURATED_PIXELS = 5


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
        The strongest detections kept.
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


def fringe_binning(config: ExperimentConfig, *, medium_index: float) -> int:
    """Pixels binned per side for the fit: as many as keep the pitch within half the medium wavelength.

    The fringes of the scattered light with the beam hold no spatial frequency above ``n/λ``
    (only propagating light reaches the camera), so a pitch up to ``λ/(2n)`` samples them all: a microscope's pitch at the
    sample (0.0851 µm behind 85× in water, λ/(2n) = 0.248 µm) is binned by 2, which makes the
    same patch twice as wide for a quarter of the pixels. A lensless sensor's pitch is never
    binned (1).
    """
    return max(1, int(config.optics.wavelength_um / (2.0 * medium_index * config.optics.pixel_um) + 1e-9))


def _binned(hologram: np.ndarray, config: ExperimentConfig, factor: int) -> tuple[np.ndarray, ExperimentConfig]:
    """The hologram's ``factor``² blocks averaged (the last rows and columns that fill no block dropped) and the config of their pitch."""
    from dataclasses import replace

    if factor == 1:
        return hologram, config
    rows, cols = (n // factor * factor for n in hologram.shape)
    if rows == 0 or cols == 0:
        raise InputError(f"hologram: expected at least {factor}x{factor} pixels, got shape {hologram.shape}")
    blocks = hologram[:rows, :cols].reshape(rows // factor, factor, cols // factor, factor).mean(axis=(1, 3))
    return blocks, replace(config, optics=replace(config.optics, pixel_um=config.optics.pixel_um * factor))


def refine_hologram(hologram: np.ndarray, config: ExperimentConfig, *, guesses=None, index_contrast: float = 0.26, medium_index: float = 1.33,
                    max_particles: int = 64, depth_window_um: float | None = None, patch_um: float | None = None, workers: int = 1,
                    progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> tuple[dict, dict]:
    """The particles of a normalised hologram: `find_particles`' guesses (or ``guesses``) fitted by `refine_particles`.

    Where the pitch is finer than half the medium wavelength, the hologram is first binned
    (`fringe_binning`): the fit sees every propagating fringe on a fraction of the pixels,
    each binned pixel integrating its area as the model's pixels do, and its patches of
    `RefineSettings.patch_px` pixels reach as many times farther. Positions are reported in the
    hologram's own coordinates (pixel ``(r, c)`` at ``(c, r) × pixel_um``).

    Parameters
    ----------
    hologram : (rows, cols) array
        Intensity with unobstructed light near 1 (divided by its background).
    config : ExperimentConfig
    guesses : pandas.DataFrame or dict of arrays, optional
        Starting guesses (``x_um, y_um, z_um, diameter_um`` at least; ``index_contrast``
        where known); default `find_particles`' in the (binned) hologram.
    index_contrast, medium_index, max_particles, depth_window_um, patch_um, workers
        As `RefineRequest`'s.
    progress, should_stop
        One step per depth searched (without ``guesses``), then one per fitted batch;
        `Stopped` when asked.

    Returns
    -------
    (table, record): the refined table as a dict of arrays (docs/formats.md, the columns of
    ``predict --refine``) and what the provenance records of the search and the fit
    (detector, binning, settings, detections, kept, seconds).
    """
    import pandas as pd

    from napari_lbs._core.foundation import Steps
    from napari_lbs._core.gap import find_particles
    from napari_lbs._core.refine import RefineSettings, refine_particles

    volume = config.volume
    window = depth_window_um if depth_window_um is not None else min(RefineSettings().depth_window_um, 0.25 * (volume.z_max_um - volume.z_min_um))
    factor = fringe_binning(config, medium_index=medium_index)
    patch_px = RefineSettings().patch_px if patch_um is None else int(round(patch_um / (factor * config.optics.pixel_um)))
    if patch_px < 16:
        raise InputError(f"patch_um: expected a patch of at least 16 pixels of {factor * config.optics.pixel_um:g} µm, got {patch_um!r} µm")
    settings = RefineSettings(medium_index=medium_index, index_contrast=index_contrast, depth_window_um=window, patch_px=patch_px, workers=workers)
    image, fit_config = _binned(np.asarray(hologram, dtype=np.float64), config, factor)
    # a binned pixel's centre lies half a block beyond its first original pixel's
    shift_um = 0.5 * (factor - 1) * config.optics.pixel_um
    started = time.perf_counter()
    if guesses is None:
        planes = len(volume.planes_um(2.0 * volume.z_step_um))
        found = find_particles(image, fit_config, max_particles=max_particles, steps=Steps(planes, progress=progress, should_stop=should_stop))
        starts = pd.DataFrame({name: found[name] for name in ("x_um", "y_um", "z_um", "diameter_um")})
        detector = "find_particles"
    else:
        starts = pd.DataFrame(guesses).reset_index(drop=True)
        starts[["x_um", "y_um"]] = starts[["x_um", "y_um"]].astype(np.float64) - shift_um
        detector = "given"
    searched = time.perf_counter() - started
    table = refine_particles(image, starts, fit_config, settings=settings, progress=progress, should_stop=should_stop)
    table[["x_um", "y_um"]] += shift_um
    record = {"detector": detector, "binning": factor, "settings": asdict(settings), "detections": len(starts), "kept": len(table),
              "seconds": {"search": searched, "fit": time.perf_counter() - started - searched}}
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
    hologram = _hologram(request.inputs, log=log)
    top = float(np.max(hologram))
    at_top = int(np.count_nonzero(hologram >= top))
    if at_top >= _SATURATED_PIXELS:
        log(f"{source}: {at_top} pixels at the frame's maximum ({top:g}): if the camera saturated there, the fits through those pixels are biased")
    background = _background(request.background_path, hologram.shape, log=log)
    dark = _background(request.dark_path, hologram.shape, log=log)
    normalised = _normalised(hologram, background, dark)
    started = time.perf_counter()
    table, find = refine_hologram(normalised, request.config, index_contrast=request.index_contrast, medium_index=request.medium_index,
                                  max_particles=request.max_particles, depth_window_um=request.depth_window_um, patch_um=request.patch_um, workers=request.workers,
                                  progress=progress, should_stop=should_stop)
    seconds = time.perf_counter() - started
    record = {**provenance(request.config, source=source, background_file=request.background_path and str(request.background_path),
                           dark_file=request.dark_path and str(request.dark_path)), "find": find, "pixels_at_maximum": at_top, "seconds": seconds, "particles": str(out)}
    write_particles(out, table, metadata=record, force=request.replace)
    write_json(record_path, record, force=request.replace)
    return StepResult(f"refined {find['kept']} of {find['detections']} detections in {source} in {seconds:.1f} s -> {out} (provenance: {record_path})",
                      table, (out, record_path))
