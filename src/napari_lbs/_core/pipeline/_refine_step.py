"""The refine step: the particles of one hologram found and fitted by Lorenz–Mie theory, with no network.

The classical detector (`find_particles`: the back-propagated field's energy, peak by peak)
gives each particle's position and depth; `refine_particles` then fits its patch of the
hologram. Nothing is trained, so a setup of any scale — a microscope's sub-wavelength pixels
as well as a lensless sensor's — is refined from its config alone (docs/microscopy.md).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, InputError, ProgressCallback, StopCallback, check_target, write_json
from napari_lbs._core.pipeline._common import Log, StepResult, _background, _hologram, _quiet, _source, provenance

__all__ = ["RefineRequest", "refine", "refine_hologram"]


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
    background_path: str | Path | None = None
    dark_path: str | Path | None = None
    index_contrast: float = 0.26
    medium_index: float = 1.33
    max_particles: int = 64
    depth_window_um: float | None = None
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


def refine_hologram(hologram: np.ndarray, config: ExperimentConfig, *, index_contrast: float = 0.26, medium_index: float = 1.33, max_particles: int = 64,
                    depth_window_um: float | None = None, workers: int = 1, progress: ProgressCallback | None = None,
                    should_stop: StopCallback | None = None) -> tuple[dict, dict]:
    """The particles of a normalised hologram: `find_particles`' guesses fitted by `refine_particles`.

    Parameters
    ----------
    hologram : (rows, cols) array
        Intensity with unobstructed light near 1 (divided by its background).
    config : ExperimentConfig
    index_contrast, medium_index, max_particles, depth_window_um, workers
        As `RefineRequest`'s.
    progress, should_stop
        One step per depth searched, then one per fitted batch; `Stopped` when asked.

    Returns
    -------
    (table, record): the refined table as a dict of arrays (docs/formats.md, the columns of
    ``predict --refine``) and what the provenance records of the search and the fit
    (settings, detections, kept, seconds).
    """
    import pandas as pd

    from napari_lbs._core.foundation import Steps
    from napari_lbs._core.gap import find_particles
    from napari_lbs._core.refine import RefineSettings, refine_particles

    volume = config.volume
    window = depth_window_um if depth_window_um is not None else min(RefineSettings().depth_window_um, 0.25 * (volume.z_max_um - volume.z_min_um))
    settings = RefineSettings(medium_index=medium_index, index_contrast=index_contrast, depth_window_um=window, workers=workers)
    started = time.perf_counter()
    planes = len(volume.planes_um(2.0 * volume.z_step_um))
    found = find_particles(hologram, config, max_particles=max_particles, steps=Steps(planes, progress=progress, should_stop=should_stop))
    searched = time.perf_counter() - started
    guesses = pd.DataFrame({name: found[name] for name in ("x_um", "y_um", "z_um", "diameter_um")})
    table = refine_particles(hologram, guesses, config, settings=settings, progress=progress, should_stop=should_stop)
    record = {"detector": "find_particles", "settings": asdict(settings), "detections": len(guesses), "kept": len(table),
              "seconds": {"search": searched, "fit": time.perf_counter() - started - searched}}
    return {name: table[name].to_numpy() for name in table.columns}, record


def _refine_outputs(request: RefineRequest) -> tuple[Path, Path]:
    """The table and its provenance, refused before any work where they exist (unless replaced) or would overwrite another file."""
    from napari_lbs._core.foundation import check_table_name

    out, record = request.outputs()
    if out.suffix.lower() == ".json":
        raise InputError(f"--out {out}: expected a particle table (.csv, or .parquet); its provenance is written beside it as .json")
    check_table_name(out)
    check_target(out, force=request.replace, flag="--out")
    if check_target(record, force=request.replace, flag="--out").is_file():
        try:
            previous = json.loads(record.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            previous = None
        # only this table's provenance from an earlier refine is replaced, never another JSON
        if not (isinstance(previous, dict) and previous.get("particles") == str(out) and "find" in previous):
            raise InputError(f"--out {out}: {record} exists and is not this table's provenance; choose another name")
    return out, record


def refine(request: RefineRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Find and fit the particles of one hologram (`refine_hologram`); write the table and its provenance."""
    from napari_lbs._core.foundation import write_particles

    out, record_path = _refine_outputs(request)
    source = str(request.inputs) if isinstance(request.inputs, (str, Path)) else _source("array", request.source)
    hologram = _hologram(request.inputs, log=log)
    background = _background(request.background_path, hologram.shape, log=log)
    dark = _background(request.dark_path, hologram.shape, log=log)
    normalised = _normalised(hologram, background, dark)
    started = time.perf_counter()
    table, find = refine_hologram(normalised, request.config, index_contrast=request.index_contrast, medium_index=request.medium_index,
                                  max_particles=request.max_particles, depth_window_um=request.depth_window_um, workers=request.workers,
                                  progress=progress, should_stop=should_stop)
    seconds = time.perf_counter() - started
    record = {**provenance(request.config, source=source, background_file=request.background_path and str(request.background_path),
                           dark_file=request.dark_path and str(request.dark_path)), "find": find, "seconds": seconds, "particles": str(out)}
    write_particles(out, table, metadata=record)
    write_json(record_path, record)
    return StepResult(f"refined {find['kept']} of {find['detections']} detections in {source} in {seconds:.1f} s -> {out} (provenance: {record_path})",
                      table, (out, record_path))
