"""The ``napari-lbs`` console script: one sub-command per step, each a thin wrapper over `_core`.

Bad input exits 2 with one line naming the culprit (a file or a flag); an unexpected error
exits 1 with one line asking for a report (``--debug`` prints the traceback); success prints
a one-line summary on stderr. See CONTRACT.md and docs/reliability.md.

Outputs are checked before any work (`check_output_path`). Everything heavy is imported
inside the sub-commands, so ``napari-lbs --version`` or ``--help`` starts in a fraction of a
second.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
import traceback
from pathlib import Path

from napari_lbs import __version__
from napari_lbs._core._files import read_json_object
from napari_lbs._core._validation import InputError, check_output_path

# Failures that are the input's or the machine's, not the program's: exit 2 with one line.
_EXPECTED_ERRORS = (ValueError, OSError, MemoryError)


class _ProgressBar:
    """A terminal progress bar on stderr (silent when stderr is not a terminal)."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.enabled = sys.stderr.isatty()
        self.start = time.perf_counter()

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled or total <= 0:
            return
        width = 30
        filled = int(width * done / total)
        elapsed = time.perf_counter() - self.start
        sys.stderr.write(f"\r{self.label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total} {elapsed:.0f}s")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _summary(text: str) -> None:
    print(text, file=sys.stderr)


def _provenance(config, **extra) -> dict:
    return {"napari_lbs": __version__, "config": config.to_dict(), **extra}


def _settings(settings_class, **values):
    """``settings_class(**values)``, with a refused value named by its flag (``population:`` → ``--population:``)."""
    try:
        return settings_class(**values)
    except ValueError as error:
        name, _, rest = str(error).partition(":")
        if name in values:
            raise InputError(f"--{name.replace('_', '-')}:{rest}") from None
        raise


def _integer(low: int, high: int | None = None):
    """An argparse type: an integer in ``[low, high]``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected an integer {f'in [{low}, {high}]' if high is not None else f'of at least {low}'}, got {value}")
        return value

    return parse


def _number(low: float, high: float = math.inf, *, above: bool = False):
    """An argparse type: a finite number in ``[low, high]`` (``(low, high]`` with ``above``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value) or value < low or (above and value == low) or value > high:
            bounds = f"{'above' if above else 'at least'} {low:g}" + (f" and at most {high:g}" if math.isfinite(high) else "")
            raise argparse.ArgumentTypeError(f"expected a finite number {bounds}, got {text}")
        return value

    return parse


def _cmd_config(args) -> None:
    from napari_lbs._core import load_config, write_config

    if args.check:
        load_config(args.check)
        _summary(f"{args.check}: valid experiment config")
        return
    if not args.write:
        raise ValueError("--write: expected a file to write the default config to")
    path = write_config(check_output_path(args.write, flag="--write"))
    _summary(f"wrote the default experiment config to {path}")


# Peak memory of a simulation per pixel of its padded FFT grid (bytes), with a margin: the
# default config's 16 layers peak at 103 (256² window) to 141 (1024²) bytes (tracemalloc).
_SIMULATION_BYTES_PER_PX = 160


def _cmd_simulate(args) -> None:
    from napari_lbs._core import load_config, random_particle_field, simulate_hologram, write_particles
    from napari_lbs._core._optics import padded_shape
    from napari_lbs._core._validation import check_memory
    from napari_lbs._core._files import atomic_path

    import tifffile

    config = load_config(args.config)
    out = check_output_path(args.out, flag="--out", folder=True, inputs=[args.config])
    for name in ("hologram.tif", "particles.csv") if args.frames is None else ("frames.tif", "particles.csv"):
        check_output_path(out / name, flag="--out")
    size = args.size if args.size is not None else config.tile.size
    count = args.particles if args.particles is not None else config.particles.per_tile
    grid = padded_shape((size, size), z_max_um=config.volume.z_max_um, wavelength_um=config.optics.wavelength_um, pixel_um=config.optics.pixel_um, medium_index=config.optics.medium_index)
    check_memory(_SIMULATION_BYTES_PER_PX * grid[0] * grid[1], what=f"a {size}x{size} simulation ({grid[0]}x{grid[1]} padded)", remedy="use a smaller --size")
    if args.frames is not None:
        _simulate_sequence(args, config, out, size=size, count=count)
        return
    for flag, value in (("--flow", args.flow), ("--speed-um", args.speed_um)):
        if value is not None:
            raise InputError(f"{flag}: describes a recording; add --frames N")
    field = random_particle_field(
        (size, size),
        count=count,
        diameter_min_um=config.particles.diameter_min_um,
        diameter_max_um=config.particles.diameter_max_um,
        layers_um=config.layer_depths_um(),
        pixel_um=config.optics.pixel_um,
        seed=args.seed,
    )
    hologram = simulate_hologram(field, wavelength_um=config.optics.wavelength_um, medium_index=config.optics.medium_index, shadowing=args.shadowing)
    out.mkdir(parents=True, exist_ok=True)
    description = json.dumps(_provenance(config, seed=args.seed, particles=len(field), shadowing=args.shadowing, pixel_um=config.optics.pixel_um))
    with atomic_path(out / "hologram.tif") as temporary:
        tifffile.imwrite(temporary, hologram, description=description, metadata=None)
    write_particles(out / "particles.csv", field.table())
    _summary(f"simulated a {size}x{size} hologram of {len(field)} particles -> {out / 'hologram.tif'}, {out / 'particles.csv'}")


def _simulate_sequence(args, config, out: Path, *, size: int, count: int) -> None:
    """``simulate --frames N``: DIR/frames.tif (one page per frame, written as it is simulated) and the truth with frame and track."""
    import numpy as np
    import tifffile

    from napari_lbs._core import simulate_sequence, write_particles
    from napari_lbs._core._validation import check_disk
    from napari_lbs._core._files import atomic_path

    check_disk(args.frames * size * size * np.dtype(np.float32).itemsize, out, what=f"{args.frames} frames of {size}x{size} pixels", remedy="use fewer --frames or a smaller --size")
    out.mkdir(parents=True, exist_ok=True)
    flow, speed_um = args.flow or "uniform", 8.0 if args.speed_um is None else args.speed_um
    description = json.dumps(_provenance(config, seed=args.seed, particles=count, shadowing=args.shadowing, pixel_um=config.optics.pixel_um, flow=flow, speed_um=speed_um, frames=args.frames))
    with atomic_path(out / "frames.tif") as temporary:
        frames = tifffile.memmap(temporary, shape=(args.frames, size, size), dtype=np.float32, description=description, metadata=None, photometric="minisblack")
        truth = simulate_sequence(config, frames=args.frames, flow=flow, size=size, count=count, speed_um=speed_um, seed=args.seed, shadowing=args.shadowing,
                                  out=frames, progress=_ProgressBar("simulate")).truth
        frames.flush()
        del frames
    write_particles(out / "particles.csv", truth)
    tracks = len(np.unique(truth["track"]))
    _summary(f"simulated {args.frames} frames of {size}x{size} pixels, {count} particles in a {flow} flow ({tracks} tracks) -> {out / 'frames.tif'}, {out / 'particles.csv'}")


def _read_inputs(args):
    from napari_lbs._core import read_hologram

    hologram = read_hologram(args.holo, log=_summary)
    return hologram, _read_background(args, hologram.shape)


def _read_background(args, shape: tuple[int, int]):
    """``--background`` (None when not given), refused unless it has the hologram's ``shape``."""
    from napari_lbs._core import read_hologram

    if not getattr(args, "background", None):
        return None
    background = read_hologram(args.background, log=_summary)
    if background.shape != shape:
        raise ValueError(f"{args.background}: expected the hologram's shape {shape}, got {background.shape}")
    return background


def _inputs(args) -> list:
    """The files a command reads, which its outputs must never replace."""
    names = [getattr(args, name, None) for name in ("holo", "background", "config", "calibration", "model", "effects_from", "data")]
    return [name for entry in names for name in (entry if isinstance(entry, list) else [entry])]  # predict takes several HOLO


def _cmd_backprop(args) -> None:
    import numpy as np
    import tifffile

    from napari_lbs._core import backpropagate, load_config
    from napari_lbs._core._validation import check_disk
    from napari_lbs._core._files import atomic_path

    config = load_config(args.config)
    out = check_output_path(args.out, flag="--out", inputs=_inputs(args))
    hologram, background = _read_inputs(args)
    z_um = config.volume.planes_um()
    check_disk(len(z_um) * hologram.size * np.dtype(np.float32).itemsize, out, what=f"{len(z_um)} planes of {hologram.shape[0]}x{hologram.shape[1]} pixels",
               remedy="raise volume.z_step_um or write elsewhere")
    description = json.dumps({"z_um": list(z_um), **_provenance(config, source=str(args.holo), background=args.background)})
    start = time.perf_counter()
    with atomic_path(out) as temporary:
        # Written straight into a memory-mapped TIFF: a deep stack never has to fit in RAM.
        stack = tifffile.memmap(temporary, shape=(len(z_um),) + hologram.shape, dtype=np.float32, description=description, metadata=None)
        backpropagate(
            hologram,
            z_um,
            wavelength_um=config.optics.wavelength_um,
            pixel_um=config.optics.pixel_um,
            medium_index=config.optics.medium_index,
            background=background,
            out=stack,
            progress=_ProgressBar("backprop"),
        )
        stack.flush()
        del stack
    _summary(f"back-propagated {args.holo} to {len(z_um)} planes ({z_um[0]:g}-{z_um[-1]:g} um) in {time.perf_counter() - start:.1f} s -> {args.out}")


def _cmd_calibrate(args) -> None:
    from napari_lbs._core import CalibrationSettings, calibrate_hologram, load_config
    from napari_lbs._core._files import write_json

    config = load_config(args.config)
    out = check_output_path(args.out, flag="--out", inputs=_inputs(args))
    settings = _settings(CalibrationSettings, mode=args.mode, generations=args.generations, population=args.population, runs=args.runs, seed=args.seed)
    hologram, background = _read_inputs(args)
    result = calibrate_hologram(hologram, config, roi=args.roi, background=background, settings=settings, progress=_ProgressBar("calibrate"))
    payload = result.to_json()
    payload["provenance"] = _provenance(config, source=str(args.holo), background=args.background, seed=args.seed)
    write_json(out, payload)
    p = result.params
    x, y, size = result.roi
    chosen = "" if args.roi else f" (chosen: {result.roi_choice})"
    _summary(
        f"calibrated on the {size}² tile at x={x}, y={y}{chosen}: N_R={p.N_R:.4f}, N_sigma={p.N_sigma:.4f}, gamma={p.gamma:.4f}, "
        f"SSIM={result.ssim:.4f}, {result.evaluations} evaluations in {result.seconds:.1f} s -> {args.out}"
    )


def _read_calibration(path) -> dict:
    from napari_lbs._core._validation import check_calibration

    calibration = read_json_object(path, what="calibration")
    check_calibration(calibration, name=str(path))
    return calibration


def _cmd_generate(args) -> None:
    from napari_lbs._core import DatasetLayout, Distractors, InputProcessing, effects_from_report, generate_dataset, load_config, parse_effects

    config = load_config(args.config)
    check_output_path(args.out, flag="--out", folder=True, inputs=_inputs(args))
    if args.calibration:
        calibration = _read_calibration(args.calibration)
        processing = InputProcessing.from_calibration(calibration)
    else:
        calibration, processing = None, InputProcessing()
    effects, source = {}, None
    if args.effects_from:
        report = read_json_object(args.effects_from, what="diagnosis report")
        effects = effects_from_report(report, name=args.effects_from)
        source = {"report": str(args.effects_from), "verdict": report["verdict"]["id"]}
    effects.update(parse_effects(args.effect))  # explicit effects are added to (or override) the report's
    if args.effect:
        source = {**(source or {}), "explicit": list(args.effect)}
    start = time.perf_counter()
    layout = _settings(DatasetLayout, kind=args.layout, depths=args.depths, context_planes=args.context_planes)
    low, high = args.impurity_diameter_um
    if low > high or (args.impurities and high >= config.particles.diameter_min_um):
        raise InputError(f"--impurity-diameter-um: expected MIN <= MAX below the particles' diameter_min_um={config.particles.diameter_min_um:g} of {args.config}, got {low:g} {high:g}")
    distractors = _settings(Distractors, impurities_per_tile=args.impurities, impurity_diameter_min_um=args.impurity_diameter_um[0],
                            impurity_diameter_max_um=args.impurity_diameter_um[1], neighbours_margin_px=args.neighbours_margin_px)
    dataset = generate_dataset(args.out, config, groups=args.groups, processing=processing, layout=layout, calibration=calibration, effects=effects, effects_source=source,
                               distractors=distractors, seed=args.seed, workers=args.workers, progress=_ProgressBar("generate"))
    seconds = time.perf_counter() - start
    planes = len(dataset.groups) * len(dataset.planes_um)
    kind = f"calibrated ({args.calibration})" if calibration else "uncalibrated: Holo-processing (0, 0, 1)"
    added = f", effects: {', '.join(effects)}" if effects else ""
    if args.effects_from and not effects:
        added = f", no effects: {args.effects_from} names none"
    if distractors.active:
        added += f", unlabelled distractors: {distractors.impurities_per_tile} impurities per tile, neighbours in a {distractors.neighbours_margin_px}-pixel margin"
    _summary(f"wrote {len(dataset.groups)} groups ({planes} input planes, {kind}{added}) in {seconds:.1f} s -> {args.out}")


def _cmd_train(args) -> None:
    from napari_lbs._core import TrainingSettings, open_dataset, train_model

    out = check_output_path(args.out, flag="--out", inputs=_inputs(args))
    for companion in (out.with_suffix(".json"), out.with_suffix(".last.pt")):
        check_output_path(companion, flag="--out", inputs=_inputs(args))
    settings = _settings(
        TrainingSettings,
        formulation=args.formulation,
        preset=args.preset,
        epochs=args.epochs,
        minutes=args.minutes,
        patience=args.patience,
        augment=not args.no_augment,
        batch_size=args.batch_size,
        learning_rate=args.learning_rate,
        device=args.device,
        seed=args.seed,
        validation_groups=args.validation_groups,
        patch_size=args.patch_size,
        foreground_weight=args.foreground_weight,
    )
    dataset = open_dataset(args.data)
    expected = int(dataset.spec["groups"])
    if len(dataset.groups) < expected:  # a stopped generate, or group files removed since
        _summary(f"{args.data}: warning: {len(dataset.groups)} of {expected} groups present; training on those (run generate again to finish the set)")
    result = train_model(dataset, out, settings=settings, resume=args.resume, progress=_ProgressBar("train"))
    best = result.log["best"]
    record = next(e for e in result.log["epochs"] if e["epoch"] == best["epoch"])["validation"]
    stopped = " (stopped)" if result.stopped else ""
    _summary(
        f"trained {settings.preset} ({settings.formulation}) for {len(result.log['epochs'])} epochs in {result.log['seconds']:.0f} s{stopped}; best epoch {best['epoch']}: "
        f"validation ER {100 * record['er']:.2f} %, JI {record['ji']:.3f} (one-to-one, held-out synthetic groups) -> {args.out}"
    )


def _predict_outputs(args) -> tuple[Path, Path]:
    """The particle table and its provenance JSON, refused where they would overwrite something else (inputs: `check_output_path`)."""
    from napari_lbs._core._io import check_table_name

    out = Path(args.out)
    if out.suffix.lower() == ".json":
        raise ValueError(f"--out {out}: expected a particle table (.csv, or .parquet); its provenance is written beside it as .json")
    check_table_name(out)  # a Parquet table without pyarrow is refused now, not after the work
    provenance = out.with_suffix(".json")
    if provenance.is_file():
        try:
            previous = json.loads(provenance.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            previous = None
        # only a previous run's provenance of this same table may be replaced (never a model's training log)
        if not (isinstance(previous, dict) and previous.get("particles") == str(out) and "model_sha256" in previous):
            raise ValueError(f"--out {out}: {provenance} exists and is not this table's provenance; choose another name")
    return out, provenance


def _cmd_predict(args) -> None:
    from napari_lbs._core import load_config, load_model, open_frames, predict_particles

    out, provenance = _predict_outputs(args)
    for path in (out, provenance):
        check_output_path(path, flag="--out", inputs=_inputs(args))
    config = load_config(args.config) if args.config else None
    with open_frames(args.holo) as frames:
        if len(frames) > 1:
            _predict_sequence(args, frames, config, out, provenance)
            return
        # one frame (an image, a one-page TIFF, a one-frame video): the single-hologram path
        args.holo, hologram = frames.name(0), frames.read(0, log=_summary)
    background = _read_background(args, hologram.shape)
    model = load_model(args.model, device=args.device)
    result = predict_particles(hologram, model, config, background=background, force=args.force, progress=_ProgressBar("predict"))
    _write_table(out, provenance, result.particles, {**result.provenance, "source": str(args.holo), "background_file": args.background, "particles": str(out)})
    count = len(result.particles["x_um"])
    _summary(f"found {count} particles in {args.holo} in {result.seconds:.1f} s -> {out} (provenance: {provenance})")


def _write_table(out: Path, provenance: Path, particles: dict, record: dict) -> None:
    """The particle table (CSV, or Parquet with ``record`` in its key-value metadata too) and its provenance JSON beside it."""
    from napari_lbs._core import write_particles
    from napari_lbs._core._files import write_json

    write_particles(out, particles, metadata=record)
    write_json(provenance, record)


def _predict_sequence(args, frames, config, out: Path, provenance: Path) -> None:
    """``predict`` of a recording: one table with a ``frame`` column; finished frames kept in OUT.parts/ until the table is written."""
    import shutil

    from napari_lbs._core import load_model, predict_sequence, read_hologram

    work_dir = check_output_path(out.with_name(out.name + ".parts"), flag="--out", folder=True)
    background = read_hologram(args.background, log=_summary) if args.background else args.sequence_background
    model = load_model(args.model, device="cpu")  # each worker moves it to --device
    result = predict_sequence(frames, model, config, background=background, background_window=args.background_window, workers=args.workers, scheduler=args.scheduler, force=args.force,
                              work_dir=work_dir, device=args.device, progress=_ProgressBar("predict"))
    _write_table(out, provenance, result.particles, {**result.provenance, "background_file": args.background, "particles": str(out)})
    shutil.rmtree(work_dir)
    count, done = len(result.particles["x_um"]), result.provenance["frames"]
    resumed = f"; {result.resumed} frames resumed from {work_dir}" if result.resumed else ""
    _summary(f"found {count} particles in {done} frames in {result.seconds:.1f} s ({result.provenance['scheduler']}{resumed}) -> {out} (provenance: {provenance})")


def _cmd_track(args) -> None:
    import numpy as np

    from napari_lbs._core import link_tracks, read_particles, write_particles
    from napari_lbs._core._files import write_json
    from napari_lbs._core._io import check_table_name
    from napari_lbs._core._tracking import DISPLACEMENT_COLUMNS

    prediction_json = Path(args.particles).with_suffix(".json")
    out = check_table_name(check_output_path(args.out, flag="--out", inputs=[args.particles, prediction_json]))
    # the tracks' provenance beside them, never over the prediction's own
    provenance_json = check_output_path(out.with_suffix(".json"), flag="--out", inputs=[args.particles, prediction_json])
    table = read_particles(args.particles)
    if "frame" not in table:
        raise InputError(f"{args.particles}: no frame column; tracks need the table of a recording (predict with several frames)")
    tracks = link_tracks(table, search_range_um=args.search_range_um, axial_search_range_um=args.axial_search_range_um, memory=args.memory)
    linking = {"particles": str(args.particles), "search_range_um": args.search_range_um, "axial_search_range_um": args.axial_search_range_um, "memory": args.memory}
    if out.suffix.lower() != ".parquet":  # a track's last detection has no displacement: an empty CSV cell (Parquet keeps NaN)
        for name in DISPLACEMENT_COLUMNS:
            tracks[name] = np.array(["" if np.isnan(value) else f"{value:.9g}" for value in tracks[name]], dtype=object)
    provenance = {"particles": str(out), "tracks": linking}
    if prediction_json.is_file():  # what made the detections: model, settings, frames
        try:
            provenance["prediction"] = json.loads(prediction_json.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            provenance["prediction"] = None
    write_particles(out, tracks, metadata=provenance)
    write_json(provenance_json, provenance)
    lengths = np.bincount(tracks["track"]) if tracks["track"].size else np.zeros(0, int)
    frames = len(np.unique(tracks["frame"]))
    _summary(f"linked {tracks['track'].size} particles of {frames} frames into {lengths.size} tracks (median length {np.median(lengths) if lengths.size else 0:g} frames) -> {out}")


def _cmd_diagnose(args) -> None:
    from napari_lbs._core import DiagnosisSettings, diagnose_hologram, load_config, parse_effects, write_report
    from napari_lbs._core._gap import MIN_TILE_PX, adapted_tile_px

    config = load_config(args.config)
    stated = parse_effects(args.known_effect, flag="--known-effect")
    out = check_output_path(args.out, flag="--out", folder=True, inputs=_inputs(args))
    for name in ("report.json", "report.md", "gap_where.png", "gap_effects.png"):
        check_output_path(out / name, flag="--out")
    settings = _settings(DiagnosisSettings, sim_tiles=args.sim_tiles, evaluations=args.evaluations, seed=args.seed)
    size = args.tile or config.tile.size
    if size < MIN_TILE_PX:
        raise InputError(f"--tile: expected at least {MIN_TILE_PX} pixels (the lowest frequency band needs them), got {size}")
    calibration = _read_calibration(args.calibration) if args.calibration else None
    hologram, background = _read_inputs(args)
    if not args.tile:
        size = adapted_tile_px(hologram.shape, size)  # what diagnose_hologram will cut
    if args.roi and not (args.roi[0] + size <= hologram.shape[1] and args.roi[1] + size <= hologram.shape[0]):
        raise InputError(f"--roi {args.roi[0]} {args.roi[1]}: a {size}-pixel tile there crosses the edge of the {hologram.shape[1]}x{hologram.shape[0]} (x by y) hologram {args.holo}")
    diagnosis = diagnose_hologram(hologram, config, background=background, tile_px=args.tile, known=not args.no_known, stated=stated, settings=settings, progress=_ProgressBar("diagnose"))
    if args.roi:
        x, y = args.roi
        cut = int(diagnosis.report["tiles"]["shape"][0])  # the tiles the diagnosis cut (adapted to the hologram)
        diagnosis.report["roi"] = {"x": x, "y": y, "tile_index": (y // cut) * (hologram.shape[1] // cut) + x // cut}
    provenance = _provenance(config, source=str(args.holo), background=args.background, calibration=calibration, seed=args.seed)
    paths = write_report(diagnosis, out, provenance=provenance)
    verdict = diagnosis.report["verdict"]
    _summary(
        f"gap {diagnosis.report['gap']['baseline']:.2f} (baseline); verdict: {verdict['id'] or 'nothing missing'} (shrink {100 * verdict['shrink']:.0f} %, "
        f"residual {verdict['residual']:.2f}) in {diagnosis.seconds:.0f} s -> {paths[0]}"
    )


def _cmd_evaluate(args) -> None:
    from napari_lbs._core import read_particles, score_particles
    from napari_lbs._core._files import json_safe
    from napari_lbs._core._metrics import AXIAL_TOL_UM, LATERAL_TOL_UM, seed_scores

    pred, truth = read_particles(args.pred), read_particles(args.truth)
    tolerances = {
        "lateral_tol_um": LATERAL_TOL_UM if args.lateral_tol_um is None else args.lateral_tol_um,
        "axial_tol_um": AXIAL_TOL_UM if args.axial_tol_um is None else args.axial_tol_um,
    }
    metrics = score_particles(pred, truth, **tolerances)
    seed = seed_scores(pred, truth, **tolerances)
    if args.json:  # strict JSON: an empty reference gives er = null, never NaN
        print(json.dumps(json_safe({**metrics, "seed_scoring": seed, **tolerances}), allow_nan=False))
    _summary(
        f"one-to-one: TP {metrics['tp']}, FP {metrics['fp']}, FN {metrics['fn']}, ER {100 * metrics['er']:.2f} %, JI {metrics['ji']:.3f} "
        f"(seed's scoring, which counts repeats: ER {100 * seed['er']:.2f} %, JI {seed['ji']:.3f})"
    )


def _cmd_demo(args) -> None:
    from dataclasses import replace

    from napari_lbs._core import (
        CalibrationSettings,
        Distractors,
        InputProcessing,
        TrainingSettings,
        backpropagate,
        calibrate_hologram,
        generate_dataset,
        load_config,
        load_sample_hologram,
        predict_particles,
        train_model,
        write_particles,
        write_stack,
    )
    from napari_lbs._core._files import write_json
    from napari_lbs._core._samples import SAMPLE_PROVENANCE

    out = check_output_path(args.out, flag="--out", folder=True)
    out.mkdir(parents=True, exist_ok=True)
    config = load_config(None)
    hologram = load_sample_hologram()
    if args.quick:  # one tile, a token of each step: checks the plumbing in about a minute
        hologram = hologram[:256, :256]
        config = replace(config, particles=replace(config.particles, per_tile=6))
        calibration_settings, groups = CalibrationSettings(generations=4, population=6, fields=1, seed=args.seed), 3
        training = TrainingSettings(epochs=1, patch_size=64, validation_groups=1, minutes=0.3, seed=args.seed)
    else:
        # About 6.5 minutes of the focus formulation on 2 idle cores. 8 epochs, not 5: with the
        # distractors the diameters need them (pseudo-real: correlation 0.02 after 5 epochs, 0.43 after 10).
        calibration_settings, groups = CalibrationSettings(generations=40, seed=args.seed), 64
        training = TrainingSettings(epochs=8, minutes=7.0, seed=args.seed)
    timings = {}
    start = time.perf_counter()
    z_um = config.volume.planes_um()
    stack = backpropagate(hologram, z_um, wavelength_um=config.optics.wavelength_um, pixel_um=config.optics.pixel_um, medium_index=config.optics.medium_index, progress=_ProgressBar("backprop"))
    stack_path = write_stack(out / "zstack.tif", stack, z_um=z_um, metadata=_provenance(config, source=SAMPLE_PROVENANCE["source"]))
    del stack
    timings["backprop"] = time.perf_counter() - start

    start = time.perf_counter()
    calibration = calibrate_hologram(hologram, config, settings=calibration_settings, progress=_ProgressBar("calibrate")).to_json()
    write_json(out / "calibration.json", calibration)
    timings["calibrate"] = time.perf_counter() - start

    start = time.perf_counter()
    if args.calibrated:  # the seed's LBS: calibrated Holo-processing of opaque discs
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
                f"uncalibrated, with unlabelled distractors ({distractors.impurities_per_tile} impurities of {distractors.impurity_diameter_min_um:g}-{distractors.impurity_diameter_max_um:g} um "
                f"per tile, neighbours in a {distractors.neighbours_margin_px}-pixel margin)")
    generate_dataset(out / "data", config, groups=groups, processing=processing, calibration=calibration, effects=effects,
                     effects_source={"explicit": ["the built-in sample: polystyrene (n 1.59) spheres in water (n 1.33), 25 um, 660 nm"]} if effects else None,
                     distractors=distractors, seed=args.seed, progress=_ProgressBar("generate"))
    timings["generate"] = time.perf_counter() - start

    start = time.perf_counter()
    trained = train_model(out / "data", out / "model.pt", settings=training, progress=_ProgressBar("train"))
    timings["train"] = time.perf_counter() - start

    result = predict_particles(hologram, trained.model_path, config, device=training.device, progress=_ProgressBar("predict"))
    particles_path = write_particles(out / "particles.csv", result.particles)
    write_json(out / "particles.json", {**result.provenance, "source": SAMPLE_PROVENANCE["source"]})
    timings["predict"] = result.seconds
    best = trained.log["best"]
    validation = next(e for e in trained.log["epochs"] if e["epoch"] == best["epoch"])["validation"]
    summary = {
        "hologram_shape": list(hologram.shape),
        "planes": len(z_um),
        "z_um": [z_um[0], z_um[-1]],
        "zstack": str(stack_path),
        "calibration": {"params": calibration["params"], "ssim": calibration["ssim"], "roi": calibration["roi"]},
        "groups": groups,
        "model": str(trained.model_path),
        "model_sha256": best["sha256"],
        "training": {"formulation": training.formulation, "preset": training.preset, "epochs_done": len(trained.log["epochs"]), "stopped_by_budget": trained.stopped,
                     "data": f"{data}, the last {len(trained.log['validation_groups'])} held out", "effects": effects,
                     "distractors": distractors.to_dict() if distractors.active else None, "calibrated": bool(args.calibrated)},
        "validation": {key: validation.get(key) for key in ("er", "ji", "tp", "fp", "fn", "threshold", "axial_um", "median_abs_dz_um", "median_abs_dd_um")},
        "particles": str(particles_path),
        "particle_count": len(result.particles["x_um"]),
        "seconds": {key: round(value, 2) for key, value in timings.items()},
        "sample": SAMPLE_PROVENANCE,
        "quick": bool(args.quick),
    }
    write_json(out / "summary.json", summary)
    print(particles_path)
    _summary(
        f"demo: calibration SSIM {calibration['ssim']:.3f} ({'used' if args.calibrated else 'recorded; --calibrated trains on it'}), {data}, "
        f"trained the {training.formulation} formulation ({training.preset}, {trained.log['seconds']:.0f} s; "
        f"validated on {len(trained.log['validation_groups'])} held-out synthetic groups: ER {100 * validation['er']:.1f} %, JI {validation['ji']:.3f}), "
        f"found {summary['particle_count']} particles in the built-in hologram -> {out}"
    )


# The built-in sample's spheres: polystyrene (n 1.59) in water (n 1.33), all light transmitted;
# the phase delay through a sphere's centre is 2π · 0.26 · d / 0.66 µm (62 rad at 25 µm).
DEMO_SAMPLE_EFFECTS = {"particle_phase": {"index_contrast": 0.26, "transmission": 1.0}}
# Its unlabelled distractors (`Distractors`): small foci of debris in the water, and the
# fringes of spheres outside the crop near its edges.
DEMO_SAMPLE_DISTRACTORS = {"impurities_per_tile": 6, "impurity_diameter_min_um": 4.0, "impurity_diameter_max_um": 14.0, "neighbours_margin_px": 96}


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``napari-lbs simulate: error: argument --size: ...``), exit 2; sub-parsers inherit it."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


_SEED = _integer(0)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="napari-lbs", description="Learning from better simulation for in-line particle holography.")
    parser.add_argument("--version", action="version", version=f"napari-lbs {__version__}")
    parser.add_argument("--debug", action="store_true", help="print the full traceback of any error")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("config", help="write (or check) an experiment config")
    p.add_argument("--write", metavar="FILE", help="write the default config to FILE")
    p.add_argument("--check", metavar="FILE", help="validate FILE")
    p.set_defaults(run=_cmd_config)

    p = sub.add_parser("simulate", help="simulate a hologram of a random particle field with its ground truth")
    p.add_argument("--config", required=True)
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--size", type=_integer(16), help="window edge in pixels (default: tile.size)")
    p.add_argument("--particles", type=_integer(0), help="number of particles (default: particles.per_tile)")
    p.add_argument("--seed", type=_SEED, default=0)
    p.add_argument("--shadowing", action="store_true", help="propagate layer by layer so particles shadow each other")
    p.add_argument("--frames", type=_integer(1), help="simulate a recording of N frames (DIR/frames.tif) with the truth of every frame and its tracks")
    p.add_argument("--flow", choices=("uniform", "vortex", "shear"), help="with --frames: how the particles move (default uniform)")
    p.add_argument("--speed-um", type=_number(0.0), help="with --frames: largest displacement of a particle between frames (µm, default 8)")
    p.set_defaults(run=_cmd_simulate)

    p = sub.add_parser("backprop", help="back-propagate a hologram into a float32 z-stack TIFF")
    p.add_argument("holo", metavar="HOLO")
    p.add_argument("--config", required=True)
    p.add_argument("--out", required=True, metavar="STACK.tif")
    p.add_argument("--background", metavar="BG")
    p.set_defaults(run=_cmd_backprop)

    p = sub.add_parser("calibrate", help="fit Holo-processing (noise + gamma) to one tile of a real hologram")
    p.add_argument("holo", metavar="HOLO")
    p.add_argument("--config", required=True)
    p.add_argument("--out", required=True, metavar="CALIB.json")
    p.add_argument("--roi", type=_integer(0), nargs=2, metavar=("X", "Y"), help="top-left pixel of the reference tile (default: the tool picks)")
    p.add_argument("--background", metavar="BG")
    p.add_argument("--seed", type=_SEED, default=0)
    p.add_argument("--mode", choices=("robust", "seed"), default="robust", help="robust (default) or the seed code's conventions")
    p.add_argument("--generations", type=_integer(1), default=100)
    p.add_argument("--population", type=_integer(2), default=12)
    p.add_argument("--runs", type=_integer(1), default=1)
    p.set_defaults(run=_cmd_calibrate)

    p = sub.add_parser("generate", help="write a synthetic training set (HCS + Holo-processing)")
    p.add_argument("--config", required=True)
    p.add_argument("--calibration", metavar="CALIB.json", help="calibrated Holo-processing (default: none, the seed's normal simulation)")
    p.add_argument("--groups", type=_integer(1), default=256)
    p.add_argument("--out", required=True, metavar="DATA")
    p.add_argument("--seed", type=_SEED, default=0)
    p.add_argument("--layout", choices=("stack", "layers"), default="stack",
                   help="stack (default): the reconstruction planes plus context, for the focus formulation; layers: the seed's one plane per layer")
    p.add_argument("--depths", choices=("uniform", "layers"), default="uniform", help="stack layout: particle depths uniform over the volume (default) or on the seed's layers")
    p.add_argument("--context-planes", type=_integer(0), default=8, help="stack layout: planes stored beyond each end of the volume (default 8)")
    p.add_argument("--workers", type=_integer(1), default=1, help="processes simulating groups at once (default 1)")
    p.add_argument("--effects-from", metavar="REPORT.json", help="add the effects a diagnosis report names (its verdict and waterfall, with their fitted parameters)")
    p.add_argument("--effect", action="append", default=[], metavar="ID[:NAME=VALUE,...]",
                   help="add an effect of the catalog, e.g. particle_phase:index_contrast=0.26,transmission=1 or quantization:bits=8,saturation=2 (repeatable)")
    p.add_argument("--impurities", type=_integer(0), default=0, metavar="N",
                   help="unlabelled small scatterers per tile, smaller than the particles (default 0; the demo uses %d)" % DEMO_SAMPLE_DISTRACTORS["impurities_per_tile"])
    p.add_argument("--impurity-diameter-um", type=_number(0.0, above=True), nargs=2, default=(4.0, 14.0), metavar=("MIN", "MAX"), help="their diameter range in um (default 4 14)")
    p.add_argument("--neighbours-margin-px", type=_integer(0, 4096), default=0, metavar="PX",
                   help="simulate each group with unlabelled particles in a margin of PX pixels around it and keep the window, as a crop of a real hologram is (default 0; the demo uses %d)" % DEMO_SAMPLE_DISTRACTORS["neighbours_margin_px"])
    p.set_defaults(run=_cmd_generate)

    p = sub.add_parser("train", help="train the U-Net on a synthetic training set")
    p.add_argument("data", metavar="DATA")
    p.add_argument("--out", required=True, metavar="MODEL.pt")
    p.add_argument("--formulation", choices=("focus", "seed"), default="focus", help="focus (default): context planes in, centre probability + depth offset + diameter out; seed: the seed paper's")
    p.add_argument("--preset", choices=("small", "medium", "paper"), default="small")
    p.add_argument("--epochs", type=_integer(1), default=10)
    p.add_argument("--minutes", type=_number(0.0), default=0.0, help="stop after M minutes of training, keeping the best model so far (default: no limit)")
    p.add_argument("--patience", type=_integer(0), default=0, help="stop after this many epochs without a better validation JI (default: never)")
    p.add_argument("--batch-size", type=_integer(1), default=8)
    p.add_argument("--learning-rate", type=_number(0.0, 1.0, above=True), help="AdamW's peak rate (default: 2e-3 small, 1e-3 medium, 3e-4 paper)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    p.add_argument("--seed", type=_SEED, default=0)
    p.add_argument("--validation-groups", type=_integer(0), default=0, help="held-out groups (default: one eighth)")
    p.add_argument("--patch-size", type=_integer(0), default=0, help="train on square crops (default: 128 focus, whole tiles seed)")
    p.add_argument("--foreground-weight", type=_number(1.0), default=1.0, help="seed formulation: MSE weight of label pixels (default 1: the seed's plain MSE)")
    p.add_argument("--no-augment", action="store_true", help="focus formulation: no random gamma, contrast, noise or quantisation")
    p.add_argument("--resume", action="store_true", help="continue from MODEL.last.pt")
    p.set_defaults(run=_cmd_train)

    p = sub.add_parser("predict", help="reconstruct the particles of a hologram or a recording with a trained model")
    p.add_argument("holo", metavar="HOLO", nargs="+", help="image files, folders of images, glob patterns, multi-page TIFFs or videos; frames numbered in this order")
    p.add_argument("--model", required=True, metavar="MODEL.pt")
    p.add_argument("--out", required=True, metavar="PARTICLES.csv", help="the particle table: CSV, or Parquet when the name ends in .parquet; provenance beside it as .json")
    p.add_argument("--config", help="optics and depths (default: the model's)")
    p.add_argument("--background", metavar="BG", help="a hologram taken without particles, divided out of every frame")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    p.add_argument("--force", action="store_true", help="run a model made for other optics or depths than the config's (without it such a run exits 2 naming both values)")
    p.add_argument("--sequence-background", choices=("global", "running", "none"), default="global",
                   help="recordings without --background: divide every frame by the median of the frames (global, default), of the frames around it (running), or nothing")
    p.add_argument("--background-window", type=_integer(1), default=21, help="frames of a running background (default 21)")
    engine = p.add_mutually_exclusive_group()
    engine.add_argument("--workers", type=_integer(1), help="recordings: run on a local dask cluster of N worker processes (default: the local threaded scheduler)")
    engine.add_argument("--scheduler", metavar="ADDRESS", help="recordings: run on an existing dask.distributed scheduler (tcp://host:8786)")
    p.set_defaults(run=_cmd_predict)

    p = sub.add_parser("track", help="link the particles of a recording into 3-D tracks (trackpy)")
    p.add_argument("particles", metavar="PARTICLES.csv", help="a particle table with a frame column (CSV or .parquet)")
    p.add_argument("--out", required=True, metavar="TRACKS.csv", help="the tracks table: CSV, or Parquet when the name ends in .parquet")
    p.add_argument("--search-range-um", type=_number(0.0, above=True), default=60.0,
                   help="largest displacement between two frames a particle is seen in (µm, default 60: a predicted depth may jump by a 50 µm plane)")
    p.add_argument("--axial-search-range-um", type=_number(0.0, above=True), help="a separate search range along z (µm; default: --search-range-um)")
    p.add_argument("--memory", type=_integer(0), default=0, help="frames a particle may be missed and keep its track (default 0)")
    p.set_defaults(run=_cmd_track)

    p = sub.add_parser("diagnose", help="diagnose the sim-to-real gap of a hologram: where, which effect, how much")
    p.add_argument("holo", metavar="HOLO")
    p.add_argument("--config", required=True)
    p.add_argument("--out", required=True, metavar="REPORT_DIR")
    p.add_argument("--roi", type=_integer(0), nargs=2, metavar=("X", "Y"), help="a reference tile to mark in the report (all tiles are used)")
    p.add_argument("--background", metavar="BG")
    p.add_argument("--calibration", metavar="CALIB.json", help="recorded as provenance (the baseline is refitted in the hologram domain)")
    p.add_argument("--tile", type=_integer(1), help="tile edge in pixels (default: tile.size)")
    p.add_argument("--no-known", action="store_true", help="diagnose the bit depth and saturation too, instead of taking them from the file's integer counts")
    p.add_argument("--known-effect", action="append", default=[], metavar="ID[:NAME=VALUE,...]",
                   help="an effect you know the experiment has, put into every model and not diagnosed, e.g. particle_phase:index_contrast=0.26,transmission=1 for polystyrene beads in water (repeatable)")
    p.add_argument("--sim-tiles", type=_integer(1), default=8)
    p.add_argument("--evaluations", type=_integer(1), default=40)
    p.add_argument("--seed", type=_SEED, default=0)
    p.set_defaults(run=_cmd_diagnose)

    p = sub.add_parser("evaluate", help="score a particle table against a reference, one-to-one")
    p.add_argument("pred", metavar="PRED.csv")
    p.add_argument("truth", metavar="TRUTH.csv")
    p.add_argument("--lateral-tol-um", type=_number(0.0, above=True), help="lateral match radius (µm; default: CONTRACT.md's, 22)")
    p.add_argument("--axial-tol-um", type=_number(0.0, above=True), help="axial match distance (µm; default: CONTRACT.md's, 150)")
    p.add_argument("--json", action="store_true", help="print the metrics JSON on stdout")
    p.set_defaults(run=_cmd_evaluate)

    p = sub.add_parser("demo", help="run the whole pipeline on the built-in real hologram")
    p.add_argument("--out", default="napari-lbs-demo", metavar="DIR")
    p.add_argument("--quick", action="store_true", help="a token run on one tile (about a minute)")
    p.add_argument("--calibrated", action="store_true",
                   help="train on the seed's LBS data (calibrated Holo-processing of opaque discs) instead of transparent spheres (docs/learning.md: pseudo-real benchmark)")
    p.add_argument("--seed", type=_SEED, default=0)
    p.set_defaults(run=_cmd_demo)
    return parser


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt


def _one_line(error: BaseException) -> str:
    """The first line of an error's message; a system error as ``FILE: reason``."""
    if isinstance(error, MemoryError):
        return "out of memory; use a smaller image, fewer planes or fewer groups at once"
    if isinstance(error, OSError) and error.strerror:
        culprit = f"{error.filename}: " if error.filename else ""
        return f"{culprit}{error.strerror}"
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``napari-lbs`` console script."""
    args = _parser().parse_args(argv)
    in_main_thread = threading.current_thread() is threading.main_thread()
    if in_main_thread:
        # SIGTERM unwinds like Ctrl-C, so every temporary file is removed on the way out
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        args.run(args)
    except KeyboardInterrupt:
        print(f"napari-lbs {args.command}: interrupted; no partial file was left (finished files, such as generated groups, are kept)", file=sys.stderr)
        return 130
    except Exception as error:  # noqa: BLE001 - every failure becomes one line and an exit status
        if args.debug:
            traceback.print_exc()
        if isinstance(error, _EXPECTED_ERRORS):
            print(f"napari-lbs {args.command}: error: {_one_line(error)}", file=sys.stderr)
            return 2
        print(f"napari-lbs {args.command}: internal error ({type(error).__name__}: {_one_line(error)}); please report it with the command line"
              f"{'' if args.debug else ' and the output of --debug'}", file=sys.stderr)
        return 1
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)
    return 0


def console_main() -> None:
    """The ``napari-lbs`` console script: `main`, and its exit status.

    An interrupted command leaves with 130 through ``os._exit`` once its streams are flushed:
    a SIGTERM that lands inside an import (numpy loads submodules lazily) makes CPython end
    the process with SIGINT at shutdown, although `main` caught it (exit -2 instead of 130).
    """
    import os

    status = main()
    if status == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(130)
    sys.exit(status)


if __name__ == "__main__":
    console_main()
