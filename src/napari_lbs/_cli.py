"""The ``napari-lbs`` console script: one sub-command per pipeline step (`napari_lbs._core.pipeline`).

Each sub-command checks its flags and outputs, builds the step's request, runs it with a progress bar and prints the
step's one-line summary.

Bad input exits 2 with one line naming the culprit (a file or a flag); an unexpected error exits 1 with one line asking
for a report (``--debug`` prints the traceback); success prints a one-line summary on stderr. See docs/formats.md and
docs/reliability.md.

Outputs are checked before any work (`check_output_path`): an existing one needs ``--force``. Everything heavy is
imported inside the sub-commands, so ``napari-lbs --version`` or ``--help`` starts in a fraction of a second.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

from napari_lbs import __version__
from napari_lbs._core import InputError, load_config, write_config
from napari_lbs._core import pipeline
from napari_lbs._core.foundation import check_output_path, interruptible, json_safe, size_threads

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


def _inputs(args) -> list:
    """The files a command reads, which its outputs must never replace."""
    names = [getattr(args, name, None) for name in ("holo", "background", "dark", "config", "calibration", "model", "effects_from", "data")]
    return [name for entry in names for name in (entry if isinstance(entry, list) else [entry])]  # predict takes several HOLO


def _checked(args, request, *, folder: bool = False):
    """``request``, once ``--out`` (a folder, or each file the step writes) is checked before any work (`check_output_path`)."""
    force = args.force or getattr(args, "resume", False)  # a resumed training replaces its own files
    for path in [args.out] if folder else request.outputs():
        check_output_path(path, flag="--out", folder=folder, inputs=_inputs(args), force=force, writes=[out.name for out in request.outputs()] if folder else ())
    return request


def _run(step, request, label: str | None = None, **callbacks):
    """Run a pipeline step with a terminal progress bar and print its one-line summary."""
    if label is not None:
        callbacks["progress"] = _ProgressBar(label)
    result = step(request, **callbacks)
    _summary(result.summary)
    return result


def _cmd_config(args) -> None:
    if args.check:
        load_config(args.check)
        _summary(f"{args.check}: valid experiment config")
        return
    if not args.write:
        raise ValueError("--write: expected a file to write the default config to")
    path = write_config(check_output_path(args.write, flag="--write", force=args.force), force=args.force)
    _summary(f"wrote the default experiment config to {path}")


def _cmd_simulate(args) -> None:
    config = load_config(args.config)
    if args.frames is None:
        for flag, value in (("--flow", args.flow), ("--speed-um", args.speed_um)):
            if value is not None:
                raise InputError(f"{flag}: describes a recording; add --frames N")
    request = pipeline.SimulateRequest(Path(args.out), config, size_px=args.size, particles=args.particles, seed=args.seed, shadowing=args.shadowing, frames=args.frames,
                                       flow=args.flow or "uniform", speed_um=8.0 if args.speed_um is None else args.speed_um, replace=args.force)
    _run(pipeline.simulate, _checked(args, request, folder=True), "simulate")


def _cmd_backprop(args) -> None:
    request = pipeline.BackpropRequest(args.holo, Path(args.out), load_config(args.config), background_path=args.background, replace=args.force)
    _run(pipeline.backprop, _checked(args, request), "backprop", log=_summary)


def _cmd_calibrate(args) -> None:
    from napari_lbs._core import CalibrationSettings

    config = load_config(args.config)
    settings = _settings(CalibrationSettings, mode=args.mode, generations=args.generations, population=args.population, runs=args.runs, seed=args.seed)
    request = pipeline.CalibrateRequest(args.holo, Path(args.out), config, settings=settings, roi=tuple(args.roi) if args.roi else None, background_path=args.background,
                                        replace=args.force)
    _run(pipeline.calibrate, _checked(args, request), "calibrate", log=_summary)


def _cmd_generate(args) -> None:
    from napari_lbs._core import DatasetLayout, Distractors

    config = load_config(args.config)
    check_output_path(args.out, flag="--out", folder=True, inputs=_inputs(args))
    effects, source = pipeline.requested_effects(report_path=args.effects_from, explicit=args.effect)
    layout = _settings(DatasetLayout, kind=args.layout, depths=args.depths, context_planes=args.context_planes)
    # the small scatterers and the neighbours the report's scene measured, unless --impurities / --neighbours-margin-px say otherwise
    measured = pipeline.report_distractors(args.effects_from, config) if args.effects_from else Distractors()
    margin = measured.neighbours_margin_px if args.neighbours_margin_px is None else args.neighbours_margin_px
    if args.impurities is None and args.effects_from:
        distractors = _settings(Distractors, impurities_per_tile=measured.impurities_per_tile, impurity_diameter_min_um=measured.impurity_diameter_min_um,
                                impurity_diameter_max_um=measured.impurity_diameter_max_um, neighbours_margin_px=margin)
    else:
        low, high = args.impurity_diameter_um
        impurities = args.impurities or 0
        if low > high or (impurities and high >= config.particles.diameter_min_um):
            raise InputError(f"--impurity-diameter-um: expected MIN <= MAX below the particles' diameter_min_um={config.particles.diameter_min_um:g} of {args.config}, got {low:g} {high:g}")
        distractors = _settings(Distractors, impurities_per_tile=impurities, impurity_diameter_min_um=low, impurity_diameter_max_um=high, neighbours_margin_px=margin)
    sizes = pipeline.report_sizes(args.effects_from, config) if args.effects_from and not args.uniform_sizes else None
    request = pipeline.GenerateRequest(Path(args.out), config, groups=args.groups, calibration_path=args.calibration, effects=effects, effects_source=source, layout=layout,
                                       distractors=distractors, sizes=sizes, keep_calibration=args.keep_calibration, seed=args.seed, workers=args.workers)
    _run(pipeline.generate, request, "generate")


def _cmd_train(args) -> None:
    from napari_lbs._core import TrainingSettings

    settings = _settings(TrainingSettings, formulation=args.formulation, preset=args.preset, epochs=args.epochs, minutes=args.minutes, patience=args.patience,
                         augment=not args.no_augment, batch_size=args.batch_size, learning_rate=args.learning_rate, device=args.device, seed=args.seed,
                         validation_groups=args.validation_groups, patch_size=args.patch_size, foreground_weight=args.foreground_weight, precision=args.precision,
                         average_last=args.average_last)
    _run(pipeline.train, _checked(args, pipeline.TrainRequest(args.data, Path(args.out), settings=settings, resume=args.resume, replace=args.force)), "train", log=_summary)


def _cmd_predict(args) -> None:
    request = pipeline.PredictRequest(args.holo, args.model, Path(args.out), load_config(args.config) if args.config else None, background_path=args.background,
                                      device=args.device, precision=args.precision, force=args.force, sequence_background=args.sequence_background, background_window=args.background_window,
                                      workers=args.workers, scheduler=args.scheduler, refine=args.refine or args.material is not None, threshold=args.threshold,
                                      material_index_contrast=args.material, replace=args.force)
    _run(pipeline.predict, _checked(args, request), "predict", log=_summary)


def _cmd_refine(args) -> None:
    from napari_lbs._core.foundation import available_threads

    request = pipeline.RefineRequest(args.holo, Path(args.out), load_config(args.config), background_path=args.background, dark_path=args.dark,
                                     index_contrast=args.index_contrast, medium_index=args.medium_index, max_particles=args.max_particles,
                                     detection_rounds=args.detection_rounds, depth_window_um=args.depth_window_um, patch_um=args.patch_um, workers=available_threads(), replace=args.force)
    _run(pipeline.refine, _checked(args, request), "refine", log=_summary)


def _cmd_track(args) -> None:
    _run(pipeline.track, pipeline.TrackRequest(args.particles, Path(args.out), search_range_um=args.search_range_um, axial_search_range_um=args.axial_search_range_um,
                                               memory=args.memory, replace=args.force))


def _cmd_diagnose(args) -> None:
    request = pipeline.DiagnoseRequest(args.holo[0] if len(args.holo) == 1 else tuple(args.holo), Path(args.out), load_config(args.config), background_path=args.background,
                                       calibration_path=args.calibration, roi=tuple(args.roi) if args.roi else None, tile_px=args.tile, seed=args.seed, replace=args.force)
    _run(pipeline.diagnose, _checked(args, request, folder=True), "diagnose", log=_summary)


def _cmd_evaluate(args) -> None:
    result = pipeline.evaluate(pipeline.EvaluateRequest(args.pred, args.truth, lateral_tol_um=args.lateral_tol_um, axial_tol_um=args.axial_tol_um))
    if args.json:  # strict JSON: an empty reference gives er = null, never NaN
        print(json.dumps(json_safe(result.value), allow_nan=False))
    _summary(result.summary)


def _cmd_demo(args) -> None:
    request = _checked(args, pipeline.DemoRequest(Path(args.out), quick=args.quick, calibrated=args.calibrated, seed=args.seed, replace=args.force), folder=True)
    result = pipeline.demo(request, progress_for=_ProgressBar, log=_summary)
    print(result.paths[0])
    _summary(result.summary)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``napari-lbs simulate: error: argument --size: ...``), exit 2; sub-parsers inherit it."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


_SEED = _integer(0)
# Every writing sub-command but predict (whose --force also covers its model's optics) takes this --force; docs/cli.md lists each one's outputs.
_FORCE = _Parser(add_help=False)
_FORCE.add_argument("--force", action="store_true", help="replace the outputs of an earlier run where they exist (without it an existing output exits 2 naming it)")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="napari-lbs", description="Learning from better simulation for in-line particle holography.")
    parser.add_argument("--version", action="version", version=f"napari-lbs {__version__}")
    parser.add_argument("--debug", action="store_true", help="print the full traceback of any error")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("config", help="write (or check) an experiment config", parents=[_FORCE])
    p.add_argument("--write", metavar="FILE", help="write the default config to FILE")
    p.add_argument("--check", metavar="FILE", help="validate FILE")
    p.set_defaults(run=_cmd_config)

    p = sub.add_parser("simulate", help="simulate a hologram of a random particle field with its ground truth", parents=[_FORCE])
    p.add_argument("--config", required=True)
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--size", type=_integer(16), help="window edge in pixels (default: tile.size)")
    p.add_argument("--particles", type=_integer(0), help="number of particles, at most 100000 (default: particles.per_tile)")
    p.add_argument("--seed", type=_SEED, default=0)
    p.add_argument("--shadowing", action="store_true", help="propagate layer by layer so particles shadow each other")
    p.add_argument("--frames", type=_integer(1), help="simulate a recording of N frames (DIR/frames.tif) with the truth of every frame and its tracks")
    p.add_argument("--flow", choices=("uniform", "vortex", "shear"), help="with --frames: how the particles move (default uniform)")
    p.add_argument("--speed-um", type=_number(0.0), help="with --frames: largest displacement of a particle between frames (µm, default 8)")
    p.set_defaults(run=_cmd_simulate)

    p = sub.add_parser("backprop", help="back-propagate a hologram into a float32 z-stack TIFF", parents=[_FORCE])
    p.add_argument("holo", metavar="HOLO")
    p.add_argument("--config", required=True)
    p.add_argument("--out", required=True, metavar="STACK.tif")
    p.add_argument("--background", metavar="BG")
    p.set_defaults(run=_cmd_backprop)

    p = sub.add_parser("calibrate", help="fit Holo-processing (noise + gamma) to one tile of a real hologram", parents=[_FORCE])
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
    p.add_argument("--effects-from", metavar="REPORT.json", help="add the effects a diagnosis report names (its verdict's effects, with their fitted parameters)")
    p.add_argument("--effect", action="append", default=[], metavar="ID[:NAME=VALUE,...]",
                   help="add an effect of the catalog, e.g. particle_phase:index_contrast=0.26,transmission=1 or quantization:bits=8,saturation=2 (repeatable)")
    p.add_argument("--impurities", type=_integer(0), default=None, metavar="N",
                   help="unlabelled small scatterers per tile, smaller than the particles (default: as many as the --effects-from report's scene measured, "
                        "with their sizes, else 0; the demo uses %d)" % pipeline.DEMO_SAMPLE_DISTRACTORS["impurities_per_tile"])
    p.add_argument("--impurity-diameter-um", type=_number(0.0, above=True), nargs=2, default=(4.0, 14.0), metavar=("MIN", "MAX"), help="their diameter range in um (default 4 14)")
    p.add_argument("--neighbours-margin-px", type=_integer(0, 4096), default=None, metavar="PX",
                   help="simulate each group with unlabelled particles in a margin of PX pixels around it and keep the window, as a crop of a real hologram is "
                        "(default: two Airy radii of the --effects-from report's median particle, else 0; the demo uses %d)" % pipeline.DEMO_SAMPLE_DISTRACTORS["neighbours_margin_px"])
    p.add_argument("--uniform-sizes", action="store_true",
                   help="particle diameters uniform over the config's range even with --effects-from (default: the sizes the report's scene measured, where it measured ten or more)")
    p.add_argument("--keep-calibration", action="store_true",
                   help="with --effects-from and --calibration: apply the calibration's Holo-processing on top of the report's effects (default: the report's model replaces it; "
                        "the calibration is recorded)")
    p.set_defaults(run=_cmd_generate)

    p = sub.add_parser("train", help="train the U-Net on a synthetic training set", parents=[_FORCE])
    p.add_argument("data", metavar="DATA")
    p.add_argument("--out", required=True, metavar="MODEL.pt")
    p.add_argument("--formulation", choices=("focus", "seed"), default="focus", help="focus (default): context planes in, centre probability + depth offset + diameter out; seed: the seed paper's")
    p.add_argument("--preset", choices=("small", "medium", "paper"), default="small")
    p.add_argument("--epochs", type=_integer(1), default=10)
    p.add_argument("--minutes", type=_number(0.0), default=0.0, help="stop after M minutes of training, keeping the best model so far (default: no limit)")
    p.add_argument("--patience", type=_integer(0), default=0, help="stop after this many epochs without a better validation JI (default: never)")
    p.add_argument("--average-last", type=_integer(0), default=0, metavar="K",
                   help="keep the mean of the last K epochs' weights instead of the best validated epoch (default 0: off)")
    p.add_argument("--batch-size", type=_integer(1), default=8)
    p.add_argument("--learning-rate", type=_number(0.0, 1.0, above=True), help="AdamW's peak rate (default: 2e-3 small, 1e-3 medium, 3e-4 paper)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    p.add_argument("--precision", choices=("float32", "auto", "bfloat16"), default="float32", help="the network's arithmetic (bfloat16: faster where native, learns more slowly)")
    p.add_argument("--seed", type=_SEED, default=0)
    p.add_argument("--validation-groups", type=_integer(0), default=0, help="held-out groups (default: one eighth)")
    p.add_argument("--patch-size", type=_integer(0), default=0, help="train on square crops (default: 128 focus, whole tiles seed)")
    p.add_argument("--foreground-weight", type=_number(1.0), default=1.0, help="seed formulation: MSE weight of label pixels (default 1: the seed's plain MSE)")
    p.add_argument("--no-augment", action="store_true", help="focus formulation: no random gamma, contrast, noise or quantisation")
    p.add_argument("--resume", action="store_true", help="continue from MODEL.last.pt (replacing MODEL.pt and its .json as it goes)")
    p.set_defaults(run=_cmd_train)

    p = sub.add_parser("predict", help="reconstruct the particles of a hologram or a recording with a trained model")
    p.add_argument("holo", metavar="HOLO", nargs="+", help="image files, folders of images, glob patterns, multi-page TIFFs or videos; frames numbered in this order")
    p.add_argument("--model", required=True, metavar="MODEL.pt")
    p.add_argument("--out", required=True, metavar="PARTICLES.csv", help="the particle table: CSV, or Parquet when the name ends in .parquet; provenance beside it as .json")
    p.add_argument("--config", help="optics and depths (default: the model's)")
    p.add_argument("--background", metavar="BG", help="a hologram taken without particles, divided out of every frame")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    p.add_argument("--precision", choices=("auto", "float32", "bfloat16"), default="auto", help="bfloat16 where the CPU (AMX, AVX-512 BF16) or GPU has it natively, else float32 (auto)")
    p.add_argument("--force", action="store_true", help="run a model made for other optics or depths than the config's (without it such a run exits 2 naming both values), "
                   "and replace PARTICLES.csv and its .json where they exist (without it they exit 2)")
    p.add_argument("--sequence-background", choices=("auto", "global", "running", "flat", "none"), default="auto",
                   help="recordings without --background: divide every frame by the median of the frames (global), of the frames around it (running), its own smooth illumination (flat), the median if the recording shows it particle-free else flat (auto, default), or nothing")
    p.add_argument("--background-window", type=_integer(1), default=21, help="frames of a running background (default 21)")
    engine = p.add_mutually_exclusive_group()
    engine.add_argument("--workers", type=_integer(1), help="recordings: run on a local dask cluster of N worker processes, at most the cores (default: the local threaded scheduler)")
    engine.add_argument("--scheduler", metavar="ADDRESS", help="recordings: run on an existing dask.distributed scheduler (tcp://host:8786)")
    p.add_argument("--refine", action="store_true", help="refine every detection by a Lorenz-Mie fit (spheres in water): the table gains index_contrast, absorption, "
                   "z_err_um, diameter_err_um, index_err, fit_residual, refined, outside_training; then the network looks again in what the fit leaves unexplained "
                   "and adds the particles it finds there of the sample's material (--material, else 0.26); one fitting process per core (docs/refinement.md)")
    p.add_argument("--threshold", type=_number(0.0, above=True), help="smallest detection score kept, below 1 for focus models (default: the model's; with --refine 0.8 of it, the fit checks the rest and drops those below the model's that it cannot refine)")
    p.add_argument("--material", type=_number(-0.9, 2.5), metavar="N", help="refine, and keep the particles of index contrast n_p - n_m = N (0.26: polystyrene in water)")
    p.set_defaults(run=_cmd_predict)

    p = sub.add_parser("refine", help="find the particles of one hologram and fit each by Lorenz-Mie theory, with no trained model", parents=[_FORCE])
    p.add_argument("holo", metavar="HOLO", help="the hologram (TIFF, PNG, BMP)")
    p.add_argument("--config", required=True, help="optics (the pixel pitch at the sample), the depths searched and the expected diameters")
    p.add_argument("--out", required=True, metavar="PARTICLES.csv", help="the particle table: CSV, or Parquet when the name ends in .parquet; provenance beside it as .json")
    p.add_argument("--background", metavar="BG", help="a hologram taken without particles, divided out (default: the hologram's own mean)")
    p.add_argument("--dark", metavar="DARK", help="a frame taken without light (the camera's dark counts), taken off the hologram and the background")
    p.add_argument("--index-contrast", type=_number(-0.9, 2.5), default=0.26, metavar="N", help="n_p - n_m where every fit starts (default 0.26: polystyrene in water)")
    p.add_argument("--medium-index", type=_number(1.0, 5.0), default=1.33, metavar="N", help="refractive index of the liquid the particles are in (default 1.33: water)")
    p.add_argument("--max-particles", type=_integer(1), default=64, metavar="N", help="the most particles the table holds: the strongest detections, then the residual's (default 64)")
    p.add_argument("--detection-rounds", type=_integer(1), default=pipeline.DETECTION_ROUNDS, metavar="N",
                   help=f"looks for particles: the hologram, then the residual the fitted particles leave, until one finds nothing new (default {pipeline.DETECTION_ROUNDS}; 1: the first look's detections alone)")
    p.add_argument("--depth-window-um", type=_number(0.0, above=True), metavar="UM", help="depths each fit scans on both sides of its guess (default: a quarter of the config's depth range, at most 400)")
    p.add_argument("--patch-um", type=_number(0.0, above=True), metavar="UM", help="largest patch edge each fit sees (default: 128 pixels of the pitch the fit sees, binned where finer than half the medium wavelength); narrower patches suit crowded fields")
    p.set_defaults(run=_cmd_refine)

    p = sub.add_parser("track", help="link the particles of a recording into 3-D tracks (trackpy)", parents=[_FORCE])
    p.add_argument("particles", metavar="PARTICLES.csv", help="a particle table with a frame column (CSV or .parquet)")
    p.add_argument("--out", required=True, metavar="TRACKS.csv", help="the tracks table: CSV, or Parquet when the name ends in .parquet")
    p.add_argument("--search-range-um", type=_number(0.0, above=True), default=60.0,
                   help="largest displacement between two frames a particle is seen in (µm, default 60: a predicted depth may jump by a 50 µm plane)")
    p.add_argument("--axial-search-range-um", type=_number(0.0, above=True), help="a separate search range along z (µm; default: --search-range-um)")
    p.add_argument("--memory", type=_integer(0, 10000), default=0, help="frames a particle may be missed and keep its track, at most 10000 (default 0)")
    p.set_defaults(run=_cmd_track)

    p = sub.add_parser("diagnose", help="diagnose the sim-to-real gap of one or more holograms of a setup: which effect, where, how much", parents=[_FORCE])
    p.add_argument("holo", metavar="HOLO", nargs="+", help="holograms of one setup: files, folders of images or multi-page TIFFs; up to 3 evenly spaced frames are diagnosed, each on its own, and pooled")
    p.add_argument("--config", required=True)
    p.add_argument("--out", required=True, metavar="REPORT_DIR")
    p.add_argument("--roi", type=_integer(0), nargs=2, metavar=("X", "Y"), help="a reference place recorded in the report (all tiles are used)")
    p.add_argument("--background", metavar="BG")
    p.add_argument("--calibration", metavar="CALIB.json", help="recorded as provenance")
    p.add_argument("--tile", type=_integer(1), metavar="PX",
                   help="tile edge in pixels: the held-out checkerboard gets the frame's shorter side over PX tiles per side, at most 16 (default 4 x 4 tiles)")
    p.add_argument("--seed", type=_SEED, default=0, help="recorded in the report's provenance (the diagnosis draws nothing at random)")
    p.set_defaults(run=_cmd_diagnose)

    p = sub.add_parser("evaluate", help="score a particle table against a reference, one-to-one")
    p.add_argument("pred", metavar="PRED.csv")
    p.add_argument("truth", metavar="TRUTH.csv")
    p.add_argument("--lateral-tol-um", type=_number(0.0, above=True), help="lateral match radius (µm; default 22)")
    p.add_argument("--axial-tol-um", type=_number(0.0, above=True), help="axial match distance (µm; default 150)")
    p.add_argument("--json", action="store_true", help="print the metrics JSON on stdout")
    p.set_defaults(run=_cmd_evaluate)

    p = sub.add_parser("demo", help="run the whole pipeline on the built-in real hologram", parents=[_FORCE])
    p.add_argument("--out", default="napari-lbs-demo", metavar="DIR")
    p.add_argument("--quick", action="store_true", help="a token run on one tile (about a minute)")
    p.add_argument("--calibrated", action="store_true", help="train on the seed's LBS data (calibrated Holo-processing of opaque discs), not transparent spheres")
    p.add_argument("--seed", type=_SEED, default=0)
    p.set_defaults(run=_cmd_demo)
    return parser


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
    try:
        with interruptible():  # SIGTERM and Ctrl-C unwind, so every temporary file is removed on the way out
            size_threads()  # torch, BLAS and the FFTs on the cores this process may run on, or NAPARI_LBS_THREADS
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
    return 0


def console_main() -> None:
    """The ``napari-lbs`` console script: `main`, and its exit status.

    An interrupted command leaves with 130 through ``os._exit`` once its streams are flushed:
    a SIGTERM that lands inside an import (numpy loads submodules lazily) makes CPython end
    the process with SIGINT at shutdown, although `main` caught it (exit -2 instead of 130).
    """
    status = main()
    if status == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        _silence_streams()
        _end_children()
        os._exit(130)
    sys.exit(status)


def _silence_streams() -> None:
    """Point this process's standard output and error at the null device, once its last line is written.

    A pool abandoned while it starts spawns workers until the process ends: one spawned
    after `_end_children` has looked reads a closed pipe and prints a traceback on the
    stream it inherits. Silenced first, every worker either exists when `_end_children`
    looks (and is killed) or inherits the null device.
    """
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        for stream in (1, 2):
            os.dup2(null, stream)
    finally:
        os.close(null)


def _end_children() -> None:
    """Kill every process this one started that is still running, before an interrupted command leaves.

    A pool or cluster abandoned while it starts goes on spawning workers in a helper thread;
    a worker still being handed its start-up data when the command leaves reads a closed pipe
    and prints a traceback, and one already running lingers until it notices its parent gone.
    psutil (a dependency of dask.distributed) sees them all, those being spawned included;
    without it, the workers multiprocessing knows of.
    """
    try:
        import psutil
    except ImportError:
        import multiprocessing

        for child in multiprocessing.active_children():
            child.kill()
        return
    for child in psutil.Process().children(recursive=True):
        try:
            child.kill()
        except psutil.Error:
            pass  # gone already


if __name__ == "__main__":
    console_main()
