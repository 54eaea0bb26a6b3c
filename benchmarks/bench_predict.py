"""`napari-lbs predict` on the built-in real 1024² hologram and on a 4096² sensor, against a previous build.

The 4096² image is the real hologram tiled 4 x 4 (``np.tile``). Each case runs the whole
console command (``python -m napari_lbs._cli predict``) in a fresh child process, this tree's
and a previous commit's (``git archive <commit> src``, put first on ``PYTHONPATH``) alternated,
and reads the child's own resource usage (``os.wait4``): wall time, core-seconds (user +
system CPU time) and peak resident memory. Printed: each run, each case's best, the new/old
ratios, the 4096²/1024² ratio of each build, and how the particle tables compare (each new
particle's nearest old one). The load average is logged before and after: on a shared machine
only the same-run ratios mean anything.

Run: python benchmarks/bench_predict.py --model demo/model.pt [--baseline 09f02ff] [--sizes 1024 4096]
[--baseline-sizes 1024] [--repeats 1]
Raw results: benchmarks/results/predict/bench_predict_<date>.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "predict"


def baseline_tree(commit: str, into: Path) -> Path:
    """The ``src`` of ``commit`` extracted under ``into``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "src"], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into / "src"


def run_child(src: Path, hologram: Path, model: str, out: Path, threads: str | None) -> dict:
    """One `predict` in a child process: wall seconds, core-seconds, peak RSS (MiB) and its table."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    if threads:
        env["NAPARI_LBS_THREADS"] = threads
    command = [sys.executable, "-m", "napari_lbs._cli", "predict", str(hologram), "--model", model, "--out", str(out)]
    start = time.perf_counter()
    child = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = child.stdout.read().decode(errors="replace")
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed ({child.returncode}):\n{output[-2000:]}")
    return {"wall_s": round(wall, 2), "core_s": round(usage.ru_utime + usage.ru_stime, 2), "peak_rss_mib": round(usage.ru_maxrss / 1024), "log": output.strip().splitlines()[-1:]}


def read_table(path: Path) -> np.ndarray:
    from napari_lbs._core import read_particles

    table = read_particles(path)
    return np.column_stack([np.asarray(table[name], float) for name in ("x_um", "y_um", "z_um", "score")]) if len(table["x_um"]) else np.zeros((0, 4))


def compare(new: np.ndarray, old: np.ndarray) -> dict:
    """How far each new particle lies from its nearest old one (µm), and the score difference."""
    from scipy.spatial import cKDTree

    if not len(new) or not len(old):
        return {"new": len(new), "old": len(old)}
    distance, index = cKDTree(old[:, :3]).query(new[:, :3])
    return {"new": len(new), "old": len(old), "within_2um": int((distance < 2.0).sum()), "max_um": round(float(distance.max()), 3),
            "median_um": round(float(np.median(distance)), 4), "max_score_change": round(float(np.abs(new[:, 3] - old[index, 3]).max()), 4)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--baseline", default="09f02ff", help="the previous build's commit")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096], help="image edges: the real hologram tiled to each (a multiple of 1024)")
    parser.add_argument("--baseline-sizes", type=int, nargs="*", default=None,
                        help="the sizes the previous build runs at too (default: all; its 4096² run needs ~15 GB)")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--threads", default=None, help="NAPARI_LBS_THREADS for the children (default: theirs)")
    args = parser.parse_args()
    import tifffile

    from napari_lbs._core import load_sample_hologram

    RESULTS.mkdir(parents=True, exist_ok=True)
    record = {"date": datetime.date.today().isoformat(), "baseline": args.baseline, "model": args.model, "load_before": os.getloadavg(), "runs": []}
    with tempfile.TemporaryDirectory(prefix="bench-predict-") as work:
        work = Path(work)
        (work / "old").mkdir()
        trees = {"old": baseline_tree(args.baseline, work / "old"), "new": ROOT / "src"}
        sample = load_sample_hologram()
        for size in args.sizes:
            hologram = work / f"real{size}.tif"
            tifffile.imwrite(hologram, np.tile(sample, (size // sample.shape[0], size // sample.shape[1])))
            for repeat in range(args.repeats):
                for name in ("old", "new") if args.baseline_sizes is None or size in args.baseline_sizes else ("new",):
                    out = work / f"{name}{size}.csv"
                    run = {"size": size, "build": name, "repeat": repeat, "load": os.getloadavg()[0], **run_child(trees[name], hologram, args.model, out, args.threads)}
                    record["runs"].append(run)
                    print(json.dumps(run), flush=True)
            if (work / f"old{size}.csv").is_file():
                record[f"tables_{size}"] = compare(read_table(work / f"new{size}.csv"), read_table(work / f"old{size}.csv"))
                print(f"{size}²: particles {record[f'tables_{size}']}", flush=True)
    record["load_after"] = os.getloadavg()
    best = {(r["size"], r["build"]): min((x for x in record["runs"] if (x["size"], x["build"]) == (r["size"], r["build"])), key=lambda x: x["wall_s"]) for r in record["runs"]}
    print(f"load average before {record['load_before'][0]:.2f}, after {record['load_after'][0]:.2f}")
    print("| image | build | wall (s) | core-s | peak RSS (MiB) |\n|---|---|---|---|---|")
    for (size, name), run in sorted(best.items()):
        print(f"| {size}² | {name} | {run['wall_s']} | {run['core_s']} | {run['peak_rss_mib']} |")
    for size in args.sizes:
        if (size, "old") not in best:
            continue
        old, new = best[(size, "old")], best[(size, "new")]
        record[f"speedup_{size}"] = {"wall": round(old["wall_s"] / new["wall_s"], 2), "core": round(old["core_s"] / new["core_s"], 2)}
        print(f"{size}²: new is {record[f'speedup_{size}']['wall']}x faster (wall), {record[f'speedup_{size}']['core']}x (core-s); peak {old['peak_rss_mib']} -> {new['peak_rss_mib']} MiB")
    if len(args.sizes) > 1:
        small, large = min(args.sizes), max(args.sizes)
        for name in ("old", "new"):
            if (large, name) not in best or (small, name) not in best:
                continue
            ratio = {"wall": round(best[(large, name)]["wall_s"] / best[(small, name)]["wall_s"], 1), "core": round(best[(large, name)]["core_s"] / best[(small, name)]["core_s"], 1)}
            record[f"ratio_{large}_{small}_{name}"] = ratio
            print(f"{name}: {large}² / {small}² = {ratio['wall']}x (wall), {ratio['core']}x (core-s)")
    path = RESULTS / f"bench_predict_{record['date']}.json"
    temporary = path.with_suffix(".json.tmp")
    temporary.write_text(json.dumps(record, indent=1))
    temporary.replace(path)
    print(f"raw: {path.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
