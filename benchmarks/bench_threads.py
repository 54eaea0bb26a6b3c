"""Two jobs side by side: each alone, two at once as started, and two at once given a share each.

A job is a fixed piece of training work (``--steps`` forward + backward + AdamW steps of the
`small` focus network on batches of 8 x 9 x 128²), the loop `train_model` runs, in its own
process sized by `size_threads` as the console script is. Prints each setting's wall time per
job and its ratio to one job alone, all measured in this run:

- ``alone``: one job, every core the machine gives it;
- ``two, as started``: two jobs at once, each sized to every core (twice as many threads as cores);
- ``two, NAPARI_LBS_THREADS``: two at once, each told its share of the cores;
- ``two, taskset``: two at once, each pinned to its own cores (its affinity sizes it);
- ``... OMP_WAIT_POLICY=ACTIVE``: OpenMP's waiting threads spin (OpenMP's default; napari-lbs
  sets PASSIVE unless told otherwise), which matters when other work shares the cores.

Run: python benchmarks/bench_threads.py [--steps 30]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

_JOB = """
import time
from napari_lbs._core.foundation._threads import size_threads
threads = size_threads()
import torch
from napari_lbs._core.learning._network import build_network
torch.manual_seed(0)
network = build_network("small", in_channels=9, out_channels=3).to(memory_format=torch.channels_last)
optimizer = torch.optim.AdamW(network.parameters(), lr=2e-3)
x = torch.rand(8, 9, 128, 128).contiguous(memory_format=torch.channels_last)
start = time.perf_counter()
for _ in range({steps}):
    optimizer.zero_grad(set_to_none=True)
    network(x).square().mean().backward()
    optimizer.step()
print(threads, time.perf_counter() - start)
"""


def _jobs(steps: int, environments: list[dict], prefixes: list[list[str]]) -> list[tuple[int, float]]:
    """Start the jobs together and return each one's (threads, seconds)."""
    running = [subprocess.Popen([*prefix, sys.executable, "-c", _JOB.format(steps=steps)], env=env, stdout=subprocess.PIPE, text=True)
               for env, prefix in zip(environments, prefixes, strict=True)]
    results = []
    for process in running:
        out, _ = process.communicate()
        threads, seconds = out.split()
        results.append((int(threads), float(seconds)))
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    steps = parser.parse_args().steps
    cores = sorted(os.sched_getaffinity(0))
    half = len(cores) // 2
    if half < 1:
        sys.exit("needs at least 2 cores")
    base = {key: value for key, value in os.environ.items() if key not in ("NAPARI_LBS_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY",
                                                        "GOMP_SPINCOUNT")}
    shared = dict(base, NAPARI_LBS_THREADS=str(half))
    shares = [",".join(map(str, cores[:half])), ",".join(map(str, cores[half : 2 * half]))]
    spinning = dict(base, OMP_WAIT_POLICY="ACTIVE")
    sleeping = dict(base, GOMP_SPINCOUNT="0")
    settings = {
        "alone": ([base], [[]]),
        "alone, GOMP_SPINCOUNT=0": ([sleeping], [[]]),
        "alone, OMP_WAIT_POLICY=ACTIVE": ([spinning], [[]]),
        "two, as started": ([base, base], [[], []]),
        "two, GOMP_SPINCOUNT=0": ([sleeping, sleeping], [[], []]),
        "two, OMP_WAIT_POLICY=ACTIVE": ([spinning, spinning], [[], []]),
        f"two, NAPARI_LBS_THREADS={half}": ([shared, shared], [[], []]),
        "two, taskset": ([base, base], [["taskset", "-c", shares[0]], ["taskset", "-c", shares[1]]]),
    }
    report = {"cores": len(cores), "steps": steps, "load_average_at_start": list(os.getloadavg()), "settings": {}}
    alone = None
    for name, (environments, prefixes) in settings.items():
        start = time.perf_counter()
        results = _jobs(steps, environments, prefixes)
        per_job = max(seconds for _, seconds in results)
        alone = alone or per_job
        report["settings"][name] = {"threads": [t for t, _ in results], "seconds": [round(s, 2) for _, s in results], "wall_s": round(time.perf_counter() - start, 2),
                                    "vs_alone": round(per_job / alone, 2)}
        print(f"{name:34s} threads {[t for t, _ in results]}  slowest job {per_job:6.1f} s  = {per_job / alone:4.2f}x alone", flush=True)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
