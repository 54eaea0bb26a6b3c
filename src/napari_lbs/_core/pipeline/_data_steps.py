"""The steps that make and use a training set: generate and train."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import ProgressCallback, ReportCallback, StopCallback
from napari_lbs._core.foundation import read_json_object
from napari_lbs._core.pipeline._common import Log, StepResult, _quiet, check_outputs, read_calibration

if TYPE_CHECKING:  # for the annotations only: the steps import these modules when they run
    from napari_lbs._core.learning import DatasetLayout, InputProcessing, TrainingSettings
    from napari_lbs._core.physics import Distractors, SizeDistribution

__all__ = ["GenerateRequest", "training_processing", "requested_effects", "report_distractors", "report_sizes", "generate", "TrainRequest", "train"]


# --- generate ------------------------------------------------------------------------------


@dataclass(frozen=True)
class GenerateRequest:
    """A synthetic training set: the one description the console script, the widget and the demo build.

    Attributes
    ----------
    out_dir : Path
    config : ExperimentConfig
    groups : int
    calibration_path : path, optional
        A calibration JSON: recorded, and its Holo-processing makes the inputs unless
        ``processing`` is given or the effects come from a diagnosis report
        (`training_processing`).
    processing : InputProcessing, optional
        How inputs are made (default: the calibration's, else none: the seed's normal simulation).
    effects : mapping
        ``{effect_id: {param: value}}`` added to every hologram (`requested_effects`).
    effects_source : dict, optional
        Where the effects came from, recorded in the data set.
    layout : DatasetLayout, optional
    distractors : Distractors, optional
    sizes : SizeDistribution, optional
        The particles' diameter distribution (`report_sizes`); default uniform over the config's range.
    keep_calibration : bool
        With effects from a diagnosis report, apply the calibration's Holo-processing on top
        of them too (default: the report's model replaces it; `training_processing`).
    seed : int
    workers : int
        Processes simulating groups at once.
    """

    out_dir: Path
    config: ExperimentConfig = ExperimentConfig()
    _: KW_ONLY  # the data above, the options below
    groups: int = 256
    calibration_path: str | Path | None = None
    processing: InputProcessing | None = None
    effects: Mapping = field(default_factory=dict)
    effects_source: dict | None = None
    layout: DatasetLayout | None = None
    distractors: Distractors | None = None
    sizes: SizeDistribution | None = None
    keep_calibration: bool = False
    seed: int = 0
    workers: int = 1


def training_processing(calibration: dict | None, *, from_report: bool, keep_calibration: bool = False) -> tuple[InputProcessing, bool]:
    """How a training set's inputs are made from a calibration and the effects' origin.

    The calibration's Holo-processing (the seed's SSIM-fitted noise offset, noise width and
    gamma map) stands in for what the seed's simulator lacks without naming any of it. A
    diagnosis report measures those differences on the experiment's own particles: the
    effects it names with their fitted parameters, the small scatterers and the sizes. With a
    report the calibration is therefore recorded and not applied, unless ``keep_calibration``:
    applied on top, its noise offset at the bound of its range (N_R = -1) folds the
    back-propagated particles bright, and on pseudo-real holograms the same report's effects
    scored JI 0.36-0.41 lower with it (docs/diagnosis.md, the loop).

    Returns
    -------
    processing : InputProcessing
    replaced : bool
        Whether a calibration was given and is not applied.
    """
    from napari_lbs._core.learning import InputProcessing

    if calibration is None:
        return InputProcessing(), False
    if from_report and not keep_calibration:
        return InputProcessing(), True
    return InputProcessing.from_calibration(calibration), False


def requested_effects(*, report_path=None, explicit: Sequence[str] = (), flag: str = "--effect") -> tuple[dict, dict | None]:
    """The effects a diagnosis report names plus explicit ones (which add to or override them), and their source.

    Parameters
    ----------
    report_path : path, optional
        A diagnosis ``report.json`` (`effects_from_report`).
    explicit : sequence of str
        Command-line forms such as ``particle_phase:index_contrast=0.26,transmission=1``.
    flag : str
        Named in the message of a malformed explicit effect.

    Returns
    -------
    effects : dict
    source : dict or None
        ``{"report": path, "verdict": id}`` and/or ``{"explicit": [...]}``; None without effects asked for.
    """
    from napari_lbs._core.physics import effects_from_report, parse_effects

    effects, source = {}, None
    if report_path:
        report = read_json_object(report_path, what="diagnosis report")
        effects = effects_from_report(report, name=str(report_path))
        source = {"report": str(report_path), "verdict": report["verdict"]["id"]}
    explicit = [text for text in explicit if text.strip()]
    effects.update(parse_effects(explicit, flag=flag))
    if explicit:
        source = {**(source or {}), "explicit": list(explicit)}
    return effects, source


def report_distractors(report_path, config: ExperimentConfig):
    """The unlabelled impurities and neighbours a diagnosis report's scene measured (`distractors_from_report`), for ``config``'s tiles and optics."""
    from napari_lbs._core.physics import distractors_from_report

    report = read_json_object(report_path, what="diagnosis report")
    return distractors_from_report(report, tile_px=config.tile.size, diameter_min_um=config.particles.diameter_min_um, wavelength_um=config.optics.wavelength_um,
                                   pixel_um=config.optics.pixel_um, medium_index=config.optics.medium_index, name=str(report_path))


def report_sizes(report_path, config: ExperimentConfig):
    """The particle sizes a diagnosis report's scene measured (`sizes_from_report`), within ``config``'s range; None where it measured none."""
    from napari_lbs._core.physics import sizes_from_report

    report = read_json_object(report_path, what="diagnosis report")
    return sizes_from_report(report, diameter_range_um=(config.particles.diameter_min_um, config.particles.diameter_max_um), name=str(report_path))


def generate(request: GenerateRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> StepResult:
    """Write the synthetic training set (`generate_dataset`)."""
    from napari_lbs._core.learning import DatasetLayout, generate_dataset
    from napari_lbs._core.physics import Distractors

    calibration = read_calibration(request.calibration_path) if request.calibration_path else None
    if request.processing is not None:
        processing, replaced = request.processing, False
    else:
        from_report = bool(request.effects_source and "report" in request.effects_source)
        processing, replaced = training_processing(calibration, from_report=from_report, keep_calibration=request.keep_calibration)
    distractors = request.distractors or Distractors()
    effects = dict(request.effects)
    start = time.perf_counter()
    source = {**request.effects_source, "calibration_applied": False} if replaced else request.effects_source
    dataset = generate_dataset(request.out_dir, request.config, groups=request.groups, processing=processing, layout=request.layout or DatasetLayout(),
                               calibration=calibration, effects=effects, effects_source=source, distractors=distractors, sizes=request.sizes, seed=request.seed,
                               workers=request.workers, progress=progress, should_stop=should_stop)
    seconds = time.perf_counter() - start
    planes = len(dataset.groups) * len(dataset.planes_um)
    if replaced:
        kind = f"uncalibrated: the report's model replaces the Holo-processing of {request.calibration_path} (recorded; --keep-calibration applies it)"
    elif request.processing is None and calibration:
        kind = f"calibrated ({request.calibration_path})"
    else:
        kind = "uncalibrated: Holo-processing (0, 0, 1)"
    added = f", effects: {', '.join(effects)}" if effects else ""
    if request.effects_source and "report" in request.effects_source and not effects:
        added = f", no effects: {request.effects_source['report']} names none"
    if distractors.active:
        added += f", unlabelled distractors: {distractors.impurities_per_tile} impurities per tile, neighbours in a {distractors.neighbours_margin_px}-pixel margin"
    if request.sizes is not None:
        quartile = lambda level: float(np.interp(level, request.sizes.levels, request.sizes.diameters_um))
        added += f", measured sizes: median {quartile(0.5):.3g} um, quartiles {quartile(0.25):.3g}-{quartile(0.75):.3g} um"
    return StepResult(f"wrote {len(dataset.groups)} groups ({planes} input planes, {kind}{added}) in {seconds:.1f} s -> {request.out_dir}", dataset, (Path(request.out_dir),))


# --- train ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainRequest:
    """A network trained on a data set folder.

    Attributes
    ----------
    data : path
        The data set folder (`generate`).
    out_path : Path
        The model file; its training log goes beside it as ``.json``, its resume state as ``.last.pt``.
    settings : TrainingSettings, optional
    resume : bool
        Continue from ``out_path``'s ``.last.pt`` (its files are the run's own: replaced as it goes).
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    data: str | Path
    out_path: Path
    _: KW_ONLY  # the data above, the options below
    settings: TrainingSettings | None = None
    resume: bool = False
    replace: bool = False

    def outputs(self) -> tuple[Path, Path, Path]:
        """The files the step writes: the model, its training log and its resume state."""
        out = Path(self.out_path)
        return out, out.with_suffix(".json"), out.with_suffix(".last.pt")


def train(request: TrainRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet,
          report: ReportCallback | None = None) -> StepResult:
    """Train the U-Net (`train_model`); a data set with missing groups trains on those present, with a warning.

    ``report(record)`` receives each epoch's record as it ends (the widget's live curves).
    """
    from napari_lbs._core.learning import open_dataset
    from napari_lbs._core.learning import TrainingSettings, train_model

    settings = request.settings or TrainingSettings()
    check_outputs(request.outputs(), replace=request.replace or request.resume)
    dataset = open_dataset(request.data)
    expected = int(dataset.spec["groups"])
    if len(dataset.groups) < expected:  # a stopped generate, or group files removed since
        log(f"{request.data}: warning: {len(dataset.groups)} of {expected} groups present; training on those (run generate again to finish the set)")
    result = train_model(dataset, request.out_path, settings=settings, resume=request.resume, progress=progress, should_stop=should_stop,
                         report=report, force=request.replace or request.resume)
    best = result.log["best"]
    record = next(e for e in result.log["epochs"] if e["epoch"] == best["epoch"])["validation"]
    stopped = f" ({result.log['stop_reason']})" if result.stopped else ""
    summary = (f"trained {settings.preset} ({settings.formulation}) for {len(result.log['epochs'])} epochs in {result.log['seconds']:.0f} s{stopped}; best epoch {best['epoch']}: "
               f"validation ER {100 * record['er']:.2f} %, JI {record['ji']:.3f} (one-to-one, held-out synthetic groups) -> {request.out_path}")
    return StepResult(summary, result, (Path(result.model_path),))
