"""The pipeline: one step per task, a frozen request in, a `StepResult` out.

The console script and the widgets only build requests and show results; the steps read
the inputs, run `_core`'s functions, write the outputs with their provenance and say in
one line what they did. `demo` is a sequence of these steps.

Every step takes keyword-only ``progress(done, total)`` and ``should_stop()`` (see
`napari_lbs._core.foundation._progress`) and ``log(text)`` for messages about the inputs (an RGB
image reduced to one channel, a data set with missing groups). Heavy modules are imported
inside the steps, so importing this module costs nothing.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from napari_lbs import __version__
from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import read_json_object, write_json
from napari_lbs._core.foundation import ProgressCallback, StopCallback
from napari_lbs._core.foundation import check_output_path

if TYPE_CHECKING:  # for the annotations only: the steps import these modules when they run
    import numpy as np

    from napari_lbs._core.calibration import CalibrationSettings
    from napari_lbs._core.learning import DatasetLayout, InputProcessing
    from napari_lbs._core.gap import DiagnosisSettings
    from napari_lbs._core.learning import LoadedModel
    from napari_lbs._core.physics import Distractors
    from napari_lbs._core.learning import TrainingSettings

__all__ = [
    "StepResult",
    "SimulateRequest",
    "simulate",
    "BackpropRequest",
    "backprop",
    "CalibrateRequest",
    "calibrate",
    "GenerateRequest",
    "requested_effects",
    "generate",
    "TrainRequest",
    "train",
    "PredictRequest",
    "prediction_outputs",
    "refined_prediction",
    "predict",
    "TrackRequest",
    "track",
    "DiagnoseRequest",
    "diagnose",
    "EvaluateRequest",
    "evaluate",
    "DemoRequest",
    "demo",
    "read_calibration",
]

Log = Callable[[str], None]


@dataclass(frozen=True)
class StepResult:
    """What a step did.

    Attributes
    ----------
    summary : str
        One line for the user (the console script prints it on stderr).
    value : object
        The step's own result (`CalibrationResult`, `SyntheticDataset`, `TrainingResult`,
        `PredictionResult`, `Diagnosis`, a metrics dict, ...).
    paths : tuple of Path
        The files and folders it wrote, the main one first.
    """

    summary: str
    value: object = None
    paths: tuple[Path, ...] = ()


def provenance(config: ExperimentConfig, **extra) -> dict:
    """What every output records: the package version, the config and the step's own inputs."""
    return {"napari_lbs": __version__, "config": config.to_dict(), **extra}


def _quiet(_text: str) -> None:
    pass


def _hologram(source, *, log: Log):
    """The hologram of a request: read from its file, or the array it holds."""
    from napari_lbs._core.foundation import read_hologram

    return read_hologram(source, log=log) if isinstance(source, (str, Path)) else source


def _background(path, shape: tuple[int, int], *, log: Log):
    """The background file (None when not given), refused unless it has the hologram's ``shape``."""
    from napari_lbs._core.foundation import read_hologram

    if not path:
        return None
    background = read_hologram(path, log=log)
    if background.shape != shape:
        raise InputError(f"{path}: expected the hologram's shape {shape}, got {background.shape}")
    return background


def _source(source, name: str | None) -> str:
    return name if name is not None else str(source)


def read_calibration(path) -> dict:
    """A calibration JSON (docs/formats.md), checked before anything uses it."""
    from napari_lbs._core.foundation import check_calibration

    calibration = read_json_object(path, what="calibration")
    check_calibration(calibration, name=str(path))
    return calibration


# --- simulate ------------------------------------------------------------------------------

# Peak memory of a simulation per pixel of its padded FFT grid (bytes), with a margin: the
# default config's 16 layers peak at 103 (256² window) to 141 (1024²) bytes (tracemalloc).
_SIMULATION_BYTES_PER_PX = 160


@dataclass(frozen=True)
class SimulateRequest:
    """A simulated hologram with its truth, or a recording with its tracks.

    Attributes
    ----------
    out_dir : Path
        Gets ``hologram.tif`` (``frames.tif`` for a recording) and ``particles.csv``.
    config : ExperimentConfig
    size_px : int, optional
        Window edge in pixels (default: ``config.tile.size``).
    particles : int, optional
        Number of particles (default: ``config.particles.per_tile``).
    seed : int
    shadowing : bool
        Propagate layer by layer so particles shadow each other.
    frames : int, optional
        A recording of this many frames instead of one hologram.
    flow : str
        A recording's flow: ``uniform``, ``vortex`` or ``shear``.
    speed_um : float
        A recording's largest displacement of a particle between frames (µm).
    """

    out_dir: Path
    config: ExperimentConfig = ExperimentConfig()
    size_px: int | None = None
    particles: int | None = None
    seed: int = 0
    shadowing: bool = False
    frames: int | None = None
    flow: str = "uniform"
    speed_um: float = 8.0


def simulate(request: SimulateRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> StepResult:
    """Simulate a hologram (or a recording) of a random particle field and write it with its truth."""
    from napari_lbs._core.foundation import tiff_pages, write_particles
    from napari_lbs._core.physics import padded_shape
    from napari_lbs._core.physics import random_particle_field, simulate_hologram
    from napari_lbs._core.foundation import check_memory

    config, out = request.config, Path(request.out_dir)
    size = request.size_px if request.size_px is not None else config.tile.size
    count = request.particles if request.particles is not None else config.particles.per_tile
    optics = config.optics
    grid = padded_shape((size, size), z_max_um=config.volume.z_max_um, wavelength_um=optics.wavelength_um, pixel_um=optics.pixel_um, medium_index=optics.medium_index)
    check_memory(_SIMULATION_BYTES_PER_PX * grid[0] * grid[1], what=f"a {size}x{size} simulation ({grid[0]}x{grid[1]} padded)", remedy="use a smaller --size")
    if request.frames is not None:
        return _simulate_recording(request, size=size, count=count, progress=progress, should_stop=should_stop)
    field_ = random_particle_field(
        (size, size),
        count=count,
        diameter_min_um=config.particles.diameter_min_um,
        diameter_max_um=config.particles.diameter_max_um,
        layers_um=config.layer_depths_um(),
        pixel_um=optics.pixel_um,
        seed=request.seed,
    )
    hologram = simulate_hologram(field_, wavelength_um=optics.wavelength_um, medium_index=optics.medium_index, shadowing=request.shadowing)
    out.mkdir(parents=True, exist_ok=True)
    description = provenance(config, seed=request.seed, particles=len(field_), shadowing=request.shadowing, pixel_um=optics.pixel_um)
    with tiff_pages(out / "hologram.tif", hologram.shape, description=description) as page:
        page[:] = hologram
    write_particles(out / "particles.csv", field_.table())
    paths = (out / "hologram.tif", out / "particles.csv")
    return StepResult(f"simulated a {size}x{size} hologram of {len(field_)} particles -> {paths[0]}, {paths[1]}", field_, paths)


def _simulate_recording(request: SimulateRequest, *, size: int, count: int, progress, should_stop) -> StepResult:
    """``frames.tif`` (one page per frame, written as it is simulated) and the truth with frame and track."""
    import numpy as np

    from napari_lbs._core.recordings import simulate_sequence
    from napari_lbs._core.foundation import tiff_pages, write_particles
    from napari_lbs._core.foundation import check_disk

    config, out, frames = request.config, Path(request.out_dir), request.frames
    check_disk(frames * size * size * np.dtype(np.float32).itemsize, out, what=f"{frames} frames of {size}x{size} pixels", remedy="use fewer --frames or a smaller --size")
    out.mkdir(parents=True, exist_ok=True)
    description = provenance(config, seed=request.seed, particles=count, shadowing=request.shadowing, pixel_um=config.optics.pixel_um, flow=request.flow,
                             speed_um=request.speed_um, frames=frames)
    with tiff_pages(out / "frames.tif", (frames, size, size), description=description) as pages:
        truth = simulate_sequence(config, frames=frames, flow=request.flow, size=size, count=count, speed_um=request.speed_um, seed=request.seed,
                                  shadowing=request.shadowing, out=pages, progress=progress, should_stop=should_stop).truth
    write_particles(out / "particles.csv", truth)
    tracks = len(np.unique(truth["track"]))
    paths = (out / "frames.tif", out / "particles.csv")
    return StepResult(f"simulated {frames} frames of {size}x{size} pixels, {count} particles in a {request.flow} flow ({tracks} tracks) -> {paths[0]}, {paths[1]}", truth, paths)


# --- backprop ------------------------------------------------------------------------------


@dataclass(frozen=True)
class BackpropRequest:
    """A hologram back-propagated to the config's planes, as a float32 ``(z, y, x)`` TIFF.

    Attributes
    ----------
    hologram : path or 2-D array
    out_path : Path
        The stack; its ImageDescription JSON holds ``z_um`` and the provenance.
    config : ExperimentConfig
    background_path : path, optional
        A hologram taken without particles, divided out.
    source : str, optional
        The hologram's name in the provenance (default: its path).
    """

    hologram: str | Path | np.ndarray
    out_path: Path
    config: ExperimentConfig = ExperimentConfig()
    background_path: str | Path | None = None
    source: str | None = None


def backprop(request: BackpropRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Back-propagate a hologram into a z-stack TIFF, written plane by plane to disk."""
    import numpy as np

    from napari_lbs._core.foundation import tiff_pages
    from napari_lbs._core.physics import backpropagate
    from napari_lbs._core.foundation import check_disk

    config, out = request.config, Path(request.out_path)
    hologram = _hologram(request.hologram, log=log)
    background = _background(request.background_path, hologram.shape, log=log)
    z_um = config.volume.planes_um()
    check_disk(len(z_um) * hologram.size * np.dtype(np.float32).itemsize, out, what=f"{len(z_um)} planes of {hologram.shape[0]}x{hologram.shape[1]} pixels",
               remedy="raise volume.z_step_um or write elsewhere")
    source = _source(request.hologram, request.source)
    description = {"z_um": list(z_um), **provenance(config, source=source, background=request.background_path and str(request.background_path))}
    start = time.perf_counter()
    # Written straight into a memory-mapped TIFF: a deep stack never has to fit in RAM.
    with tiff_pages(out, (len(z_um),) + hologram.shape, description=description) as stack:
        backpropagate(hologram, z_um, wavelength_um=config.optics.wavelength_um, pixel_um=config.optics.pixel_um, medium_index=config.optics.medium_index,
                      background=background, out=stack, progress=progress, should_stop=should_stop)
    seconds = time.perf_counter() - start
    return StepResult(f"back-propagated {source} to {len(z_um)} planes ({z_um[0]:g}-{z_um[-1]:g} µm) in {seconds:.1f} s -> {out}", z_um, (out,))


# --- calibrate -----------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrateRequest:
    """Holo-processing fitted to one tile of a real hologram, written as calibration JSON.

    Attributes
    ----------
    hologram : path or 2-D array
    out_path : Path
    config : ExperimentConfig
    settings : CalibrationSettings, optional
        How to fit (default: `CalibrationSettings`'s defaults).
    roi : (x, y), optional
        Top-left pixel of the reference tile (default: the tool picks).
    background_path : path, optional
    source : str, optional
        The hologram's name in the provenance (default: its path).
    """

    hologram: str | Path | np.ndarray
    out_path: Path
    config: ExperimentConfig = ExperimentConfig()
    settings: CalibrationSettings | None = None
    roi: tuple[int, int] | None = None
    background_path: str | Path | None = None
    source: str | None = None


def calibrate(request: CalibrateRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Calibrate Holo-processing (`calibrate_hologram`) and write the calibration JSON with its provenance."""
    from napari_lbs._core.calibration import CalibrationSettings, calibrate_hologram

    config, settings = request.config, request.settings or CalibrationSettings()
    hologram = _hologram(request.hologram, log=log)
    background = _background(request.background_path, hologram.shape, log=log)
    result = calibrate_hologram(hologram, config, roi=request.roi, background=background, settings=settings, progress=progress, should_stop=should_stop)
    payload = result.to_json()
    payload["provenance"] = provenance(config, source=_source(request.hologram, request.source), background=request.background_path and str(request.background_path), seed=settings.seed)
    write_json(request.out_path, payload)
    p = result.params
    x, y, size = result.roi
    chosen = "" if request.roi else f" (chosen: {result.roi_choice})"
    summary = (f"calibrated on the {size}² tile at x={x}, y={y}{chosen}: N_R={p.N_R:.4f}, N_sigma={p.N_sigma:.4f}, gamma={p.gamma:.4f}, "
               f"SSIM={result.ssim:.4f}, {result.evaluations} evaluations in {result.seconds:.1f} s -> {request.out_path}")
    return StepResult(summary, result, (Path(request.out_path),))


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
        ``processing`` is given.
    processing : InputProcessing, optional
        How inputs are made (default: the calibration's, else none: the seed's normal simulation).
    effects : mapping
        ``{effect_id: {param: value}}`` added to every hologram (`requested_effects`).
    effects_source : dict, optional
        Where the effects came from, recorded in the data set.
    layout : DatasetLayout, optional
    distractors : Distractors, optional
    seed : int
    workers : int
        Processes simulating groups at once.
    """

    out_dir: Path
    config: ExperimentConfig = ExperimentConfig()
    groups: int = 256
    calibration_path: str | Path | None = None
    processing: InputProcessing | None = None
    effects: Mapping = field(default_factory=dict)
    effects_source: dict | None = None
    layout: DatasetLayout | None = None
    distractors: Distractors | None = None
    seed: int = 0
    workers: int = 1


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


def generate(request: GenerateRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> StepResult:
    """Write the synthetic training set (`generate_dataset`)."""
    from napari_lbs._core.learning import DatasetLayout, InputProcessing, generate_dataset
    from napari_lbs._core.physics import Distractors

    calibration = read_calibration(request.calibration_path) if request.calibration_path else None
    processing = request.processing or (InputProcessing.from_calibration(calibration) if calibration else InputProcessing())
    distractors = request.distractors or Distractors()
    effects = dict(request.effects)
    start = time.perf_counter()
    dataset = generate_dataset(request.out_dir, request.config, groups=request.groups, processing=processing, layout=request.layout or DatasetLayout(),
                               calibration=calibration, effects=effects, effects_source=request.effects_source, distractors=distractors, seed=request.seed,
                               workers=request.workers, progress=progress, should_stop=should_stop)
    seconds = time.perf_counter() - start
    planes = len(dataset.groups) * len(dataset.planes_um)
    kind = f"calibrated ({request.calibration_path})" if request.processing is None and calibration else "uncalibrated: Holo-processing (0, 0, 1)"
    added = f", effects: {', '.join(effects)}" if effects else ""
    if request.effects_source and "report" in request.effects_source and not effects:
        added = f", no effects: {request.effects_source['report']} names none"
    if distractors.active:
        added += f", unlabelled distractors: {distractors.impurities_per_tile} impurities per tile, neighbours in a {distractors.neighbours_margin_px}-pixel margin"
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
        Continue from ``out_path``'s ``.last.pt``.
    """

    data: str | Path
    out_path: Path
    settings: TrainingSettings | None = None
    resume: bool = False


def train(request: TrainRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Train the U-Net (`train_model`); a data set with missing groups trains on those present, with a warning."""
    from napari_lbs._core.learning import open_dataset
    from napari_lbs._core.learning import TrainingSettings, train_model

    settings = request.settings or TrainingSettings()
    dataset = open_dataset(request.data)
    expected = int(dataset.spec["groups"])
    if len(dataset.groups) < expected:  # a stopped generate, or group files removed since
        log(f"{request.data}: warning: {len(dataset.groups)} of {expected} groups present; training on those (run generate again to finish the set)")
    result = train_model(dataset, request.out_path, settings=settings, resume=request.resume, progress=progress, should_stop=should_stop)
    best = result.log["best"]
    record = next(e for e in result.log["epochs"] if e["epoch"] == best["epoch"])["validation"]
    stopped = f" ({result.log['stop_reason']})" if result.stopped else ""
    summary = (f"trained {settings.preset} ({settings.formulation}) for {len(result.log['epochs'])} epochs in {result.log['seconds']:.0f} s{stopped}; best epoch {best['epoch']}: "
               f"validation ER {100 * record['er']:.2f} %, JI {record['ji']:.3f} (one-to-one, held-out synthetic groups) -> {request.out_path}")
    return StepResult(summary, result, (Path(result.model_path),))


# --- predict -------------------------------------------------------------------------------


@dataclass(frozen=True)
class PredictRequest:
    """The particles of a hologram or a recording, found by a trained model.

    Attributes
    ----------
    inputs : sequence of paths, or a 2-D array
        Image files, folders, glob patterns, multi-page TIFFs or videos (`open_frames`); frames
        numbered in this order. An array is one hologram already read.
    model : path or LoadedModel
    out_path : Path
        The particle table (CSV, or Parquet for ``.parquet``); provenance beside it as ``.json``.
    config : ExperimentConfig, optional
        Optics and depths (default: the model's).
    background_path : path, optional
        A hologram taken without particles, divided out of every frame.
    device : str
    precision : str
        The network's arithmetic: ``auto``, ``float32`` or ``bfloat16`` (`resolve_precision`).
    force : bool
        Run a model made for other optics or depths than the config's.
    sequence_background : str
        Recordings without a background file: ``auto``, ``global``, ``running``, ``flat`` or ``none`` (`predict_sequence`).
    background_window : int
        Frames of a running background.
    workers : int, optional
        Recordings: a local dask cluster of this many workers.
    scheduler : str, optional
        Recordings: an existing dask.distributed scheduler's address.
    source : str, optional
        The hologram's name in the provenance when ``inputs`` is an array.
    refine : bool
        Refine every detection by a Lorenz–Mie fit (`refine_particles`); the table gains its columns.
    threshold : float, optional
        The smallest score a detection keeps (`predict_particles`); default the model's, and
        with ``refine`` `REFINE_PROPOSAL_FRACTION` of it.
    material_index_contrast : float, optional
        The sample's ``n_p - n_m`` (implies ``refine``); particles of another material
        (`same_material`) are listed in the provenance instead of the table.
    """

    inputs: Sequence[str | Path] | np.ndarray
    model: str | Path | LoadedModel
    out_path: Path
    config: ExperimentConfig | None = None
    background_path: str | Path | None = None
    device: str = "auto"
    precision: str = "auto"
    force: bool = False
    sequence_background: str = "auto"
    background_window: int = 21
    workers: int | None = None
    scheduler: str | None = None
    source: str | None = None
    refine: bool = False
    threshold: float | None = None
    material_index_contrast: float | None = None


# With a fit to check them, detections are proposed at this fraction of the model's score
# threshold: on the development holograms of docs/refinement.md the fit turned the extra
# proposals into the spheres the network had scored just below its threshold (sizes beyond
# its training range, overlapping holograms), and kept few false ones, down to 0.8 of it.
REFINE_PROPOSAL_FRACTION = 0.8


def _proposal_threshold(meta: dict, threshold: float | None) -> float:
    """The score down to which a refined prediction proposes: ``threshold``, else `REFINE_PROPOSAL_FRACTION` of the model's."""
    return float(threshold) if threshold is not None else REFINE_PROPOSAL_FRACTION * float(meta["threshold"])


def _network_proposals(model, config: ExperimentConfig | None, *, threshold: float, device: str, precision: str, force: bool, progress, should_stop):
    """``propose(image)``: the network's proposals (down to ``threshold``) in an image as the fit sees it (divided by the background, else by its mean), for `residual_particles`."""
    from napari_lbs._core.learning import predict_particles

    return lambda image: predict_particles(image, model, config, device=device, precision=precision, force=force, threshold=threshold, progress=progress,
                                           should_stop=should_stop).particles


def refined_prediction(hologram: np.ndarray, model, config: ExperimentConfig | None = None, *, background: np.ndarray | None = None, device: str = "auto",
                       precision: str = "auto", force: bool = False, threshold: float | None = None, material_index_contrast: float | None = None,
                       progress: ProgressCallback | None = None, should_stop: StopCallback | None = None):
    """`predict_particles` down to `REFINE_PROPOSAL_FRACTION` of the model's threshold (or ``threshold``), then `refine_particles`.

    The fit sees the hologram divided by ``background``, else by its mean. The network then
    looks again in what the refined table leaves unexplained (`residual_particles`: spheres
    hidden in their neighbours' fringes, sizes it scored low), and the sample's particles
    the fit measures there join the table. Returns a `PredictionResult` whose particles are
    the refined table (`REFINE_COLUMNS` after the first four) and whose provenance gains
    ``refine`` (settings, counts, seconds; ``residual``: the second look's proposals, finds
    and seconds). With
    ``material_index_contrast`` (the sample's ``n_p - n_m``) the fits start there and the
    particles of another material (`same_material`) leave the table for the provenance's
    ``refine.material.other_particles``. ``progress`` counts the prediction's planes, then
    the fit's batches, then the same for the second look.
    """
    import numpy as np

    from napari_lbs._core.learning import LoadedModel, load_model
    from napari_lbs._core.learning import PredictionResult, predict_particles

    started = time.perf_counter()
    model = model if isinstance(model, LoadedModel) else load_model(model, device=device)
    proposal = _proposal_threshold(model.meta, threshold)
    result = predict_particles(hologram, model, config, background=background, device=device, precision=precision, force=force,
                               threshold=proposal, progress=progress, should_stop=should_stop)
    normalised = np.asarray(hologram, dtype=np.float64) / (background if background is not None else float(np.mean(hologram)))
    propose = _network_proposals(model, config, threshold=proposal, device=device, precision=precision, force=force, progress=progress,
                                 should_stop=should_stop)
    particles, record = _refined(normalised, result.particles, config or model.config, material=material_index_contrast, device=device, propose=propose,
                                 progress=progress, should_stop=should_stop)
    return PredictionResult(particles, {**result.provenance, "refine": record}, time.perf_counter() - started)


def prediction_outputs(out_path) -> tuple[Path, Path]:
    """The particle table and its provenance JSON, refused where they would overwrite something else."""
    from napari_lbs._core.foundation import check_table_name

    out = Path(out_path)
    if out.suffix.lower() == ".json":
        raise InputError(f"--out {out}: expected a particle table (.csv, or .parquet); its provenance is written beside it as .json")
    check_table_name(out)  # a Parquet table without pyarrow is refused now, not after the work
    record = out.with_suffix(".json")
    if record.is_file():
        try:
            previous = json.loads(record.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            previous = None
        # only a previous run's provenance of this same table may be replaced (never a model's training log)
        if not (isinstance(previous, dict) and previous.get("particles") == str(out) and "model_sha256" in previous):
            raise InputError(f"--out {out}: {record} exists and is not this table's provenance; choose another name")
    return out, record


def _write_table(out: Path, record_path: Path, particles: dict, record: dict) -> None:
    """The particle table (CSV, or Parquet with ``record`` in its key-value metadata too) and its provenance JSON beside it."""
    from napari_lbs._core.foundation import write_particles

    write_particles(out, particles, metadata=record)
    write_json(record_path, record)


def predict(request: PredictRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Predict the particles of one hologram, or of every frame of a recording (one table with a ``frame`` column)."""
    from napari_lbs._core.learning import load_model
    from napari_lbs._core.learning import predict_particles
    from napari_lbs._core.recordings import open_frames

    out, record_path = prediction_outputs(request.out_path)
    if isinstance(request.inputs, (str, Path, list, tuple)):
        inputs = [request.inputs] if isinstance(request.inputs, (str, Path)) else list(request.inputs)
        with open_frames(inputs) as frames:
            if len(frames) > 1:
                return _predict_recording(request, frames, out, record_path, progress=progress, should_stop=should_stop, log=log)
            # one frame (an image, a one-page TIFF, a one-frame video): the single-hologram path
            source, hologram = frames.name(0), frames.read(0, log=log)
    else:
        source, hologram = _source("array", request.source), request.inputs
    background = _background(request.background_path, hologram.shape, log=log)
    model = request.model if not isinstance(request.model, (str, Path)) else load_model(request.model, device=request.device)
    options = {"background": background, "device": request.device, "precision": request.precision, "force": request.force, "threshold": request.threshold,
               "progress": progress, "should_stop": should_stop}
    refine = request.refine or request.material_index_contrast is not None  # the fit measures the material
    if refine:
        options["material_index_contrast"] = request.material_index_contrast
    result = (refined_prediction if refine else predict_particles)(hologram, model, request.config, **options)
    particles, provenance = result.particles, result.provenance
    refined = _refine_summary(provenance["refine"]) if refine else ""
    _write_table(out, record_path, particles, {**provenance, "source": str(source), "background_file": request.background_path, "particles": str(out)})
    count = provenance["refine"]["detections"] if refine else len(particles["x_um"])
    return StepResult(f"found {count} particles in {source} in {result.seconds:.1f} s{refined} -> {out} (provenance: {record_path})", result, (out, record_path))


def _refine_summary(record: dict) -> str:
    """What the fit did, for a prediction's one-line summary."""
    line = f", {record['kept']} kept by the fit in {record['seconds']:.1f} s, {record['residual']['found']} more found in its residual"
    if "material" in record:
        line += f", {record['material']['other_material']} of another material than {record['material']['index_contrast']:g} left out"
    return line


def _refined_frames(frames, particles: dict, config: ExperimentConfig, *, background, material: float | None, device: str, propose, log: Log, progress,
                    should_stop) -> tuple[dict, dict]:
    """Each frame's rows of a recording's table refined on that frame (divided by the background file, else by its mean)."""
    import numpy as np

    frame_of = np.asarray(particles["frame"]).astype(np.int64)
    parts, records = [], []
    for index in np.unique(frame_of):
        rows = frame_of == index
        hologram = np.asarray(frames.read(int(index), log=log), dtype=np.float64)
        divisor = background if isinstance(background, np.ndarray) else float(hologram.mean())
        table, record = _refined(hologram / divisor, {name: np.asarray(values)[rows] for name, values in particles.items()}, config, material=material, device=device,
                                 propose=propose, progress=progress, should_stop=should_stop)
        if len(table["x_um"]) and "frame" in table:
            table["frame"] = np.full(len(table["x_um"]), index, dtype=np.asarray(particles["frame"]).dtype)
        parts.append(table)
        records.append(record)
    merged = {name: np.concatenate([part[name] for part in parts]) for name in parts[0]} if parts else particles
    summary = {"settings": records[0]["settings"] if records else None, "detections": sum(r["detections"] for r in records),
               "kept": sum(r["kept"] for r in records), "seconds": sum(r["seconds"] for r in records),
               "residual": {key: sum(r["residual"][key] for r in records) for key in ("proposals", "found", "seconds")}}
    if material is not None:
        from napari_lbs._core.refine import MATERIAL_SIGMAS, MATERIAL_TOLERANCE

        others = [r["material"]["other_particles"] for r in records]
        summary["material"] = {"index_contrast": float(material), "tolerance": MATERIAL_TOLERANCE, "sigmas": MATERIAL_SIGMAS,
                               "other_material": sum(r["material"]["other_material"] for r in records),
                               "other_particles": {name: [value for table in others for value in table[name]] for name in (others[0] if others else particles)}}
    return merged, summary


def _refined(hologram: np.ndarray, particles: dict, config: ExperimentConfig, *, material: float | None, device: str, propose, progress,
             should_stop) -> tuple[dict, dict]:
    """The particle table refined by `refine_particles`, with the finds in its residual (`residual_particles`, ``propose``), of the ``material`` where given (as a dict of arrays), and its provenance."""
    from dataclasses import asdict

    import numpy as np
    import pandas as pd

    from napari_lbs._core.refine import MATERIAL_SIGMAS, MATERIAL_TOLERANCE, same_material
    from napari_lbs._core.refine import RefineSettings, refine_particles
    from napari_lbs._core.refine import residual_particles
    from napari_lbs._core.foundation import available_threads

    # the prediction's device (CUDA where it ran there); on the CPU one fitting process per core;
    # a declared material is also where every fit starts
    settings = RefineSettings(device=device, workers=available_threads(), **({} if material is None else {"index_contrast": float(material)}))
    started = time.perf_counter()
    table = refine_particles(hologram, pd.DataFrame(particles), config, settings=settings, progress=progress, should_stop=should_stop)
    record = {"settings": asdict(settings), "detections": len(particles["x_um"]), "kept": len(table), "seconds": time.perf_counter() - started}
    started = time.perf_counter()
    proposals = []

    def counted(image):
        proposals.append(propose(image))
        return proposals[-1]

    if len(table) and table["refined"].any():  # with nothing refined, the residual is the hologram the network has seen
        found = residual_particles(hologram, table, config, propose=counted, settings=settings, background=np.ones(hologram.shape), progress=progress,
                                   should_stop=should_stop)
        table = pd.concat([table, found], ignore_index=True) if len(found) else table
    record["residual"] = {"proposals": len(pd.DataFrame(dict(proposals[0]))) if proposals else 0, "found": len(table) - record["kept"], "seconds": time.perf_counter() - started}
    if material is not None:
        member = same_material(table, index_contrast=material, tolerance=MATERIAL_TOLERANCE, sigmas=MATERIAL_SIGMAS)
        record["material"] = {"index_contrast": float(material), "tolerance": MATERIAL_TOLERANCE, "sigmas": MATERIAL_SIGMAS, "other_material": int((~member).sum()),
                              "other_particles": {name: table[name].to_numpy()[~member].tolist() for name in table.columns}}
        table = table[member]
    return {name: table[name].to_numpy() for name in table.columns}, record


def _predict_recording(request: PredictRequest, frames, out: Path, record_path: Path, *, progress, should_stop, log: Log) -> StepResult:
    """A recording: one table with a ``frame`` column; finished frames kept in OUT.parts/ until the table is written."""
    from napari_lbs._core.foundation import read_hologram
    from napari_lbs._core.learning import load_model
    from napari_lbs._core.recordings import predict_sequence

    work_dir = check_output_path(out.with_name(out.name + ".parts"), flag="--out", folder=True)
    background = read_hologram(request.background_path, log=log) if request.background_path else request.sequence_background
    model = load_model(request.model, device="cpu")  # each worker moves it to the device
    refine = request.refine or request.material_index_contrast is not None  # the fit measures the material
    result = predict_sequence(frames, model, request.config, background=background, background_window=request.background_window, workers=request.workers,
                              scheduler=request.scheduler, force=request.force, work_dir=work_dir, device=request.device, precision=request.precision,
                              threshold=_proposal_threshold(model.meta, request.threshold) if refine else request.threshold, progress=progress,
                              should_stop=should_stop)
    particles, provenance = result.particles, dict(result.provenance)
    if refine:
        # the second look runs in this process, on the prediction's device (the workers moved their own copies there)
        looker = load_model(request.model, device=request.device) if isinstance(request.model, (str, Path)) else model
        propose = _network_proposals(looker, request.config, threshold=_proposal_threshold(model.meta, request.threshold), device=request.device,
                                     precision=request.precision, force=request.force, progress=progress, should_stop=should_stop)
        particles, provenance["refine"] = _refined_frames(frames, particles, request.config or model.config, background=background,
                                                          material=request.material_index_contrast, device=request.device, propose=propose, log=log,
                                                          progress=progress, should_stop=should_stop)
    _write_table(out, record_path, particles, {**provenance, "background_file": request.background_path, "particles": str(out)})
    shutil.rmtree(work_dir)
    count, done = len(result.particles["x_um"]), result.provenance["frames"]
    resumed = f"; {result.resumed} frames resumed from {work_dir}" if result.resumed else ""
    refined = _refine_summary(provenance["refine"]) if refine else ""
    return StepResult(f"found {count} particles in {done} frames in {result.seconds:.1f} s ({result.provenance['scheduler']}{resumed}){refined} -> {out} "
                      f"(provenance: {record_path})", result, (out, record_path))


# --- track ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrackRequest:
    """The particles of a recording linked into 3-D tracks.

    Attributes
    ----------
    particles_path : path
        A particle table with a ``frame`` column (CSV or ``.parquet``).
    out_path : Path
        The tracks table; its provenance beside it as ``.json``.
    search_range_um : float
        Largest displacement between two frames a particle is seen in (µm).
    axial_search_range_um : float, optional
        A separate search range along z (µm).
    memory : int
        Frames a particle may be missed and keep its track.
    """

    particles_path: str | Path
    out_path: Path
    search_range_um: float = 60.0
    axial_search_range_um: float | None = None
    memory: int = 0


def track(request: TrackRequest) -> StepResult:
    """Link tracks (`link_tracks`) and write them with the prediction's provenance."""
    import numpy as np

    from napari_lbs._core.foundation import check_table_name, read_particles, write_particles
    from napari_lbs._core.recordings import DISPLACEMENT_COLUMNS, link_tracks

    prediction_json = Path(request.particles_path).with_suffix(".json")
    out = check_table_name(check_output_path(request.out_path, flag="--out", inputs=[request.particles_path, prediction_json]))
    # the tracks' provenance beside them, never over the prediction's own
    provenance_json = check_output_path(out.with_suffix(".json"), flag="--out", inputs=[request.particles_path, prediction_json])
    table = read_particles(request.particles_path)
    if "frame" not in table:
        raise InputError(f"{request.particles_path}: no frame column; tracks need the table of a recording (predict with several frames)")
    tracks = link_tracks(table, search_range_um=request.search_range_um, axial_search_range_um=request.axial_search_range_um, memory=request.memory)
    linking = {"particles": str(request.particles_path), "search_range_um": request.search_range_um, "axial_search_range_um": request.axial_search_range_um, "memory": request.memory}
    if out.suffix.lower() != ".parquet":  # a track's last detection has no displacement: an empty CSV cell (Parquet keeps NaN)
        for name in DISPLACEMENT_COLUMNS:
            tracks[name] = np.array(["" if np.isnan(value) else f"{value:.9g}" for value in tracks[name]], dtype=object)
    record = {"particles": str(out), "tracks": linking}
    if prediction_json.is_file():  # what made the detections: model, settings, frames
        try:
            record["prediction"] = json.loads(prediction_json.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            record["prediction"] = None
    write_particles(out, tracks, metadata=record)
    write_json(provenance_json, record)
    lengths = np.bincount(tracks["track"]) if tracks["track"].size else np.zeros(0, int)
    frames = len(np.unique(tracks["frame"]))
    return StepResult(f"linked {tracks['track'].size} particles of {frames} frames into {lengths.size} tracks (median length {np.median(lengths) if lengths.size else 0:g} frames) -> {out}",
                      tracks, (out, provenance_json))


# --- diagnose ------------------------------------------------------------------------------


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
    paths = write_report(diagnosis, request.out_dir, provenance=record)
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


# --- demo ----------------------------------------------------------------------------------

# The built-in sample's spheres: polystyrene (n 1.59) in water (n 1.33), all light transmitted;
# the phase delay through a sphere's centre is 2π · 0.26 · d / 0.66 µm (62 rad at 25 µm).
DEMO_SAMPLE_EFFECTS = {"particle_phase": {"index_contrast": 0.26, "transmission": 1.0}}
# Its unlabelled distractors (`Distractors`): small foci of debris in the water, and the
# fringes of spheres outside the crop near its edges.
DEMO_SAMPLE_DISTRACTORS = {"impurities_per_tile": 6, "impurity_diameter_min_um": 4.0, "impurity_diameter_max_um": 14.0, "neighbours_margin_px": 96}
# The demo's training budget: a safety stop for a machine many times slower or busier than 2
# idle cores, never the normal end (the summary's ``stop_reason`` says when it ended training).
DEMO_SAFETY_MINUTES = 60.0


@dataclass(frozen=True)
class DemoRequest:
    """The whole pipeline on the built-in real hologram.

    Attributes
    ----------
    out_dir : Path
    quick : bool
        A token run on one tile (about a minute): checks the plumbing.
    calibrated : bool
        Train on the seed's LBS data (calibrated Holo-processing of opaque discs) instead of
        transparent spheres with the sample's distractors.
    seed : int
    """

    out_dir: Path
    quick: bool = False
    calibrated: bool = False
    seed: int = 0


def demo(request: DemoRequest, *, progress_for: Callable[[str], ProgressCallback | None] = lambda step: None, log: Log = _quiet) -> StepResult:
    """Back-propagate, calibrate, generate, train, predict and refine on the built-in sample; ``summary.json`` records it all.

    The particle table is the refined prediction (`refined_prediction`) of the sample's
    material, polystyrene in water; the particles of another material are in its provenance.
    ``progress_for(step)`` gives the progress callback of each step (``backprop``,
    ``calibrate``, ``generate``, ``train``, ``predict``: the prediction's planes, then the
    fit's batches).
    """
    from napari_lbs._core.calibration import CalibrationSettings
    from napari_lbs._core.learning import InputProcessing
    from napari_lbs._core.foundation import SAMPLE_PROVENANCE, load_sample_hologram
    from napari_lbs._core.physics import Distractors
    from napari_lbs._core.learning import TrainingSettings

    out, seed = Path(request.out_dir), request.seed
    out.mkdir(parents=True, exist_ok=True)
    config = ExperimentConfig()
    hologram = load_sample_hologram()
    if request.quick:  # one tile, a token of each step: checks the plumbing in about a minute
        hologram = hologram[:256, :256]
        config = replace(config, particles=replace(config.particles, per_tile=6))
        calibration_settings, groups = CalibrationSettings(generations=4, population=6, fields=1, seed=seed), 3
        training = TrainingSettings(epochs=1, patch_size=64, validation_groups=1, minutes=DEMO_SAFETY_MINUTES, seed=seed)
    else:
        # A fixed amount of work, so that the model depends on the seed and not on the machine's
        # speed or load: 5 epochs of the focus formulation, the last 2 validated (the best of them
        # kept), about 6 minutes on 2 idle cores. On the Lorenz-Mie pseudo-real holograms
        # (benchmarks/results/learning/demo_epochs_pseudoreal.log) it finds as many spheres as 8
        # epochs did (JI 1.000 / 0.975 at 4x / 0.935 with distractors, against 1.000 / 0.978 /
        # 0.917); its diameters are less sharp (median error 0.9-1.3 um against 0.7-0.8 um).
        calibration_settings, groups = CalibrationSettings(generations=40, seed=seed), 64
        training = TrainingSettings(epochs=5, validate_last=2, minutes=DEMO_SAFETY_MINUTES, seed=seed)
    sample = SAMPLE_PROVENANCE["source"]
    timings = {}
    start = time.perf_counter()
    stacked = backprop(BackpropRequest(hologram, out / "zstack.tif", config, source=sample), progress=progress_for("backprop"))
    timings["backprop"] = time.perf_counter() - start

    start = time.perf_counter()
    calibration = calibrate(CalibrateRequest(hologram, out / "calibration.json", config, settings=calibration_settings, source=sample),
                            progress=progress_for("calibrate")).value.to_json()
    timings["calibrate"] = time.perf_counter() - start

    if request.calibrated:  # the seed's LBS: calibrated Holo-processing of opaque discs
        processing, effects, distractors = InputProcessing.from_calibration(calibration), {}, Distractors()
        data = f"{groups} better-synthetic groups of {config.tile.size}² (calibrated Holo-processing)"
    else:
        # What the sample is (polystyrene spheres in water) rather than the calibration: on the
        # Lorenz-Mie pseudo-real benchmark, calibrated data scored JI 0.21 where the seed's plain
        # simulation with these transparent spheres scored 0.86 (0.83 against 0.45 at 4x the density).
        # Its distractors too (unlabelled): on the pseudo-real hologram with debris and spheres
        # outside the crop, a model trained without them reported 20 false particles among 119.
        processing, effects, distractors = InputProcessing(), dict(DEMO_SAMPLE_EFFECTS), Distractors(**DEMO_SAMPLE_DISTRACTORS)
        data = (f"{groups} synthetic groups of {config.tile.size}² of transparent spheres (particle_phase: index contrast {effects['particle_phase']['index_contrast']:g}), "
                f"uncalibrated, with unlabelled distractors ({distractors.impurities_per_tile} impurities of {distractors.impurity_diameter_min_um:g}-{distractors.impurity_diameter_max_um:g} µm "
                f"per tile, neighbours in a {distractors.neighbours_margin_px}-pixel margin)")
    start = time.perf_counter()
    source = {"explicit": ["the built-in sample: polystyrene (n 1.59) spheres in water (n 1.33), 25 um, 660 nm"]} if effects else None
    generate(GenerateRequest(out / "data", config, groups=groups, calibration_path=out / "calibration.json", processing=processing, effects=effects, effects_source=source,
                             distractors=distractors, seed=seed), progress=progress_for("generate"))
    timings["generate"] = time.perf_counter() - start

    start = time.perf_counter()
    trained = train(TrainRequest(out / "data", out / "model.pt", settings=training), progress=progress_for("train"), log=log).value
    if trained.log["stop_reason"]:
        log(f"demo: warning: training ended early ({trained.log['stop_reason']}) after {len(trained.log['epochs'])} of {training.epochs} epochs; another run with this seed may differ")
    timings["train"] = time.perf_counter() - start

    # Every detection refined by the Lorenz-Mie fit (about 20 s for the sample's 100 particles on
    # 2 cores, a small share of the demo's minutes), and the sample's material kept: its debris
    # fit as small spheres of another index contrast (docs/refinement.md).
    predicted = predict(PredictRequest(hologram, trained.model_path, out / "particles.csv", config, device=training.device, source=sample, refine=True,
                                       material_index_contrast=DEMO_SAMPLE_EFFECTS["particle_phase"]["index_contrast"]), progress=progress_for("predict"))
    result = predicted.value
    refined = result.provenance["refine"]
    timings["predict"] = result.seconds - refined["seconds"] - refined["residual"]["seconds"]
    timings["refine"] = refined["seconds"]
    timings["residual"] = refined["residual"]["seconds"]
    best = trained.log["best"]
    validation = next(e for e in trained.log["epochs"] if e["epoch"] == best["epoch"])["validation"]
    z_um = stacked.value
    summary = {
        "hologram_shape": list(hologram.shape),
        "planes": len(z_um),
        "z_um": [z_um[0], z_um[-1]],
        "zstack": str(stacked.paths[0]),
        "calibration": {"params": calibration["params"], "ssim": calibration["ssim"], "roi": calibration["roi"]},
        "groups": groups,
        "model": str(trained.model_path),
        "model_sha256": best["sha256"],
        "weights_sha256": best["weights_sha256"],
        "training": {"formulation": training.formulation, "preset": training.preset, "epochs_done": len(trained.log["epochs"]), "epochs_planned": training.epochs,
                     "stop_reason": trained.log["stop_reason"], "threads": trained.log["threads"],
                     "data": f"{data}, the last {len(trained.log['validation_groups'])} held out", "effects": effects,
                     "distractors": distractors.to_dict() if distractors.active else None, "calibrated": bool(request.calibrated)},
        "validation": {key: validation.get(key) for key in ("er", "ji", "tp", "fp", "fn", "threshold", "axial_um", "median_abs_dz_um", "median_abs_dd_um")},
        "particles": str(predicted.paths[0]),
        "particle_count": len(result.particles["x_um"]),
        "refine": {"proposals": refined["detections"], "kept_by_fit": refined["kept"], "found_in_residual": refined["residual"]["found"],
                   "material_index_contrast": refined["material"]["index_contrast"], "other_material": refined["material"]["other_material"]},
        "seconds": {key: round(value, 2) for key, value in timings.items()},
        "sample": SAMPLE_PROVENANCE,
        "quick": bool(request.quick),
    }
    write_json(out / "summary.json", summary)
    line = (f"demo: calibration SSIM {calibration['ssim']:.3f} ({'used' if request.calibrated else 'recorded; --calibrated trains on it'}), {data}, "
            f"trained the {training.formulation} formulation ({training.preset}, {trained.log['seconds']:.0f} s; "
            f"validated on {len(trained.log['validation_groups'])} held-out synthetic groups: ER {100 * validation['er']:.1f} %, JI {validation['ji']:.3f}), "
            f"found {summary['particle_count']} particles in the built-in hologram ({refined['detections']} proposals fitted, {refined['residual']['found']} more found "
            f"in the fit's residual, {refined['material']['other_material']} of another material set apart) -> {out}")
    return StepResult(line, summary, (predicted.paths[0], out / "summary.json"))
