"""The loop's size distribution: training data with the sizes a diagnosis measured, against the config's uniform sizes.

A pseudo-real hologram (`pseudoreal.py`: polystyrene spheres in water, Lorenz–Mie theory,
pixel integration, a beam envelope, photon noise, 8 bits; a forward model the project never
trains on) of a monodisperse sample: 100 spheres in 1024² whose diameters are normal around
25 µm with a spread of ``--sd-um`` (clipped to the config's 20–30 µm), 50 debris spheres of
n 1.45 and 3–12 µm per window, and spheres and debris in a 128-pixel margin, none of them
but the 100 in the truth. The diagnosis (`diagnose_scene`) sees the hologram, never its
truth. Two models are trained the same way (the demo's ``small`` network, focus
formulation, ``--epochs`` epochs on ``--groups`` groups, threshold chosen on held-out
synthetic groups) on the seed's simulation (opaque discs, no calibration) plus what the
report says, as ``generate --effects-from`` takes it (its effects, its small scatterers as
unlabelled impurities):

``uniform``   the particles' diameters uniform over the config's range (``--uniform-sizes``);
``measured``  their diameters drawn from the size distribution the report's scene fitted.

Both predict the hologram; one-to-one ER/JI (22 µm, 150 µm), the matched particles' median
|Δz|, median |Δd| and median Δd (bias) are printed and written to ``--out``/results.json.
Every stage is cached in ``--out`` and training resumes from its last epoch. Seeds are
fixed: the same result each run.

Run: python benchmarks/bench_measured_sizes.py [--out DIR] [--groups G] [--epochs E] [--sd-um SD]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pseudoreal  # noqa: E402

from napari_lbs._core import (  # noqa: E402
    InputProcessing,
    TrainingSettings,
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
from napari_lbs._core.foundation._files import write_json  # noqa: E402
from napari_lbs._core.learning._metrics import depth_errors_um  # noqa: E402
from napari_lbs._core.physics import distractors_from_report, sizes_from_report  # noqa: E402

COUNT = 100  # the built-in hologram's density
WITH_DISTRACTORS = {"impurities": 50, "margin_px": 128}


def _hologram(out: Path, sd_um: float) -> tuple[np.ndarray, dict]:
    import tifffile

    image_path, truth_path = out / "hologram.tif", out / "hologram_truth.csv"
    if not image_path.is_file():
        start = time.perf_counter()
        image, truth = pseudoreal.pseudo_real(COUNT, seed=7, diameter_sd_um=sd_um, **WITH_DISTRACTORS)
        write_particles(truth_path, truth, force=True)
        tifffile.imwrite(image_path, image)
        print(f"hologram: {COUNT} Lorenz-Mie spheres (diameter SD {sd_um} um) in {time.perf_counter() - start:.0f} s", flush=True)
    return read_hologram(image_path), read_particles(truth_path)


def run(out: Path, *, groups: int, epochs: int, sd_um: float) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    config = load_config(None)
    hologram, truth = _hologram(out, sd_um)
    report_path = out / "diagnosis" / "report.json"
    if not report_path.is_file():
        start = time.perf_counter()
        diagnosis = diagnose_scene(hologram, config)
        write_report(diagnosis, out / "diagnosis", provenance={"source": "pseudo-real monodisperse hologram with distractors"}, force=True)
        print(f"diagnosis: {time.perf_counter() - start:.0f} s, verdict {diagnosis.report['verdict']['id']}", flush=True)
    report = json.loads(report_path.read_text())
    effects = effects_from_report(report, name=str(report_path))
    distractors = distractors_from_report(report, tile_px=config.tile.size, diameter_min_um=config.particles.diameter_min_um, name=str(report_path))
    sizes = sizes_from_report(report, diameter_range_um=(config.particles.diameter_min_um, config.particles.diameter_max_um), name=str(report_path))
    results = {"load_average_before": os.getloadavg(), "sd_um": sd_um, "groups": groups, "epochs": epochs, "verdict": report["verdict"]["id"], "effects": effects,
               "distractors": distractors.to_dict(), "sizes": sizes.to_dict() if sizes else None,
               "truth_diameter_quartiles_um": np.percentile(truth["diameter_um"], [25, 50, 75]).round(3).tolist(), "stages": {}}
    print(f"report: {results['verdict']}, impurities {results['distractors']}, sizes {results['sizes']}", flush=True)
    for stage, stage_sizes in (("uniform", None), ("measured", sizes)):
        model_path, log_path = out / f"{stage}.pt", out / f"{stage}.json"
        done = len(json.loads(log_path.read_text())["epochs"]) if log_path.is_file() else 0
        if done < epochs:
            start = time.perf_counter()
            dataset = generate_dataset(out / f"data_{stage}", config, groups=groups, processing=InputProcessing(), effects=effects, distractors=distractors,
                                       sizes=stage_sizes, seed=0)
            generated = time.perf_counter() - start
            trained = train_model(dataset, model_path, settings=TrainingSettings(epochs=epochs, seed=0), resume=model_path.with_suffix(".last.pt").is_file(), force=True)
            print(f"{stage}: generated {groups} groups in {generated:.0f} s, trained {epochs} epochs in {trained.log['seconds']:.0f} s", flush=True)
        result = predict_particles(hologram, model_path, config, device="cpu")
        metrics = score_particles(result.particles, truth)
        pairs = np.array(match_particles(result.particles, truth), dtype=int).reshape(-1, 2)
        dd = result.particles["diameter_um"][pairs[:, 0]] - truth["diameter_um"][pairs[:, 1]]
        dz = np.abs(depth_errors_um(result.particles, truth))
        row = {**metrics, "median_abs_dz_um": float(np.median(dz)) if dz.size else None, "median_abs_dd_um": float(np.median(np.abs(dd))) if dd.size else None,
               "median_dd_um": float(np.median(dd)) if dd.size else None,
               "predicted_diameter_quartiles_um": np.percentile(result.particles["diameter_um"], [25, 50, 75]).round(3).tolist() if len(result.particles["diameter_um"]) else None}
        results["stages"][stage] = row
        print(f"{stage:9s}: ER {100 * metrics['er']:6.2f} %  JI {metrics['ji']:.3f}  TP {metrics['tp']} FP {metrics['fp']} FN {metrics['fn']}  "
              f"median |dz| {row['median_abs_dz_um'] or float('nan'):.0f} um  median |dd| {row['median_abs_dd_um'] or float('nan'):.2f} um  "
              f"median dd {row['median_dd_um'] or float('nan'):+.2f} um", flush=True)
    results["load_average_after"] = os.getloadavg()
    write_json(out / "results.json", results)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="measured-sizes-bench", help="cache and results folder")
    parser.add_argument("--groups", type=int, default=64)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--sd-um", type=float, default=0.8, help="the spheres' diameter spread around 25 um (default 0.8)")
    args = parser.parse_args()
    run(Path(args.out), groups=args.groups, epochs=args.epochs, sd_um=args.sd_um)


if __name__ == "__main__":
    main()
