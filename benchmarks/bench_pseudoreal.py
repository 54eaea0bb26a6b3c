"""Pseudo-real benchmark: detection accuracy on Lorenz–Mie holograms with ground truth.

The holograms come from `pseudoreal.py` (transparent polystyrene spheres in water, Lorenz–Mie
theory, pixel integration, a beam envelope, photon noise, 8 bits): a forward model the project
never trains on. Three models are trained the same way (the demo's: ``small`` network, focus
formulation, ``--epochs`` epochs on ``--groups`` groups, threshold chosen on held-out
synthetic groups only) on three kinds of synthetic data:

``plain``    the seed's simulation: opaque discs, Holo-processing (0, 0, 1), no calibration;
``lbs``      LBS: Holo-processing calibrated (GA, SSIM) to the pseudo-real hologram;
``effects``  LBS plus the effects that `diagnose` names for that hologram (`effects_from_report`);
``transparent`` as ``effects``, plus transparent spheres stated from the physics rather than
             fitted: ``particle_phase`` with the phase delay through a 25 µm polystyrene sphere in
             water, 2π/λ · (1.59 − 1.33) · 25 µm = 62 rad, transmission 1 (what a user who knows
             the sample would add with ``generate --effect``);
``plain_transparent`` the seed's simulation (no calibration) with those transparent spheres.
``plain_effects`` the seed's simulation (no calibration) plus the effects `diagnose` names: the
             closed loop for the demo's uncalibrated recipe, against ``plain``.
``distractors`` as ``plain_transparent``, plus the demo's unlabelled distractors (`Distractors`:
             6 impurities of 4–14 µm per tile, neighbours in a 96-pixel margin).
``plain_report`` the closed loop on a hologram that holds debris: the seed's simulation (no
             calibration) plus what the diagnosis of the hologram *with distractors* reports,
             its effects (`effects_from_report`) and the small scatterers its scene measured
             as unlabelled impurities (`distractors_from_report`), as
             ``generate --effects-from`` takes them; against ``plain``.
``plain_report_effects`` as ``plain_report`` without the impurities (``--impurities 0``): what
             the report's effects alone bring.
``lbs_report`` LBS (``lbs``, what ``demo --calibrated`` trains on) plus all that
             ``generate --effects-from`` takes from the report of the hologram with
             distractors, its effects, its small scatterers as impurities and its fitted
             particles' sizes (`sizes_from_report`), the calibration applied on top
             (``generate --keep-calibration``); against ``lbs``.
``loop_report`` the closed loop from the seed's recipe as ``generate --calibration C
             --effects-from REPORT`` makes it (`training_processing`: the report's model
             replaces the calibration's Holo-processing); against ``lbs``.
``loop_report_margin`` as ``loop_report`` with neighbours in the demo's margin
             (``--neighbours-margin-px 96``).
``plain_report_sizes`` as ``plain_report`` with the fitted sizes too: all that
             ``generate --effects-from`` takes, on the uncalibrated recipe.
``lbs_report_uniform`` as ``lbs_report`` with the config's uniform sizes (``--uniform-sizes``).

Each model predicts the pseudo-real hologram at the real hologram's density (~100 spheres in
1024²), the same 100 spheres with distractors (50 small debris spheres of n 1.45, 3–12 µm, per
window, and spheres and debris outside the window: a 128-pixel margin; none of them in the
truth), and 4× the density; one-to-one ER/JI (22 µm, 150 µm) and |Δz| of the matches are printed.
Calibration and diagnosis see only the real-density hologram (``plain_report``'s diagnosis the
one with distractors), never their truth. Every stage
is cached in ``--out`` and training resumes from its last epoch, so an interrupted run
continues where it stopped. Seeds are fixed: same result each run.

Run: python benchmarks/bench_pseudoreal.py [--out DIR] [--groups G] [--epochs E] [--stages S ...] [--seed S] [--real-density-only] [--without-4x] [--check]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pseudoreal  # noqa: E402

from napari_lbs._core.pipeline import DEMO_SAMPLE_DISTRACTORS, training_processing  # noqa: E402

from napari_lbs._core import (
    CalibrationSettings,
    Distractors,
    InputProcessing,
    TrainingSettings,
    calibrate_hologram,
    diagnose_scene,
    effects_from_report,
    generate_dataset,
    load_config,
    match_particles,
    predict_particles,
    read_hologram,
    read_particles,
    score_particles,
    train_model,
    write_particles,
    write_report,
)
from napari_lbs._core.foundation._files import write_json
from napari_lbs._core.physics import distractors_from_report, sizes_from_report
from napari_lbs._core.learning._metrics import depth_errors_um

DENSITIES = {"real density": 100, "4x density": 400}
EDGE_BAND_UM = 200.0  # false positives this close to the window's edge are counted apart (neighbours' fringes)
WITH_DISTRACTORS = {"impurities": 50, "margin_px": 128}  # the real density's 100 spheres, with distractors
DEMO_DISTRACTORS = Distractors(**DEMO_SAMPLE_DISTRACTORS)
TRANSPARENT = {"particle_phase": {"index_contrast": round(pseudoreal.N_PARTICLE - pseudoreal.N_MEDIUM, 3), "transmission": 1.0}}


def _hologram(folder: Path, name: str, count: int, seed: int, distractors: dict | None = None) -> tuple[np.ndarray, dict]:
    import tifffile

    image_path, truth_path = folder / f"{name}.tif", folder / f"{name}_truth.csv"
    if not image_path.is_file():
        start = time.perf_counter()
        image, truth = pseudoreal.pseudo_real(count, seed=seed, **(distractors or {}))
        tifffile.imwrite(image_path, image)
        write_particles(truth_path, truth, force=True)  # a run stopped before its image left the truth: made again
        print(f"{name}: {count} Lorenz-Mie spheres in {time.perf_counter() - start:.0f} s", flush=True)
    return read_hologram(image_path), read_particles(truth_path)


def run(out: Path, groups: int, epochs: int, only: list[str] | None = None, real_density_only: bool = False, without_4x: bool = False, seed: int = 0) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    config = load_config(None)
    densities = {"real density": DENSITIES["real density"]} if real_density_only or without_4x else DENSITIES
    holograms = {label: _hologram(out, label.replace(" ", "_"), count, seed=7 + i) for i, (label, count) in enumerate(densities.items())}
    experiment = holograms["real density"][0]  # what the user has: a hologram, no truth
    if not real_density_only:
        holograms["with distractors"] = _hologram(out, "real_density_distractors", DENSITIES["real density"], seed=7, distractors=WITH_DISTRACTORS)

    calibration_path = out / "calibration.json"
    calibrated = not only or {"lbs", "transparent", "effects", "lbs_report", "lbs_report_uniform", "loop_report", "loop_report_margin"} & set(only)
    if calibrated and not calibration_path.is_file():
        write_json(calibration_path, calibrate_hologram(experiment, config, settings=CalibrationSettings(generations=40, seed=0)).to_json())
    calibration = json.loads(calibration_path.read_text()) if calibrated else {"params": None, "ssim": None}
    report_path = out / "diagnosis" / "report.json"
    needs_report = not only or {"transparent", "effects", "plain_effects"} & set(only)
    if needs_report and not report_path.is_file():
        start = time.perf_counter()
        diagnosis = diagnose_scene(experiment, config)
        write_report(diagnosis, out / "diagnosis", provenance={"source": "pseudo-real hologram, real density"}, force=True)
        print(f"diagnosis: {time.perf_counter() - start:.0f} s, verdict {diagnosis.report['verdict']}", flush=True)
    report = json.loads(report_path.read_text()) if needs_report else {"verdict": None, "posterior": None}
    effects = effects_from_report(report, name=str(report_path)) if needs_report else {}
    busy_report_path = out / "diagnosis_distractors" / "report.json"
    busy_effects, busy_distractors, busy_report, busy_sizes = {}, Distractors(), {}, None
    if (not only or {"plain_report", "plain_report_effects", "lbs_report", "plain_report_sizes", "lbs_report_uniform", "loop_report", "loop_report_margin"} & set(only)) and not real_density_only:
        if not busy_report_path.is_file():
            start = time.perf_counter()
            diagnosis = diagnose_scene(holograms["with distractors"][0], config)
            write_report(diagnosis, out / "diagnosis_distractors", provenance={"source": "pseudo-real hologram with distractors"}, force=True)
            print(f"diagnosis with distractors: {time.perf_counter() - start:.0f} s, verdict {diagnosis.report['verdict']['id']}", flush=True)
        busy_report = json.loads(busy_report_path.read_text())
        busy_effects = effects_from_report(busy_report, name=str(busy_report_path))
        busy_distractors = distractors_from_report(busy_report, tile_px=config.tile.size, diameter_min_um=config.particles.diameter_min_um, name=str(busy_report_path))
        busy_sizes = sizes_from_report(busy_report, diameter_range_um=(config.particles.diameter_min_um, config.particles.diameter_max_um), name=str(busy_report_path))

    lbs = InputProcessing.from_calibration(calibration) if calibrated else None
    loop = training_processing(calibration if calibrated else None, from_report=True)[0]  # what generate --calibration --effects-from makes
    stages = {
        "plain": (InputProcessing(), {}, Distractors(), None),
        "lbs": (lbs, {}, Distractors(), None),
        "plain_transparent": (InputProcessing(), TRANSPARENT, Distractors(), None),
        "transparent": (lbs, {**effects, **TRANSPARENT}, Distractors(), None),
        "effects": (lbs, effects, Distractors(), None),
        "plain_effects": (InputProcessing(), effects, Distractors(), None),
        "distractors": (InputProcessing(), TRANSPARENT, DEMO_DISTRACTORS, None),
        "plain_report": (InputProcessing(), busy_effects, busy_distractors, None),
        "plain_report_effects": (InputProcessing(), busy_effects, Distractors(), None),
        "lbs_report": (lbs, busy_effects, busy_distractors, busy_sizes),
        "plain_report_sizes": (InputProcessing(), busy_effects, busy_distractors, busy_sizes),
        "lbs_report_uniform": (lbs, busy_effects, busy_distractors, None),
        "loop_report": (loop, busy_effects, busy_distractors, busy_sizes),
        "loop_report_margin": (loop, busy_effects,
                               dataclasses.replace(busy_distractors, neighbours_margin_px=DEMO_SAMPLE_DISTRACTORS["neighbours_margin_px"]), busy_sizes),
    }
    results = {"calibration": calibration["params"], "ssim": calibration["ssim"], "verdict": report["verdict"], "posterior": report.get("posterior"), "effects": effects,
               "with_distractors_report": {"verdict": (busy_report.get("verdict") or {}).get("id"), "effects": busy_effects, "distractors": busy_distractors.to_dict(),
                                           "sizes": busy_sizes.to_dict() if busy_sizes else None, "scene": busy_report.get("scene")} if busy_report else None,
               "stages": {}}
    for stage, (processing, stage_effects, distractors, sizes) in stages.items():
        if only and stage not in only:
            continue
        # another seed (`--seed`) draws other training data and another network start: the spread of a recipe's scores
        name = stage if seed == 0 else f"{stage}_seed{seed}"
        model_path, log_path = out / f"{name}.pt", out / f"{name}.json"
        done = len(json.loads(log_path.read_text())["epochs"]) if log_path.is_file() else 0
        if done < epochs:  # not trained, or interrupted: generation and training both resume
            start = time.perf_counter()
            dataset = generate_dataset(out / f"data_{name}", config, groups=groups, processing=processing, effects=stage_effects, distractors=distractors,
                                       sizes=sizes, seed=seed)
            generated = time.perf_counter() - start
            trained = train_model(dataset, model_path, settings=TrainingSettings(epochs=epochs, seed=seed), resume=model_path.with_suffix(".last.pt").is_file(), force=True)
            print(f"{stage}: generated {groups} groups in {generated:.0f} s, trained {epochs} epochs (from epoch {done}) in {trained.log['seconds']:.0f} s", flush=True)
        scores_path = out / f"{name}_scores.json"
        log = json.loads(log_path.read_text())
        best = log["best"]
        row = json.loads(scores_path.read_text()) if scores_path.is_file() else {}
        if row.get("model_sha256") != best["sha256"]:  # scores of another model (retrained since): start over
            row = {}
        if all(label in row for label in holograms):
            results["stages"][stage] = row
            continue
        validation = next(e for e in log["epochs"] if e["epoch"] == best["epoch"])["validation"]
        row["model_sha256"] = best["sha256"]
        row["synthetic_validation"] = {"er": validation["er"], "ji": validation["ji"]}
        for label, (hologram, truth) in holograms.items():
            if label in row:
                continue
            result = predict_particles(hologram, model_path, config, device="cpu")
            metrics = score_particles(result.particles, truth)
            dz = np.abs(depth_errors_um(result.particles, truth))
            pairs = np.array(match_particles(result.particles, truth), dtype=int).reshape(-1, 2)  # int even when nothing matched
            predicted_d, true_d = result.particles["diameter_um"][pairs[:, 0]], truth["diameter_um"][pairs[:, 1]]
            diameters = {"median_abs_dd_um": float(np.median(np.abs(predicted_d - true_d))), "diameter_corr": float(np.corrcoef(predicted_d, true_d)[0, 1]),
                         "predicted_diameter_p5_p95_um": [float(v) for v in np.percentile(predicted_d, [5, 95])]} if len(pairs) > 2 else {}
            unmatched = np.setdiff1d(np.arange(len(result.particles["x_um"])), pairs[:, 0])
            extent = (hologram.shape[1] - 1) * pseudoreal.PIXEL_UM, (hologram.shape[0] - 1) * pseudoreal.PIXEL_UM
            x, y = result.particles["x_um"][unmatched], result.particles["y_um"][unmatched]
            edge = np.minimum.reduce([x, y, extent[0] - x, extent[1] - y]) < EDGE_BAND_UM
            row[label] = {**metrics, "fp_near_edge": int(edge.sum()), "median_abs_dz_um": float(np.median(dz)) if dz.size else None, **diameters, "predict_seconds": round(result.seconds, 1)}
            print(f"{stage:8s} {label:12s}: ER {100 * metrics['er']:6.2f} %  JI {metrics['ji']:.3f}  TP {metrics['tp']} FP {metrics['fp']} ({row[label]['fp_near_edge']} near the edge) FN {metrics['fn']}  "
                  f"median |dz| {row[label]['median_abs_dz_um'] or float('nan'):.0f} um  median |dd| {diameters.get('median_abs_dd_um', float('nan')):.1f} um "
                  f"(corr {diameters.get('diameter_corr', float('nan')):.2f})  (synthetic validation JI {validation['ji']:.3f})", flush=True)
        results["stages"][stage] = row
        write_json(scores_path, row)
    write_json(out / ("results.json" if seed == 0 else f"results_seed{seed}.json"), results)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="pseudoreal-bench", help="cache and results folder")
    parser.add_argument("--groups", type=int, default=64)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--stages", nargs="+", help="run only these stages (default: all)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the training data and the network (calibration and diagnosis stay those of seed 0)")
    parser.add_argument("--real-density-only", action="store_true", help="only the real-density hologram (no 4x density, no distractors): the closed loop's short form")
    parser.add_argument("--without-4x", action="store_true", help="leave the 4x density hologram out (its 400 Lorenz-Mie spheres take the longest to make)")
    parser.add_argument("--check", action="store_true", help="only check the fast Lorenz-Mie field against pylorenzmie on a full plane")
    args = parser.parse_args()
    print(f"azimuthal decomposition vs pylorenzmie on a full plane: max relative error {pseudoreal.check_azimuthal():.1e}", flush=True)
    if not args.check:
        results = run(Path(args.out), args.groups, args.epochs, args.stages, real_density_only=args.real_density_only, without_4x=args.without_4x, seed=args.seed)
        print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
