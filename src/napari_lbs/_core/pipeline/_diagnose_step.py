"""The steps that measure: diagnose (the sim-to-real gap of a setup's holograms) and evaluate (a table against a reference)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import ProgressCallback, StopCallback
from napari_lbs._core.pipeline._common import Log, StepResult, _background, _quiet, _source, check_outputs, provenance, read_calibration

if TYPE_CHECKING:  # for the annotations only: the steps import these modules when they run
    import numpy as np

    from napari_lbs._core.gap import DiagnosisSettings

__all__ = ["REPORT_FILES", "DiagnoseRequest", "DIAGNOSED_FRAMES", "diagnose", "EvaluateRequest", "evaluate"]


# --- diagnose ------------------------------------------------------------------------------


# What a diagnosis writes into its folder (`write_report`).
REPORT_FILES = ("report.json", "report.md", "gap_where.png", "gap_effects.png")


@dataclass(frozen=True)
class DiagnoseRequest:
    """The sim-to-real gap of one or more holograms of a setup: where, which effect, how much.

    Attributes
    ----------
    hologram : path, sequence of paths, or array
        Each path an image, a multi-page TIFF, a folder of images or a glob pattern
        (`open_frames`); an array a 2-D hologram or a (frames, rows, cols) stack. Every frame
        is pooled into one report; a recording longer than `DIAGNOSED_FRAMES` is read at that
        many evenly spaced frames.
    out_dir : Path
        Gets ``report.json``, ``report.md`` and the figures.
    config : ExperimentConfig
    settings : DiagnosisSettings, optional
    background_path : path, optional
    calibration_path : path, optional
        Recorded as provenance.
    roi : (x, y), optional
        A reference place recorded in the report (all tiles are used).
    tile_px : int, optional
        Tile edge in pixels (default: 128, or a quarter of the sensor's shorter side where smaller).
    known : bool
        Take the bit depth from the file's integer counts.
    stated : mapping
        Effects the user knows the experiment has (`parse_effects`), put into every simulation.
    source : str, optional
        The hologram's name in the provenance (default: its path).
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    hologram: str | Path | Sequence | np.ndarray
    out_dir: Path
    config: ExperimentConfig = ExperimentConfig()
    settings: DiagnosisSettings | None = None
    background_path: str | Path | None = None
    calibration_path: str | Path | None = None
    roi: tuple[int, int] | None = None
    tile_px: int | None = None
    known: bool = True
    stated: Mapping = field(default_factory=dict)
    source: str | None = None
    replace: bool = False

    def outputs(self) -> tuple[Path, ...]:
        """The files the step writes into ``out_dir`` (`REPORT_FILES`)."""
        return tuple(Path(self.out_dir) / name for name in REPORT_FILES)


DIAGNOSED_FRAMES = 16  # frames of a recording a diagnosis reads: the features are averaged, and 16 frames average out the particles


def _diagnosed_frames(source, *, log: Log) -> tuple[list, list[str]]:
    """The frames a diagnosis reads (at most `DIAGNOSED_FRAMES`, evenly spaced) and their names."""
    import numpy as np

    from napari_lbs._core.recordings import open_frames

    if isinstance(source, np.ndarray):
        frames = [source] if source.ndim == 2 or (source.ndim == 3 and source.shape[-1] in (3, 4)) else list(source)
        chosen = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), DIAGNOSED_FRAMES)).round().astype(int))
        return [frames[i] for i in chosen], [f"array[frame {i}]" for i in chosen]
    with open_frames([source] if isinstance(source, (str, Path)) else list(source)) as frames:
        frames.check()
        chosen = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), DIAGNOSED_FRAMES)).round().astype(int))
        return [frames.read(int(i), log=log) for i in chosen], [frames.name(int(i)) for i in chosen]


def diagnose(request: DiagnoseRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Diagnose the gap (`diagnose_hologram`) and write the report with its provenance."""
    import numpy as np

    from napari_lbs._core.gap import MIN_TILE_PX, DiagnosisSettings, diagnose_hologram, write_report

    config, settings = request.config, request.settings or DiagnosisSettings()
    check_outputs(request.outputs(), replace=request.replace)
    if request.tile_px is not None and request.tile_px < MIN_TILE_PX:
        raise InputError(f"--tile: expected at least {MIN_TILE_PX} pixels (the lowest frequency band needs them), got {request.tile_px}")
    calibration = read_calibration(request.calibration_path) if request.calibration_path else None
    frames, names = _diagnosed_frames(request.hologram, log=log)
    shape = np.shape(frames[0])[:2]
    background = _background(request.background_path, tuple(shape), log=log)
    source = _source(request.hologram if isinstance(request.hologram, (str, Path)) else ", ".join(dict.fromkeys(n.split("[frame")[0] for n in names)), request.source)
    if request.roi and not (request.roi[0] < shape[1] and request.roi[1] < shape[0]):
        raise InputError(f"--roi {request.roi[0]} {request.roi[1]}: outside the {shape[1]}x{shape[0]} (x by y) hologram {source}")
    diagnosis = diagnose_hologram(frames, config, background=background, tile_px=request.tile_px, known=request.known, stated=dict(request.stated), settings=settings,
                                  progress=progress, should_stop=should_stop)
    if request.roi:
        diagnosis.report["roi"] = {"x": int(request.roi[0]), "y": int(request.roi[1])}
    diagnosis.report["tiles"]["frame_names"] = names
    record = provenance(config, source=source, background=request.background_path and str(request.background_path), calibration=calibration, seed=settings.seed,
                        diagnoser=diagnosis.report["diagnoser"]["key"])
    paths = write_report(diagnosis, request.out_dir, provenance=record, force=request.replace)
    verdict = diagnosis.report["verdict"]
    named = verdict["id"] or ("undecided between " + " and ".join(verdict["undecided"]) if verdict["undecided"] else "nothing missing")
    summary = (f"verdict: {named} (P {verdict['probability']:.2f}); gap {diagnosis.report['gap']['baseline']:.2f} (baseline) -> {verdict['residual']:.2f}; "
               f"{len(frames)} frame(s) in {diagnosis.seconds:.0f} s -> {paths[0]}")
    return StepResult(summary, diagnosis, tuple(Path(p) for p in paths))


# --- evaluate ------------------------------------------------------------------------------


@dataclass(frozen=True)
class EvaluateRequest:
    """A particle table scored against a reference, one-to-one.

    Attributes
    ----------
    pred_path, truth_path : path
    lateral_tol_um, axial_tol_um : float, optional
        Match tolerances (µm; default 22 and 150).
    """

    pred_path: str | Path
    truth_path: str | Path
    lateral_tol_um: float | None = None
    axial_tol_um: float | None = None


def evaluate(request: EvaluateRequest) -> StepResult:
    """The metrics (`score_particles`) with the seed's scoring and the tolerances used; ``value`` is the metrics JSON."""
    from napari_lbs._core.foundation import read_particles
    from napari_lbs._core.learning import AXIAL_TOL_UM, LATERAL_TOL_UM, score_particles, seed_scores

    pred, truth = read_particles(request.pred_path), read_particles(request.truth_path)
    tolerances = {
        "lateral_tol_um": LATERAL_TOL_UM if request.lateral_tol_um is None else request.lateral_tol_um,
        "axial_tol_um": AXIAL_TOL_UM if request.axial_tol_um is None else request.axial_tol_um,
    }
    metrics = score_particles(pred, truth, **tolerances)
    seed = seed_scores(pred, truth, **tolerances)
    summary = (f"one-to-one: TP {metrics['tp']}, FP {metrics['fp']}, FN {metrics['fn']}, ER {100 * metrics['er']:.2f} %, JI {metrics['ji']:.3f} "
               f"(seed's scoring, which counts repeats: ER {100 * seed['er']:.2f} %, JI {seed['ji']:.3f})")
    return StepResult(summary, {**metrics, "seed_scoring": seed, **tolerances})
