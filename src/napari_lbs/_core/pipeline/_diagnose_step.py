"""The steps that measure: diagnose (the sim-to-real gap of a setup's holograms) and evaluate (a table against a reference)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import ProgressCallback, StopCallback, WorkerPool, available_threads, begin_phase
from napari_lbs._core.pipeline._common import Log, StepResult, _background, _quiet, _source, check_outputs, provenance, read_calibration

if TYPE_CHECKING:  # for the annotations only: the steps import these modules when they run
    import numpy as np

    from napari_lbs._core.gap import SceneDiagnosis, SceneDiagnosisSettings

__all__ = ["REPORT_FILES", "DiagnoseRequest", "DIAGNOSED_FRAMES", "tiles_per_side", "diagnose", "EvaluateRequest", "evaluate"]


# --- diagnose ------------------------------------------------------------------------------


# What a diagnosis writes into its folder (`write_report`).
REPORT_FILES = ("report.json", "report.md", "gap_where.png", "gap_effects.png")

# Frames of a recording a diagnosis reads, evenly spaced, each diagnosed on its own (minutes for
# a 1024² frame on 2 cores): three tell an accident of one frame from the setup's own effects.
DIAGNOSED_FRAMES = 3

_MIN_FRAME_PX = 128  # the smallest frame side `diagnose_scene` takes
_MOST_TILES = 16  # the most tiles per side of the held-out checkerboard (`SceneDiagnosisSettings.grid`)


@dataclass(frozen=True)
class DiagnoseRequest:
    """The sim-to-real gap of one or more holograms of a setup: which effects, where, how much.

    Attributes
    ----------
    hologram : path, sequence of paths, or array
        Each path an image, a multi-page TIFF, a folder of images or a glob pattern
        (`open_frames`); an array a 2-D hologram or a (frames, rows, cols) stack. At most
        `DIAGNOSED_FRAMES` evenly spaced frames are diagnosed, each on its own, and pooled into
        one report.
    out_dir : Path
        Gets ``report.json``, ``report.md`` and the figures.
    config : ExperimentConfig
    settings : SceneDiagnosisSettings, optional
        How `diagnose_scene` fits and decides (default: its defaults, with the fits in one
        process per available core, `available_threads`).
    background_path : path, optional
    calibration_path : path, optional
        Recorded as provenance.
    roi : (x, y), optional
        A reference place recorded in the report (every tile is used).
    tile_px : int, optional
        Tile edge in pixels: the held-out checkerboard gets the frame's shorter side over it
        tiles per side (`tiles_per_side`; default: the settings' ``grid``).
    seed : int
        Recorded as provenance (the diagnosis draws nothing at random).
    source : str, optional
        The hologram's name in the provenance and in the frames' names (default: its path).
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    hologram: str | Path | Sequence | np.ndarray
    out_dir: Path
    config: ExperimentConfig = ExperimentConfig()
    settings: SceneDiagnosisSettings | None = None
    background_path: str | Path | None = None
    calibration_path: str | Path | None = None
    roi: tuple[int, int] | None = None
    tile_px: int | None = None
    seed: int = 0
    source: str | None = None
    replace: bool = False

    def outputs(self) -> tuple[Path, ...]:
        """The files the step writes into ``out_dir`` (`REPORT_FILES`)."""
        return tuple(Path(self.out_dir) / name for name in REPORT_FILES)


def tiles_per_side(shape: tuple[int, int], tile_px: int, *, flag: str = "--tile") -> int:
    """Tiles per side of the held-out checkerboard for tiles of ``tile_px`` pixels on a frame of ``shape``: its shorter side over them, at most 16.

    Raises `InputError` naming ``flag`` where fewer than 3 tiles fit in a line: an effect is
    selected by a sign test over the tiles (`SceneDiagnosisSettings.level_z`), which 4 tiles
    cannot pass.
    """
    grid = min(shape) // tile_px if tile_px > 0 else 0
    if grid < 3:
        raise InputError(f"{flag} {tile_px}: a {shape[1]}x{shape[0]} (x by y) frame holds {grid} tile(s) of {tile_px} px in a line; expected at most {min(shape) // 3} px (3 tiles)")
    return min(grid, _MOST_TILES)


def _diagnosed_frames(source, name: str | None, *, log: Log) -> tuple[list, list[str]]:
    """The frames a diagnosis reads (at most `DIAGNOSED_FRAMES`, evenly spaced), each checked as a hologram, and their names."""
    import numpy as np

    from napari_lbs._core.foundation import as_hologram
    from napari_lbs._core.recordings import open_frames

    if isinstance(source, np.ndarray):
        frames = [source] if source.ndim == 2 or (source.ndim == 3 and source.shape[-1] in (3, 4)) else list(source)
        chosen = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), DIAGNOSED_FRAMES)).round().astype(int))
        names = [name or "array"] if len(frames) == 1 else [f"{name or 'array'}[frame {i}]" for i in chosen]
        return [as_hologram(frames[i], name=n, log=log) for i, n in zip(chosen, names, strict=True)], names
    with open_frames([source] if isinstance(source, (str, Path)) else list(source)) as frames:
        frames.check()
        chosen = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), DIAGNOSED_FRAMES)).round().astype(int))
        return [frames.read(int(i), log=log) for i in chosen], [frames.name(int(i)) for i in chosen]


class _FrameProgress:
    """Frame ``index`` of ``count`` as part of one bar over them all: its phases named "frame k of n: ...", each phase's steps within the frame's share of the bar."""

    def __init__(self, progress: ProgressCallback, index: int, count: int) -> None:
        self._progress, self._index, self._count = progress, index, count

    def __call__(self, done: int, total: int) -> None:
        if total > 0:
            self._progress(self._index * total + min(done, total), self._count * total)

    def phase(self, name: str) -> None:
        begin_phase(self._progress, f"frame {self._index + 1} of {self._count}: {name}")


def _pooled(diagnoses: list[SceneDiagnosis], names: list[str]) -> SceneDiagnosis:
    """The first frame's diagnosis, with each frame's verdict in ``frames`` and the effects a majority of the frames name as its verdict.

    The verdict's ``catalog_explains`` holds where it holds in a majority of the frames; its
    ``probability`` is the mean over the frames of each one's probability of its own verdict
    where that verdict is the pooled one (0 where it is another): the chance that one of these
    frames, drawn again, gives it. The parameters of each effect it names are those of the
    first frame that names it (what `effects_from_report` reads).
    """
    from collections import Counter
    from dataclasses import replace

    verdicts = [d.report["verdict"] for d in diagnoses]
    frames = [{"name": name, "verdict": v["id"], "catalog_explains": v["catalog_explains"], "residual": v["residual"], "probability": v.get("probability")}
              for name, v in zip(names, verdicts, strict=True)]
    first = diagnoses[0].report
    report = {**first, "frames": frames}
    if len(diagnoses) > 1:
        count = len(diagnoses)
        named = Counter(effect for v in verdicts if v["id"] for effect in v["id"].split("+"))
        majority = sorted(effect for effect, times in named.items() if 2 * times > count)
        explained = sum(bool(v["catalog_explains"]) for v in verdicts)
        pooled_id = "+".join(majority) or None
        agreeing = [v.get("probability") or 0.0 for v in verdicts if v["id"] == pooled_id]
        report["verdict"] = {**first["verdict"], "id": pooled_id, "catalog_explains": 2 * explained > count, "probability": sum(agreeing) / count,
                             "reason": f"named in a majority of the {count} frames diagnosed: {', '.join(majority) or 'nothing'}; the catalog explains "
                                       f"{explained} of them; the first frame: {first['verdict']['reason']}"}
        fitted = {}  # each named effect's parameters (and their errors) from the first frame that named it
        for diagnosis in diagnoses:
            named_here = set((diagnosis.report["verdict"]["id"] or "").split("+"))
            for effect in diagnosis.report["effects"]:
                if effect["id"] in majority and effect["id"] in named_here:
                    fitted.setdefault(effect["id"], {key: effect[key] for key in ("params", "params_err") if key in effect})
        report["effects"] = [{**e, **fitted.get(e["id"], {}), "selected": e["id"] in majority} for e in first["effects"]]
    return replace(diagnoses[0], report=report, seconds=round(sum(d.seconds for d in diagnoses), 2))


def diagnose(request: DiagnoseRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Diagnose each frame's gap (`diagnose_scene`, one progress bar over the frames), pool them (`DIAGNOSED_FRAMES`) and write the report with its provenance."""
    from dataclasses import replace

    import numpy as np

    config = request.config
    check_outputs(request.outputs(), replace=request.replace)
    calibration = read_calibration(request.calibration_path) if request.calibration_path else None
    frames, names = _diagnosed_frames(request.hologram, request.source, log=log)
    shape = tuple(np.shape(frames[0])[:2])
    grid = tiles_per_side(shape, request.tile_px) if request.tile_px is not None else None
    if min(shape) < _MIN_FRAME_PX:
        raise InputError(f"{names[0]}: expected at least {_MIN_FRAME_PX} pixels a side, got {shape[1]}x{shape[0]} (x by y)")
    background = _background(request.background_path, shape, log=log)
    source = _source(request.hologram if isinstance(request.hologram, (str, Path)) else ", ".join(dict.fromkeys(n.split("[frame")[0] for n in names)), request.source)
    if request.roi and not (request.roi[0] < shape[1] and request.roi[1] < shape[0]):
        raise InputError(f"--roi {request.roi[0]} {request.roi[1]}: outside the {shape[1]}x{shape[0]} (x by y) hologram {source}")
    from napari_lbs._core.gap import SceneDiagnosisSettings, diagnose_scene, write_report  # the fits' torch, once the inputs are checked

    settings = request.settings
    if settings is None:  # the fits in one process per core, as `predict --refine`'s
        default = SceneDiagnosisSettings()
        settings = replace(default, refine=replace(default.refine, workers=available_threads()))
    if grid is not None:
        settings = replace(settings, grid=grid)
    with WorkerPool(settings.refine.workers) as pool:  # the frames' fits in processes that start once
        diagnoses = [diagnose_scene(frame, config, settings=settings, background=background, progress=_FrameProgress(progress, k, len(frames)) if progress else None,
                                    should_stop=should_stop, pool=pool)
                     for k, frame in enumerate(frames)]
    diagnosis = _pooled(diagnoses, names)
    if request.roi:
        diagnosis.report["roi"] = {"x": int(request.roi[0]), "y": int(request.roi[1])}
    record = provenance(config, source=source, background=request.background_path and str(request.background_path), calibration=calibration, seed=request.seed, frames=names)
    paths = write_report(diagnosis, request.out_dir, settings=settings, provenance=record, force=request.replace)
    verdict, gap = diagnosis.report["verdict"], diagnosis.report["gap"]
    named = verdict["id"] or ("undecided between " + " and ".join(verdict["undecided"]) if verdict["undecided"] else "nothing named")
    probability = f"; probability {verdict['probability']:.2f}" if verdict.get("probability") is not None else ""
    optics = diagnosis.report.get("particle_optics") or {}
    if optics.get("model") == "undecided" and optics.get("particles"):
        probability += "; particle optics undecided"
    recorded = gap.get("baseline_recorded_frame")
    window = f"{recorded:.3f} (the scene alone on the recorded frame) -> " if recorded is not None else ""
    alone = "the scene alone without the window's grains" if recorded is not None else "the scene alone"
    summary = (f"verdict: {named}{probability}; unexplained share {window}{gap['baseline']:.3f} ({alone}) -> {verdict['residual']:.3f}, the catalog "
               f"{'explains' if verdict['catalog_explains'] else 'does not explain'} it; {len(frames)} frame(s) in {diagnosis.seconds:.0f} s -> {paths[0]}")
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
