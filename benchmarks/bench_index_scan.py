"""Can a frame tell its spheres' index contrast? The scene's strongest spheres refitted with the contrast held at each value of a grid.

The scene diagnosis fits every particle with its index contrast free, but from the
refinement's start (0.26) and within the phase-delay valley it starts in: its index
percentiles describe the fits, not the material (docs/diagnosis.md, Reading the report). Here
the strongest ``--spheres`` particles of the frame's scene (`diagnose_scene`'s fitted table,
strongest first) are fitted again by `refine_particles` with the index contrast held at each
value of ``--grid`` and the absorption at 0 (position, depth and size free, one round), and
the mean squared relative residual of the fits (``fit_residual``) is printed per value. A
frame that holds its spheres' contrast shows a minimum there; a flat curve says the fits
cannot read it. Each line also gives the refitted diameters' median.

    python benchmarks/bench_index_scan.py real --out benchmarks/results/diagnosis/index_scan_real.json
    python benchmarks/bench_index_scan.py frame /tmp/dev/polystyrene.tif --out benchmarks/results/diagnosis/index_scan_polystyrene.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from napari_lbs._core import load_config, load_sample_hologram, read_hologram
from napari_lbs._core.foundation import available_threads
from napari_lbs._core.gap import SceneDiagnosisSettings, diagnose_scene
from napari_lbs._core.refine import RefineSettings, refine_particles

_GRID = (0.12, 0.18, 0.22, 0.24, 0.25, 0.26, 0.27, 0.28, 0.30, 0.36, 0.40)


def scan(image: np.ndarray, *, spheres: int, grid: tuple[float, ...], workers: int) -> dict:
    """The frame's scene (`diagnose_scene`), then its strongest ``spheres`` refitted at each index contrast of ``grid``."""
    config = load_config()
    settings = RefineSettings(min_gain=0.0, workers=workers)
    diagnosis = diagnose_scene(image, config, settings=SceneDiagnosisSettings(refine=settings))
    table = diagnosis.particles.iloc[:spheres][["x_um", "y_um", "z_um", "diameter_um"]].reset_index(drop=True)
    rows = []
    for contrast in grid:
        started = time.perf_counter()
        fitted = refine_particles(image / np.mean(image), table, config, fixed={"index_contrast": float(contrast), "absorption": 0.0},
                                  settings=RefineSettings(min_gain=0.0, workers=workers, rounds=1))
        rows.append({"index_contrast": contrast, "spheres": int(len(fitted)), "mean_squared_residual": float(np.mean(fitted["fit_residual"] ** 2)),
                     "median_residual": float(np.median(fitted["fit_residual"])), "diameter_median_um": float(np.median(fitted["diameter_um"])),
                     "seconds": round(time.perf_counter() - started, 1)})
        print(f"contrast {contrast:.3f}: {len(fitted)} spheres, mean squared residual {rows[-1]['mean_squared_residual'] * 1e4:.2f}e-4, "
              f"median diameter {rows[-1]['diameter_median_um']:.2f} um, {rows[-1]['seconds']} s", flush=True)
    best = min(rows, key=lambda row: row["mean_squared_residual"])
    others = [row["mean_squared_residual"] for row in rows if row is not best]
    return {"scene_particles": int(len(diagnosis.particles)), "spheres": int(len(table)), "rows": rows, "best": best["index_contrast"],
            "best_over_next": float(best["mean_squared_residual"] / min(others)) if others else None,
            "scene_index_percentiles": diagnosis.report["scene"]["index_contrast"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", choices=("real", "frame"))
    parser.add_argument("path", nargs="?", help="the frame (with 'frame')")
    parser.add_argument("--spheres", type=int, default=64)
    parser.add_argument("--grid", default=",".join(f"{v:g}" for v in _GRID), help="index contrasts, comma-separated")
    parser.add_argument("--workers", type=int, default=available_threads())
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    image = load_sample_hologram() if args.source == "real" else read_hologram(args.path)
    load_before = os.getloadavg()[0]
    result = scan(np.asarray(image, np.float64), spheres=args.spheres, grid=tuple(float(v) for v in args.grid.split(",")), workers=args.workers)
    result.update({"source": args.source if args.source == "real" else str(args.path), "load_average": [load_before, os.getloadavg()[0]]})
    print(f"best {result['best']} (its residual over the next best's: {result['best_over_next']:.3f}); load {load_before:.1f} -> {os.getloadavg()[0]:.1f}")
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
