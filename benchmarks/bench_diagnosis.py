"""Gap diagnosis benchmarks: the withheld-effect suites, in-simulation recovery, the seed check, the real hologram.

    python benchmarks/bench_diagnosis.py suite DIR [--level P] [--cache DIR] [--keep KEPT]
        Score a suite written by ``withheld_suite.py make`` (DIR/design.json and its holograms):
        top-1 and top-2 (the expected model first, or among the two most probable), false
        alarms among the controls, each with a 95 % Wilson interval, and the calibration of the
        reported probabilities (of the verdicts given at P >= 0.8, the share right).
    python benchmarks/bench_diagnosis.py rescore KEPT --level P [--level Q ...]
        The kept reports' verdicts at other levels (the posterior does not change with the level).
    python benchmarks/bench_diagnosis.py insim [--size PX] [--fresh N]
        The setup's diagnoser (trained and cached on first use) on N fresh simulations from its
        own prior: the share whose most probable model is the true one, per model size.
    python benchmarks/bench_diagnosis.py seeds HOLO
        The same hologram diagnosed with seeds 0, 1 and 2: verdicts and the largest posterior difference.
    python benchmarks/bench_diagnosis.py real
        The built-in real hologram: verdict, posterior, time (the diagnoser cached first).

Every figure is printed with what it was measured on; logs go to benchmarks/results/.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from napari_lbs._core import ExperimentConfig, read_hologram
from napari_lbs._core.physics._effects import EFFECTS
from napari_lbs._core.gap import DiagnosisSettings, amortized_diagnoser, diagnose_hologram, forest_posterior
from napari_lbs._core.gap._diagnose import decide
from napari_lbs._core.gap._amortized import _simulate
from napari_lbs._core.gap._scenarios import ScenarioPrior, TileGrid, catalog_candidates

CONFIG = ExperimentConfig()


def wilson(successes: int, trials: int) -> tuple[float, float]:
    """95 % Wilson score interval of a proportion."""
    if trials == 0:
        return (0.0, 1.0)
    z = 1.96
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    return (max(0.0, centre - half), min(1.0, centre + half))


def _model_name(effects: list[str]) -> str:
    """The posterior's name of a set of effects: catalog order, joined by '+' ('null' for none)."""
    return "+".join(e for e in EFFECTS if e in effects) or "null"


def _share(hits: int, trials: int) -> str:
    low, high = wilson(hits, trials)
    return f"{hits}/{trials} ({100 * hits / max(trials, 1):.0f} %, 95 % interval {100 * low:.0f}-{100 * high:.0f} %)"


def _row(case: dict, report: dict, seconds: float) -> dict:
    """One case's result line: what was expected, what was said, how sure, and the gaps."""
    expected = _model_name(case["expected"])
    ranked = list(report["posterior"])
    verdict = report["verdict"]
    named = verdict["id"] or "null"
    top = sorted(report["marginals"].items(), key=lambda kv: -kv[1])[:3]
    return {
        "case": case["name"], "size": case["size"], "expected": expected, "verdict": verdict["id"], "undecided": verdict["undecided"],
        "probability": round(verdict["probability"], 3), "p_expected": round(report["posterior"].get(expected, 0.0), 3), "top2": expected in ranked[:2],
        "right": named == expected,  # a control is right when nothing is named (nothing missing, or undecided)
        "names_one": bool(verdict["id"]) and any(e in named.split("+") for e in case["expected"]),
        "presence": {k: round(v, 3) for k, v in top}, "posterior": {k: round(v, 3) for k, v in list(report["posterior"].items())[:4]},
        "gap": round(report["gap"]["baseline"], 3), "residual": round(verdict["residual"], 3), "residual_interval": [round(v, 3) for v in verdict["residual_interval"]],
        "c2st_accuracy": round(report["gap"]["baseline_c2st_accuracy"], 3), "catalog_explains": verdict["catalog_explains"], "seconds": round(seconds, 1),
    }


def _score(rows: list[dict], title: str) -> None:
    effects = [r for r in rows if r["expected"] != "null"]
    controls = [r for r in rows if r["expected"] == "null"]
    pairs = [r for r in effects if "+" in r["expected"]]
    alarms = sum(r["verdict"] is not None for r in controls)
    confident = [r for r in rows if (r["verdict"] is not None or not r["undecided"]) and r["probability"] >= 0.8]
    print(title)
    print(f"  top-1 {_share(sum(r['right'] for r in effects), len(effects))} of the cases with a withheld effect")
    print(f"  top-2 {_share(sum(r['top2'] for r in effects), len(effects))}")
    print(f"  false alarms {_share(alarms, len(controls))} of the controls")
    print(f"  two-effect cases: both named {sum(r['right'] for r in pairs)}/{len(pairs)}, at least one {sum(r['names_one'] for r in pairs)}/{len(pairs)}")
    print(f"  calibration: of {len(confident)} answers at P >= 0.8, {sum(r['right'] for r in confident)} right")
    print(f"  undecided: {sum(bool(r['undecided']) for r in rows)}; the catalog said not to explain the data: {sum(not r['catalog_explains'] for r in rows)}")
    print(f"  time per diagnosis: median {np.median([r['seconds'] for r in rows]):.1f} s (diagnosers cached)")


def suite(folder: str, *, level: float, cache: str | None, keep: str | None, sizes: list[int] | None = None) -> None:
    design = json.loads((Path(folder) / "design.json").read_text())
    settings = DiagnosisSettings(level=level, cache_dir=cache)
    rows = []
    for case in design["cases"]:
        if sizes and case["size"] not in sizes:
            continue
        image = read_hologram(Path(folder) / case["file"])
        start = time.perf_counter()
        report = diagnose_hologram(image, CONFIG, settings=settings).report
        rows.append(_row(case, report, time.perf_counter() - start))
        print(json.dumps(rows[-1]), flush=True)
        if keep:
            Path(keep).mkdir(parents=True, exist_ok=True)
            (Path(keep) / f"{case['name']}.json").write_text(json.dumps({"case": case, "report": report, "seconds": rows[-1]["seconds"]}))
    _score(rows, f"suite {design['suite']} (seed {design['seed']}, {len(rows)} cases), level {level}:")


def rescore(folder: str, levels: list[float]) -> None:
    """The kept reports' verdicts again at other levels (`decide`: no simulation, no new diagnosis)."""
    kept = [json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))]
    for level in levels:
        rows = []
        for item in kept:
            report = item["report"]
            verdict_id, _, probability, undecided, reason = decide(report["marginals"], report["posterior"], level=level)
            report = {**report, "verdict": {**report["verdict"], "id": verdict_id, "probability": probability, "undecided": undecided, "reason": reason}}
            rows.append(_row(item["case"], report, item["seconds"]))
        _score(rows, f"{folder}: {len(rows)} kept reports at level {level}:")


def insim(size: int, fresh: int) -> None:
    grid = TileGrid((size, size), min(128, size // 4))
    known = {"quantization": {"bits": 8.0}}
    prior = ScenarioPrior(candidates=catalog_candidates(known), bits=8.0)
    settings = DiagnosisSettings()
    diagnoser = amortized_diagnoser(CONFIG, grid, prior, settings=settings)
    by_size = {0: [0, 0], 1: [0, 0], 2: [0, 0]}
    confusion: dict[str, dict[str, int]] = {}
    for index in range(10**6, 10**6 + fresh):
        _, features, _, present, _ = _simulate((index, CONFIG, grid, prior, settings.training_seed))
        _, posterior = forest_posterior(diagnoser, features)
        best = max(posterior, key=posterior.get)
        truth = _model_name(list(present))
        by_size[len(present)][0] += best == truth
        by_size[len(present)][1] += 1
        if len(present) <= 1:
            confusion.setdefault(truth, {}).setdefault(best, 0)
            confusion[truth][best] += 1
    print(f"in-simulation, {size}² sensor, {fresh} fresh simulations from the prior (diagnoser {diagnoser.key}, {diagnoser.features.shape[0]} simulations):")
    for count, (hits, trials) in by_size.items():
        print(f"  {count} effect(s): most probable model right {_share(hits, trials)}")
    for truth, answers in sorted(confusion.items()):
        total = sum(answers.values())
        print(f"  {truth}: recall {answers.get(truth, 0)}/{total}; answered " + ", ".join(f"{k} {v}" for k, v in sorted(answers.items(), key=lambda kv: -kv[1])))


def seeds(path: str) -> None:
    image = read_hologram(path)
    reports = [diagnose_hologram(image, CONFIG, settings=DiagnosisSettings(seed=seed)).report for seed in (0, 1, 2)]
    keys = set().union(*(r["posterior"] for r in reports))
    spread = max(max(r["posterior"].get(k, 0.0) for r in reports) - min(r["posterior"].get(k, 0.0) for r in reports) for k in keys)
    print(f"{path}: verdicts {[r['verdict']['id'] for r in reports]}, largest posterior difference {spread:.4f}, seconds {[r['seconds'] for r in reports]}")


def real() -> None:
    from napari_lbs._core import load_sample_hologram

    image = load_sample_hologram()
    start = time.perf_counter()
    diagnosis = diagnose_hologram(image, CONFIG)
    report = diagnosis.report
    print(json.dumps({"verdict": report["verdict"], "posterior": {k: round(v, 3) for k, v in list(report["posterior"].items())[:6]}, "gap": report["gap"]["baseline"],
                      "effects": [(e["id"], round(e["probability"], 3), round(e["gap_after"], 3)) for e in report["effects"]], "seconds": round(time.perf_counter() - start, 1),
                      "train_seconds": report["diagnoser"]["train_seconds"]}, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("suite")
    p.add_argument("folder")
    p.add_argument("--level", type=float, default=DiagnosisSettings().level)
    p.add_argument("--cache")
    p.add_argument("--size", type=int, action="append", help="only the cases of this sensor size (repeatable)")
    p.add_argument("--keep", help="folder to keep every case's report in (for rescore)")
    p = sub.add_parser("rescore")
    p.add_argument("folder")
    p.add_argument("--level", type=float, action="append", required=True)
    p = sub.add_parser("insim")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--fresh", type=int, default=300)
    p = sub.add_parser("seeds")
    p.add_argument("holo")
    sub.add_parser("real")
    args = parser.parse_args()
    if args.command == "suite":
        suite(args.folder, level=args.level, cache=args.cache, keep=args.keep, sizes=args.size)
    elif args.command == "rescore":
        rescore(args.folder, args.level)
    elif args.command == "insim":
        insim(args.size, args.fresh)
    elif args.command == "seeds":
        seeds(args.holo)
    else:
        real()


if __name__ == "__main__":
    sys.exit(main())
