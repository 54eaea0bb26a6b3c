"""Does the mean of a training's last epochs transfer better than the epoch synthetic validation picks?

`train_model` keeps the best validated epoch (its peak JI, then ER). With ``average_last`` it
keeps instead the mean of the last epochs' weights, its batch-norm statistics measured again
(`napari_lbs._core.learning._training`). Both are validated for their own decoding settings on
the same synthetic groups; here each network's table (`predict_particles`, no refinement) is
scored at its own kept threshold on holograms of an independent Lorenz–Mie model:

* ``lensless`` networks (the demo's recipe: ``napari-lbs demo``'s data set, 5 epochs, the last 2
  validated, the mean of those 2): `bench_pseudoreal.py`'s holograms with the seed
  `LENSLESS_SEED` — the real density's 100 spheres, alone and with distractors — default
  tolerances (22 µm lateral, 150 µm axial);
* ``microscope`` networks (`bench_microscopy_lbs.py`'s recipe: its ``data_g96``, 3 epochs, all
  validated, the mean of all 3): that benchmark's ``frozen-4`` frames (six pylorenzmie frames of
  20–50 spheres), pooled, with its tolerances (0.5 µm, 2 µm).

Frozen design, written before the first run and not changed after it: training seeds 0 and 1
for each recipe, six (network pair, test set) pairs. The mean is adopted for a recipe's
default when its JI is higher than the validated epoch's in more pairs than it is lower, and
lower by more than 0.02 in none.

    python benchmarks/bench_epoch_average.py train DEMO_DATA /tmp/avg/demo-s0 --epochs 5 --seed 0 --validate-last 2 --average-last 2
    python benchmarks/bench_epoch_average.py train MICRO_DATA /tmp/avg/micro-s0 --epochs 3 --seed 0 --average-last 3
    python benchmarks/bench_epoch_average.py score --work /tmp/avg/tests --lensless DEMO_DATA /tmp/avg/demo-s0 /tmp/avg/demo-s1 \\
        --microscope MICRO_DATA /tmp/avg/micro-s0 /tmp/avg/micro-s1 --out F.json
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
import bench_threshold_transfer  # noqa: E402

LENSLESS_SEED = 20261215


def validated_epoch(run: Path) -> Path:
    """The epoch model `train_model` keeps without averaging: the best by (peak JI, ER) of the run's validated epochs (the first of ties)."""
    import torch

    best, best_score = None, None
    for path in sorted(run.glob("epoch*.pt"), key=lambda p: int(p.stem[5:])):
        validation = json.loads(torch.load(path, weights_only=True)["meta"])["validation"]
        score = (validation["peak_ji"], validation["er"])
        if best_score is None or score > best_score:
            best, best_score = path, score
    return best


def scored(model: Path, data: Path, holograms: list, tolerances: dict) -> dict:
    """The model's table scored at its own kept threshold (validated again under the current code), and its best threshold on the test."""
    rule = bench_threshold_transfer.validated(model, data)
    by_threshold = bench_threshold_transfer.model_curve(model, holograms, tolerances)
    kept = by_threshold[round(rule["threshold"], 2)]
    best = max(by_threshold, key=lambda t: by_threshold[t]["ji"])
    return {"model": str(model), "validation": rule, "kept": kept, "best_on_test": {"threshold": best, **by_threshold[best]},
            "by_threshold": {f"{t:.2f}": v for t, v in by_threshold.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    modes = parser.add_subparsers(dest="mode", required=True)
    train = modes.add_parser("train", help="train once, writing every validated epoch's model and the epochs' mean (kept.pt)")
    train.add_argument("data", type=Path)
    train.add_argument("out_dir", type=Path)
    train.add_argument("--epochs", type=int, required=True)
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--validate-last", type=int, default=0)
    train.add_argument("--average-last", type=int, required=True)
    score = modes.add_parser("score", help="score each run's validated epoch against its mean")
    score.add_argument("--work", type=Path, required=True, help="test holograms cached here")
    score.add_argument("--lensless", nargs="+", default=[], metavar="DATA_OR_RUN", help="the demo's data set folder, then its runs' folders")
    score.add_argument("--microscope", nargs="+", default=[], metavar="DATA_OR_RUN", help="the microscope data set folder, then its runs' folders")
    score.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.mode == "train":
        started = time.perf_counter()
        paths = bench_threshold_transfer.write_epoch_models(args.data, args.out_dir, epochs=args.epochs, seed=args.seed, validate_last=args.validate_last,
                                                             average_last=args.average_last)
        print(*paths, args.out_dir / "kept.pt", f"{time.perf_counter() - started:.0f} s", sep="\n", flush=True)
        return
    from napari_lbs._core.foundation import process_threads

    load_before = os.getloadavg()
    sets = bench_threshold_transfer.test_sets(args.work, lensless_seed=LENSLESS_SEED, microscope_set="frozen-4")
    rows, higher, lower = [], 0, 0
    for setup, given in (("lensless", args.lensless), ("microscope", args.microscope)):
        if not given:
            continue
        data, runs = Path(given[0]), [Path(r) for r in given[1:]]
        for run in runs:
            for name, holograms, tolerances in sets[setup]:
                started = time.perf_counter()
                epoch, mean = scored(validated_epoch(run), data, holograms, tolerances), scored(run / "kept.pt", data, holograms, tolerances)
                higher += mean["kept"]["ji"] > epoch["kept"]["ji"]
                lower += mean["kept"]["ji"] < epoch["kept"]["ji"]
                rows.append({"setup": setup, "run": str(run), "test": name, "epoch": epoch, "mean": mean, "seconds": round(time.perf_counter() - started, 1)})
                line = "; ".join(f"{label} {Path(r['model']).stem} thr {r['validation']['threshold']:.2f} JI {r['kept']['ji']:.3f} ({r['kept']['tp']}/{r['kept']['fp']}/{r['kept']['fn']}), "
                                 f"best on test {r['best_on_test']['threshold']:.2f} {r['best_on_test']['ji']:.3f}" for label, r in (("epoch", epoch), ("mean", mean)))
                print(f"{setup} {run.name} {name}: {line}", flush=True)
    largest_drop = max((r["epoch"]["kept"]["ji"] - r["mean"]["kept"]["ji"] for r in rows), default=0.0)
    verdict = {"higher": higher, "lower": lower, "pairs": len(rows), "largest_drop": largest_drop, "adopted": higher > lower and largest_drop <= 0.02}
    print(json.dumps(verdict), flush=True)
    result = {"rows": rows, "verdict": verdict, "threads": process_threads(), "load_before": load_before, "load_after": os.getloadavg()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
