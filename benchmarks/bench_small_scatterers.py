"""The small scatterers a scene diagnosis measures, against the debris a pseudo-real frame holds.

Frames from `pseudoreal.py` (Lorenz–Mie polystyrene spheres of 20–30 µm, the real
hologram's density, photon noise and 8 bits; debris of index `pseudoreal.IMPURITY_INDEX`
at uniform positions and depths; spheres and debris in a margin around the window, as on a
crop of a larger sensor), 512² at 2.2 µm. Each is diagnosed (`diagnose_scene`, the default
settings) and the report's `scene.small_scatterers` is read as `generate --effects-from`
reads it (`distractors_from_report`, 256-pixel tiles).

`FROZEN` was fixed before its first run and is scored once; ``--set development`` holds the
frames the counting rule was looked at on (the control frames of `withheld_suite.py`'s
development suite and `bench_pseudoreal.py`'s frame with debris are its other evidence).

Pass rules, fixed with the set: a frame without debris adds no impurities to training data
(``impurities_per_tile`` 0); a frame with debris adds at least one per tile, its largest
reported diameter is below the particles' 20 µm, and it counts no more small scatterers than
the window holds debris (plus 2).

    python benchmarks/bench_small_scatterers.py --set frozen --out benchmarks/results/diagnosis/small_scatterers_frozen_<date>.json
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

from napari_lbs._core import ExperimentConfig, diagnose_scene  # noqa: E402
from napari_lbs._core.physics import distractors_from_report  # noqa: E402

SIZE = 512
SPHERES = 25  # the real hologram's density: 100 in 1024²
MARGIN_PX = 64
# name: (seed, debris per window, their diameter range in µm)
FROZEN = {"clean-a": (41101, 0, (3.0, 12.0)), "clean-b": (41102, 0, (3.0, 12.0)), "debris-12": (41103, 12, (3.0, 12.0)),
          "debris-24": (41104, 24, (4.0, 14.0)), "debris-8-large": (41105, 8, (6.0, 16.0))}
DEVELOPMENT = {"clean": (7, 0, (3.0, 12.0)), "debris-12": (8, 12, (3.0, 12.0))}
SETS = {"frozen": FROZEN, "development": DEVELOPMENT}


def score(name: str, seed: int, debris: int, sizes: tuple[float, float], config: ExperimentConfig) -> dict:
    started = time.perf_counter()
    image, _, truth = pseudoreal.pseudo_real(SPHERES, size=SIZE, seed=seed, impurities=debris, impurity_diameter_um=sizes, margin_px=MARGIN_PX, impurities_truth=True)
    made = time.perf_counter() - started
    diagnosis = diagnose_scene(image, config)
    found = diagnosis.report["scene"]["small_scatterers"]
    impurities = distractors_from_report(diagnosis.report, tile_px=256, diameter_min_um=config.particles.diameter_min_um)
    in_window = int(truth["diameter_um"].size)
    if debris == 0:
        passed = impurities.impurities_per_tile == 0
    else:
        passed = impurities.impurities_per_tile >= 1 and found["diameter_um"] is not None and found["diameter_um"][1] < config.particles.diameter_min_um \
            and found["count"] <= in_window + 2
    row = {"seed": seed, "debris_per_window": debris, "debris_diameter_um": list(sizes), "debris_in_window": in_window,
           "debris_in_window_diameter_um": [float(truth["diameter_um"].min()), float(truth["diameter_um"].max())] if in_window else None,
           "found": found, "impurities_per_tile": impurities.impurities_per_tile,
           "impurity_diameter_um": [impurities.impurity_diameter_min_um, impurities.impurity_diameter_max_um] if impurities.active else None,
           "verdict": diagnosis.report["verdict"]["id"], "passed": bool(passed), "make_s": round(made, 1), "diagnose_s": diagnosis.seconds}
    print(f"{name}: {in_window} debris in the window; found {found['count']} ({found['per_256px_tile']:.2f} per tile, {found['diameter_um']} um) -> "
          f"{impurities.impurities_per_tile} impurities per tile; {'pass' if passed else 'FAIL'} ({diagnosis.seconds:.0f} s)", flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", choices=tuple(SETS), default="development")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    load = [os.getloadavg()[0]]
    config = ExperimentConfig()
    rows = {name: score(name, *case, config) for name, case in SETS[args.set].items()}
    load.append(os.getloadavg()[0])
    result = {"set": args.set, "cases": rows, "passed": sum(row["passed"] for row in rows.values()), "of": len(rows), "load_average": load}
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"{result['passed']} of {result['of']} pass; load average {load[0]:.2f} -> {load[1]:.2f}")


if __name__ == "__main__":
    main()
