"""The demo: every step in turn on the built-in real hologram, recorded in ``summary.json``."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass, replace
from pathlib import Path

from napari_lbs._core.foundation import ExperimentConfig, available_threads
from napari_lbs._core.foundation import ProgressCallback
from napari_lbs._core.foundation import write_json
from napari_lbs._core.pipeline._common import Log, StepResult, _quiet, check_outputs
from napari_lbs._core.pipeline._data_steps import GenerateRequest, TrainRequest, generate, train
from napari_lbs._core.pipeline._predict import PredictRequest, predict
from napari_lbs._core.pipeline._setup_steps import BackpropRequest, CalibrateRequest, backprop, calibrate

__all__ = ["DEMO_FILES", "DEMO_SAMPLE_EFFECTS", "DEMO_SAMPLE_DISTRACTORS", "DEMO_SAFETY_MINUTES", "DemoRequest", "demo"]


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

# What the demo writes into its folder, besides the training set ``data/`` (resumed when it was made with the same settings).
DEMO_FILES = ("zstack.tif", "calibration.json", "model.pt", "model.json", "model.last.pt", "particles.csv", "particles.json", "summary.json")


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
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    out_dir: Path
    _: KW_ONLY  # the data above, the options below
    quick: bool = False
    calibrated: bool = False
    seed: int = 0
    replace: bool = False

    def outputs(self) -> tuple[Path, ...]:
        """The files the demo writes into ``out_dir`` (`DEMO_FILES`)."""
        return tuple(Path(self.out_dir) / name for name in DEMO_FILES)


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

    out, seed, replacing = Path(request.out_dir), request.seed, request.replace
    check_outputs(request.outputs(), replace=replacing)
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
    stacked = backprop(BackpropRequest(hologram, out / "zstack.tif", config, source=sample, replace=replacing), progress=progress_for("backprop"))
    timings["backprop"] = time.perf_counter() - start

    start = time.perf_counter()
    calibration = calibrate(CalibrateRequest(hologram, out / "calibration.json", config, settings=calibration_settings, source=sample, replace=replacing),
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
                             distractors=distractors, seed=seed, workers=available_threads()), progress=progress_for("generate"))
    timings["generate"] = time.perf_counter() - start

    start = time.perf_counter()
    trained = train(TrainRequest(out / "data", out / "model.pt", settings=training, replace=replacing), progress=progress_for("train"), log=log).value
    if trained.log["stop_reason"]:
        log(f"demo: warning: training ended early ({trained.log['stop_reason']}) after {len(trained.log['epochs'])} of {training.epochs} epochs; another run with this seed may differ")
    timings["train"] = time.perf_counter() - start

    # Every detection refined by the Lorenz-Mie fit (about 20 s for the sample's 100 particles on
    # 2 cores, a small share of the demo's minutes), and the sample's material kept: its debris
    # fit as small spheres of another index contrast (docs/refinement.md).
    predicted = predict(PredictRequest(hologram, trained.model_path, out / "particles.csv", config, device=training.device, source=sample, refine=True,
                                       material_index_contrast=DEMO_SAMPLE_EFFECTS["particle_phase"]["index_contrast"], replace=replacing), progress=progress_for("predict"))
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
    write_json(out / "summary.json", summary, force=replacing)
    line = (f"demo: calibration SSIM {calibration['ssim']:.3f} ({'used' if request.calibrated else 'recorded; --calibrated trains on it'}), {data}, "
            f"trained the {training.formulation} formulation ({training.preset}, {trained.log['seconds']:.0f} s; "
            f"validated on {len(trained.log['validation_groups'])} held-out synthetic groups: ER {100 * validation['er']:.1f} %, JI {validation['ji']:.3f}), "
            f"found {summary['particle_count']} particles in the built-in hologram ({refined['detections']} proposals fitted, {refined['residual']['found']} more found "
            f"in the fit's residual, {refined['material']['other_material']} of another material set apart) -> {out}")
    return StepResult(line, summary, (predicted.paths[0], out / "summary.json"))
