"""Recordings: the peak memory of `napari-lbs predict` does not grow with the number of frames.

Simulates ``--distinct`` (10) frames of ``--size``² pixels (a multi-page float32 TIFF written
page by page, `napari-lbs simulate --flow uniform`) and writes, for each N of ``--frames``, a
recording of N frames that cycles through them (page by page: frame k is simulated frame
k mod ``--distinct``; simulating 200 distinct 1024² frames would cost more than predicting
them, and what is measured does not depend on the pixels), then runs
``napari-lbs predict`` on each as a separate process (with ``--sequence-background`` and
``--workers`` as asked) and samples the resident memory of that process and of all its
children every 0.05 s. Reported per run: the peak RSS of the calling process, of each worker
process (with ``--workers``), of their sum at any one time and of that sum while each 25
frames were being done, the wall time and the CPU time (user + system of the process
tree: core-seconds).

What is measured is the recording machinery (frames read lazily, at most a few in flight,
every result written to the work folder as it arrives): the model and the depths are kept
small so that hundreds of 1024² frames run in minutes on two cores (``--planes``: a
config whose volume has that many planes, 100 µm apart from 1800 µm; a focus model trained for
it in seconds on 3 groups: what it finds is not the point, the network still runs on every
plane of every frame). A frame's own working memory grows with the planes (the
reconstruction stack), not with the frame count.

Run: python benchmarks/bench_memory.py [--frames 50 200] [--size 1024] [--planes 5]
[--background auto] [--workers N] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil
import tifffile

from napari_lbs._core import DatasetLayout, ExperimentConfig, TrainingSettings, generate_dataset, load_model, train_model, write_config


def tiny_model(folder: Path, config_path: Path, planes: int) -> Path:
    from napari_lbs._core import load_config

    config = load_config(config_path)
    data = generate_dataset(folder / "data", config, groups=3, layout=DatasetLayout(kind="stack", context_planes=2), seed=5)
    settings = TrainingSettings(epochs=1, batch_size=4, device="cpu", validation_groups=1, patch_size=32, context=(-2, -1, 0, 1, 2))
    path = train_model(data, folder / "model.pt", settings=settings).model_path
    assert len(load_model(path).meta["planes_um"]) == planes + 4
    return path


def sample_tree(process: psutil.Process, stop: threading.Event, peaks: dict, parts: Path, *, bucket: int = 25) -> None:
    """Peak RSS of ``process`` (``caller``), of each child (by pid) and of their sum, every 0.05 s.

    ``peaks["by_frames"]`` holds the peak of the sum while the work folder ``parts`` held
    0..bucket-1, bucket..2 bucket-1, ... finished frames (counted every 0.5 s): memory that
    grew with the frames done would show as a rising sequence.
    """
    done, ticks = 0, 0
    while not stop.is_set():
        if ticks % 10 == 0 and parts.is_dir():
            done = sum(1 for _ in parts.glob("frame_*.npz"))
        ticks += 1
        try:
            tree = [process, *process.children(recursive=True)]
        except psutil.Error:
            break
        total = 0
        for member in tree:
            try:
                rss = member.memory_info().rss
            except psutil.Error:
                continue
            total += rss
            key = "caller" if member.pid == process.pid else member.pid
            peaks[key] = max(peaks.get(key, 0), rss)
        peaks["sum"] = max(peaks.get("sum", 0), total)
        window = f"{done // bucket * bucket}-{done // bucket * bucket + bucket - 1}"
        by_frames = peaks.setdefault("by_frames", {})
        by_frames[window] = max(by_frames.get(window, 0), total)
        stop.wait(0.05)


def run_predict(recording: Path, model: Path, out: Path, *, background: str, workers: int | None) -> dict:
    command = [sys.executable, "-c", "from napari_lbs._cli import console_main; console_main()", "predict", str(recording), "--model", str(model),
               "--out", str(out), "--sequence-background", background]
    if workers:
        command += ["--workers", str(workers)]
    start = time.perf_counter()
    child = psutil.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    peaks: dict = {}
    stop = threading.Event()
    sampler = threading.Thread(target=sample_tree, args=(child, stop, peaks, out.with_name(out.name + ".parts")), daemon=True)
    sampler.start()
    cpu = {}
    while child.poll() is None:  # the tree's CPU time, taken while its members are alive
        try:
            for member in [child, *child.children(recursive=True)]:
                times = member.cpu_times()
                cpu[member.pid] = times.user + times.system + getattr(times, "children_user", 0) + getattr(times, "children_system", 0)
        except psutil.Error:
            pass
        time.sleep(0.2)
    output = child.stdout.read().decode()
    stop.set()
    sampler.join()
    if child.returncode != 0:
        raise SystemExit(f"predict failed ({child.returncode}): {output}")
    mib = 2**20
    return {"seconds": round(time.perf_counter() - start, 1), "core_seconds_at_least": round(sum(cpu.values()), 1),
            "peak_rss_caller_mib": round(peaks["caller"] / mib), "peak_rss_sum_mib": round(peaks["sum"] / mib),
            "peak_rss_workers_mib": sorted(round(v / mib) for k, v in peaks.items() if k not in ("caller", "sum", "by_frames") and v > 200 * mib),
            "peak_rss_sum_by_frames_done_mib": {k: round(v / mib) for k, v in peaks.get("by_frames", {}).items()},
            "summary": output.strip().splitlines()[-1]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[50, 200])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--particles", type=int, default=40)
    parser.add_argument("--distinct", type=int, default=10, help="frames simulated; the recordings cycle through them (default 10)")
    parser.add_argument("--planes", type=int, default=5)
    parser.add_argument("--background", default="auto")
    parser.add_argument("--workers", type=int)
    parser.add_argument("--model", type=Path, help="a model for the --planes config (default: trained here in seconds)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    folder = Path(tempfile.mkdtemp(prefix="bench-memory-"))
    config = ExperimentConfig.from_dict({"volume": {"z_min_um": 1800.0, "z_max_um": 1800.0 + 100.0 * (args.planes - 1), "z_step_um": 100.0},
                                         "particles": {"per_tile": 3, "layer_step_um": 200.0}, "tile": {"size": 48}})
    config_path = write_config(folder / "config.toml", config)
    model = args.model or tiny_model(folder, config_path, args.planes)
    report = {"size": args.size, "planes": args.planes, "distinct_frames": args.distinct, "particles": args.particles, "background": args.background, "workers": args.workers,
              "load_average_at_start": [round(v, 2) for v in psutil.getloadavg()], "cpu_count": psutil.cpu_count(), "runs": {}}
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", "from napari_lbs._cli import console_main; console_main()", "simulate", "--config", str(config_path), "--out", str(folder / "sim"),
                    "--size", str(args.size), "--particles", str(args.particles), "--frames", str(args.distinct), "--flow", "uniform", "--seed", "0"], check=True, stdout=subprocess.DEVNULL)
    report["simulate_seconds"] = round(time.perf_counter() - start, 1)
    for count in sorted(args.frames):
        recording = folder / f"frames_{count}.tif"
        with tifffile.TiffFile(folder / "sim" / "frames.tif") as source, tifffile.TiffWriter(recording) as writer:
            source.pages.cache = False
            for page in range(count):
                writer.write(source.pages[page % args.distinct].asarray(), photometric="minisblack", contiguous=False)
        report["runs"][str(count)] = run = run_predict(recording, model, folder / f"p_{count}.csv", background=args.background, workers=args.workers)
        run["frame_mib"] = round(args.size * args.size * 4 / 2**20, 1)
        provenance = json.loads((folder / f"p_{count}.json").read_text())
        run.update(background_used=provenance.get("background_used"), frames_per_second=provenance.get("frames_per_second"),
                   particles=sum(1 for _ in open(folder / f"p_{count}.csv")) - 1)
        print(count, json.dumps(run), flush=True)
        recording.unlink()
    report["load_average_at_end"] = [round(v, 2) for v in psutil.getloadavg()]
    print(json.dumps(report, indent=1))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
