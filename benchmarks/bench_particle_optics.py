"""Particle optics on the built-in real hologram: does the data prefer transparent spheres to opaque ones?

The scene is found without a network (`find_particles`), the strongest ``--particles``
guesses are refined with the index contrast held at each value of a grid (absorption 0:
transparent spheres) and once as opaque spheres (index contrast 0, absorption ``--opaque-kappa``),
every other parameter fitted. Per particle and model the fit's relative rms residual is
kept; reported are the mean squared residual over the particles refined under every model,
each particle's best index contrast, and the paired difference opaque − best transparent,
with the load average before and after. A second part starts the free fit (index contrast
fitted) at several values, to show whether the fitted index follows its start.

    python benchmarks/bench_particle_optics.py --particles 16 --out benchmarks/results/diagnosis/particle_optics.json
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import pandas as pd

from napari_lbs._core import ExperimentConfig, RefineSettings, find_particles, load_sample_hologram, refine_particles


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=16)
    parser.add_argument("--grid", type=float, nargs="+", default=[0.06, 0.12, 0.18, 0.22, 0.26, 0.30, 0.36, 0.45])
    parser.add_argument("--starts", type=float, nargs="+", default=[0.05, 0.26, 0.45])
    parser.add_argument("--opaque-kappa", type=float, default=1.0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    load = [os.getloadavg()[0]]
    hologram = load_sample_hologram().astype(np.float64)
    hologram /= hologram.mean()
    config = ExperimentConfig()
    started = time.perf_counter()
    guesses = pd.DataFrame(find_particles(hologram, config, max_particles=args.particles))
    seconds = {"find": round(time.perf_counter() - started, 1)}
    settings = RefineSettings(workers=1, min_gain=0.0)
    models = {"opaque": {"index_contrast": 0.0, "absorption": args.opaque_kappa}}
    models.update({f"{value:g}": {"index_contrast": value, "absorption": 0.0} for value in args.grid})
    residual, diameters = {}, {}
    for name, fixed in models.items():
        started = time.perf_counter()
        table = refine_particles(hologram, guesses, config, fixed=fixed, settings=settings)
        seconds[name] = round(time.perf_counter() - started, 1)
        residual[name] = table["fit_residual"].to_numpy(np.float64)
        diameters[name] = table["diameter_um"].to_numpy(np.float64)
        print(name, seconds[name], "s", flush=True)
    costs = np.array([residual[name] ** 2 for name in models])
    common = np.all(np.isfinite(costs), axis=0)
    costs = costs[:, common]
    names = list(models)
    transparent = costs[1:]
    best = np.argmin(transparent, axis=0)
    free = {}
    for start in args.starts:
        table = refine_particles(hologram, guesses, config, settings=RefineSettings(workers=1, index_contrast=start))
        kept = table[table["refined"]]
        free[f"{start:g}"] = {"index_contrast_quartiles": np.percentile(kept["index_contrast"], [25, 50, 75]).round(4).tolist(),
                              "median_fit_residual": round(float(kept["fit_residual"].median()), 5), "diameter_median_um": round(float(kept["diameter_um"].median()), 2)}
        print("free fit from", start, free[f"{start:g}"], flush=True)
    load.append(os.getloadavg()[0])
    result = {
        "particles": int(common.sum()),
        "mean_squared_residual": {name: round(float(row.mean()), 6) for name, row in zip(names, costs, strict=True)},
        "best_index_contrast_per_particle": [float(names[1 + b]) for b in best],
        "opaque_minus_best_transparent": {"mean": float((costs[0] - transparent.min(axis=0)).mean()), "per_particle": (costs[0] - transparent.min(axis=0)).round(6).tolist()},
        "diameter_median_um": {name: round(float(np.median(d[common])), 2) for name, d in diameters.items()},
        "free_fit_by_start": free,
        "seconds": seconds,
        "load_average": load,
    }
    with open(args.out, "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=1)
    print(json.dumps({k: result[k] for k in ("particles", "mean_squared_residual", "free_fit_by_start")}, indent=1))


if __name__ == "__main__":
    main()
