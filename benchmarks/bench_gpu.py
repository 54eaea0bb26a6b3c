"""The GPU figures in one run: the demo's steps on the device, each beside the same work on two CPU cores of the same machine.

Steps (each timed on ``--device``; the CPU figure beside it is measured in the same run, in a
child process of this script pinned to two cores, at a reduced size and scaled per unit, so
both figures come from one machine under one load):

``backprop``  the built-in 1024² hologram to the default config's 61 planes
              (device: `device_backpropagated_planes`, torch.fft; CPU: `backpropagate`, numpy)
``generate``  the demo's synthetic groups (CPU work in worker processes; no device figure)
``train``     one epoch of the demo's recipe on 64 and 128 groups (batch 8, float32), and on
              128 groups with batch 32, float32 and bfloat16 (`TrainingSettings.precision`
              "auto"); the GPU's busy share sampled by ``nvidia-smi`` every 100 ms
``predict``   the built-in 1024² hologram × 61 planes, back-propagation included (the model
              of the 64-group epoch)
``refine``    100 spheres on a 1024² Lorenz–Mie hologram from guesses off by ~1.5 µm
              laterally, ~15 µm in depth, ~1.5 µm in diameter

``--demo`` also times a whole ``napari-lbs demo`` (a subprocess; its ``summary.json`` steps).

    python benchmarks/bench_gpu.py                       # on a CUDA machine: about 5 minutes
    python benchmarks/bench_gpu.py --device cpu --quick  # the plumbing on any machine, a few minutes
    python benchmarks/bench_gpu.py --profile             # and torch.profiler's top ops of prediction and refinement

Writes ``benchmarks/results/gpu/bench_gpu_<device>[_quick].json`` (or ``--out``) and prints the
table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

TARGETS = {"backprop": "", "generate": "", "train_64": "", "train_128": "≤ 5 s/epoch, ≥ 30× 2 cores, GPU busy ≥ 80 %",
           "train_128_b32": "≤ 5 s/epoch", "train_128_b32_bf16": "≤ 5 s/epoch", "predict": "≤ 1 s", "refine": "≤ 3 s", "demo": "≤ 60 s"}


class GpuBusy:
    """The GPU's utilisation (%) sampled by ``nvidia-smi`` every 100 ms between `start` and `stop`; None without a GPU or ``nvidia-smi``."""

    def __init__(self, device: str) -> None:
        self.samples: list[int] = []
        self._on = device == "cuda" and shutil.which("nvidia-smi") is not None
        self._process = None

    def start(self) -> None:
        if self._on and self._process is None:
            self._process = subprocess.Popen(["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits", "-lms", "100"],
                                             stdout=subprocess.PIPE, text=True)
            threading.Thread(target=self._read, args=(self._process,), daemon=True).start()

    def _read(self, process) -> None:
        for line in process.stdout:
            value = line.strip().split(",")[0].strip()
            if value.isdigit():
                self.samples.append(int(value))

    def stop(self) -> None:
        if self._process is not None:
            self._process.terminate()
            self._process.wait()

    @property
    def mean(self) -> float | None:
        return round(float(np.mean(self.samples)), 1) if self.samples else None


class Profile:
    """With ``folder``: `torch.profiler` over the block (CPU and, on CUDA, kernels); its top ops by device and by host time written to ``folder/profile_NAME.txt``."""

    def __init__(self, folder: Path | None, name: str, device: str) -> None:
        self.folder, self.name, self.device, self._profiler = folder, name, device, None

    def __enter__(self) -> "Profile":
        if self.folder is not None:
            from torch.profiler import ProfilerActivity, profile

            activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if self.device == "cuda" else [])
            self._profiler = profile(activities=activities)
            self._profiler.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._profiler is None:
            return
        self._profiler.__exit__(*exc)
        averages = self._profiler.key_averages()
        launches = sum(e.count for e in averages if e.key.startswith("aten::"))
        text = [f"{self.name} on {self.device}: {launches} aten ops"]
        for key in (["self_cuda_time_total"] if self.device == "cuda" else []) + ["self_cpu_time_total"]:
            text.append(averages.table(sort_by=key, row_limit=25))
        self.folder.mkdir(parents=True, exist_ok=True)
        (self.folder / f"profile_{self.name}_{self.device}.txt").write_text("\n\n".join(text))


def synchronise(device: str) -> None:
    import torch

    if device == "cuda":
        torch.cuda.synchronize()


def bench_backprop(device: str, quick: bool) -> dict:
    import torch

    from napari_lbs._core import ExperimentConfig, load_sample_hologram
    from napari_lbs._core.learning._device_planes import device_backpropagated_planes
    from napari_lbs._core.physics import backpropagate

    hologram = load_sample_hologram()[: 256 if quick else None, : 256 if quick else None]
    config = ExperimentConfig()
    planes, optics = config.volume.planes_um(), {"wavelength_um": config.optics.wavelength_um, "pixel_um": config.optics.pixel_um, "medium_index": config.optics.medium_index}
    times = []
    for _ in range(2):  # cold (kernels built and moved), then warm
        start = time.perf_counter()
        if device == "cpu":
            backpropagate(hologram, planes, **optics)
        else:
            for _, _, block in device_backpropagated_planes(hologram, planes, device=torch.device(device), **optics):
                block.sum()
            synchronise(device)
        times.append(time.perf_counter() - start)
    return {"size": f"{hologram.shape[0]}² × {len(planes)} planes", "seconds": round(times[1], 3), "cold_seconds": round(times[0], 3)}


def make_data(folder: Path, groups: int, quick: bool) -> tuple[Path, float]:
    from dataclasses import replace

    from napari_lbs._core import Distractors, ExperimentConfig, generate_dataset
    from napari_lbs._core.foundation import process_threads
    from napari_lbs._core.pipeline._demo import DEMO_SAMPLE_DISTRACTORS, DEMO_SAMPLE_EFFECTS

    config = ExperimentConfig()
    if quick:  # a shorter depth range: fewer planes per group and per prediction
        config = replace(config, volume=replace(config.volume, z_min_um=1800.0, z_max_um=2400.0))
    start = time.perf_counter()
    generate_dataset(folder, config, groups=groups, effects=dict(DEMO_SAMPLE_EFFECTS), distractors=Distractors(**DEMO_SAMPLE_DISTRACTORS), seed=0,
                     workers=process_threads())
    return folder, time.perf_counter() - start


def bench_train(data: Path, out: Path, device: str, *, batch: int = 8, precision: str = "float32", batches: int | None = None) -> dict:
    """One epoch (``batches`` None) or the rate over batches 5 … ``batches`` (a part epoch, the CPU leg)."""
    from napari_lbs._core import Stopped, TrainingSettings, open_dataset, train_model

    dataset = open_dataset(data)
    settings = TrainingSettings(epochs=2, validate_last=1, batch_size=batch, precision=precision, device=device, seed=0)
    marks: dict[int, float] = {}
    per_epoch = []

    busy = GpuBusy(device)  # sampled over the epoch's batches only (not the data's loading)

    def progress(done: int, total: int) -> None:
        per_epoch.append(total // 2)
        marks[done] = time.perf_counter()
        if done == 1:
            busy.start()
        if done == per_epoch[0]:
            busy.stop()

    try:
        train_model(dataset, out, settings=settings, progress=progress,
                    should_stop=lambda: bool(per_epoch) and max(marks) >= (batches if batches is not None else per_epoch[0] + 1))
    except Stopped:
        pass
    finally:
        busy.stop()
    log = json.loads(out.with_suffix(".json").read_text())
    samples = per_epoch[0] * batch
    if batches is None:
        seconds = log["epochs"][0]["train_seconds"]
    else:
        seconds = (marks[batches] - marks[5]) / (batches - 5) * per_epoch[0]
    return {"groups": len(log["training_groups"]), "samples": samples, "batch": batch, "precision": log["precision"], "epoch_seconds": round(seconds, 2),
            "samples_per_second": round(samples / seconds, 1), "gpu_busy_percent": busy.mean, "part_epoch": batches is not None}


def model_for_prediction(data: Path, out: Path, device: str) -> Path:
    from napari_lbs._core import TrainingSettings, open_dataset, train_model

    return train_model(open_dataset(data), out, settings=TrainingSettings(epochs=1, device=device, seed=0)).model_path


def bench_predict(model: Path, device: str, quick: bool, crop: int | None = None, profile: Path | None = None) -> dict:
    from napari_lbs._core import load_sample_hologram, predict_particles

    hologram = load_sample_hologram()
    hologram = hologram[: crop or (256 if quick else None), : crop or (256 if quick else None)]
    times = []
    for repeat in range(2):
        start = time.perf_counter()
        with Profile(profile if repeat else None, "predict", device):
            result = predict_particles(hologram, model, device=device)
            synchronise(device)
        times.append(time.perf_counter() - start)
    return {"size": f"{hologram.shape[0]}²", "seconds": round(times[1], 3), "cold_seconds": round(times[0], 3), "particles": len(result.particles["x_um"]),
            "pixels": int(hologram.size)}


def sphere_table(count: int, size: int, seed: int):
    import pandas as pd

    rng = np.random.default_rng(seed)
    pixel_um, margin = 3.45, 60
    return pd.DataFrame({"x_um": rng.uniform(margin, size - margin, count) * pixel_um, "y_um": rng.uniform(margin, size - margin, count) * pixel_um,
                         "z_um": rng.uniform(2000.0, 4500.0, count), "diameter_um": rng.uniform(20.0, 30.0, count), "index_contrast": np.full(count, 0.26)})


def bench_refine(device: str, count: int, size: int, workers: int, profile: Path | None = None) -> dict:
    from napari_lbs._core import ExperimentConfig
    from napari_lbs._core.refine import RefineSettings, particle_hologram, refine_particles

    config = ExperimentConfig()
    truth = sphere_table(count, size, seed=1)
    hologram = particle_hologram((size, size), truth, config) + np.random.default_rng(2).normal(0.0, 0.01, (size, size))
    rng = np.random.default_rng(3)
    guesses = truth[["x_um", "y_um", "z_um", "diameter_um"]].copy()
    for column, sigma in (("x_um", 1.5), ("y_um", 1.5), ("z_um", 15.0), ("diameter_um", 1.5)):
        guesses[column] = guesses[column] + rng.normal(0.0, sigma, count)
    start = time.perf_counter()
    with Profile(profile, "refine", device):
        table = refine_particles(hologram, guesses, config, settings=RefineSettings(device=device, workers=workers))
        synchronise(device)
    seconds = time.perf_counter() - start
    return {"particles": count, "seconds": round(seconds, 2), "seconds_per_particle": round(seconds / count, 4), "kept": len(table),
            "median_abs_dz_um": round(float(np.median(np.abs(table["z_um"].to_numpy()[: len(table)] - truth["z_um"].to_numpy()[: len(table)]))), 2) if len(table) == count else None}


def bench_demo(device: str, quick: bool) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        subprocess.run(["napari-lbs", "demo", "--out", folder] + (["--quick"] if quick else []), check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - start
        summary = json.loads((Path(folder) / "summary.json").read_text())
    return {"seconds": round(wall, 1), "steps": summary["seconds"], "particles": summary["particle_count"]}


def run_leg(device: str, quick: bool, work: Path, *, shared: Path | None, profile: Path | None = None) -> dict:
    """Every step on ``device``. The CPU leg (``shared``: the device leg's folder) trains on its data sets and predicts with its model, at reduced sizes."""
    from napari_lbs._core.foundation import process_threads

    figures: dict[str, dict] = {}
    figures["backprop"] = bench_backprop(device, quick)
    groups = (4, 6) if quick else (64, 128)
    if shared is None:
        data64, seconds = make_data(work / "data64", groups[0], quick)
        figures["generate"] = {"groups": groups[0], "seconds": round(seconds, 2), "seconds_per_group": round(seconds / groups[0], 3), "workers": process_threads()}
        data128 = work / "data128"  # the same first groups (linked, not copied), extended
        shutil.copytree(data64, data128, copy_function=os.link)
        make_data(data128, groups[1], quick)
        model = model_for_prediction(data64, work / "predict.pt", device)
    else:
        data64, data128, model = shared / "data64", shared / "data128", shared / "predict.pt"
        count = 2 if quick else 8
        _, seconds = make_data(work / "generate", count, quick)
        figures["generate"] = {"groups": count, "seconds": round(seconds, 2), "seconds_per_group": round(seconds / count, 3), "workers": process_threads()}
    part = 25 if shared is not None and not quick else None  # the CPU leg times batches 5-25 of an epoch
    figures["train_64"] = bench_train(data64, work / "m64.pt", device, batches=part)
    figures["train_128"] = bench_train(data128, work / "m128.pt", device, batches=part)
    if shared is None:
        figures["train_128_b32"] = bench_train(data128, work / "m128b.pt", device, batch=32)
        figures["train_128_b32_bf16"] = bench_train(data128, work / "m128c.pt", device, batch=32, precision="auto")
    figures["predict"] = bench_predict(model, device, quick, crop=512 if shared is not None and not quick else None, profile=profile)
    count = 3 if quick else (12 if shared is not None else 100)
    figures["refine"] = bench_refine(device, count, 256 if quick else 1024, workers=2 if shared is not None else 1, profile=profile)
    return figures


def cpu_leg(quick: bool, shared: Path) -> dict:
    """This script's CPU leg in a child process on two cores (``NAPARI_LBS_THREADS=2``, ``taskset`` where present)."""
    out = shared / "cpu.json"
    command = [sys.executable, __file__, "--device", "cpu", "--leg", str(shared), "--out", str(out)] + (["--quick"] if quick else [])
    if shutil.which("taskset"):
        command = ["taskset", "-c", "0,1"] + command
    subprocess.run(command, check=True, env=os.environ | {"NAPARI_LBS_THREADS": "2"})
    return json.loads(out.read_text())["figures"]


def table(device_figures: dict, cpu_figures: dict | None) -> list[dict]:
    rows = []
    for step, figure in device_figures.items():
        row = {"step": step, "device": figure}
        cpu = (cpu_figures or {}).get(step)
        if cpu is not None:
            row["cpu_2_cores"] = cpu
            if "samples_per_second" in figure:
                row["ratio"] = round(figure["samples_per_second"] / cpu["samples_per_second"], 1)
            elif step == "predict":
                row["ratio"] = round(cpu["seconds"] * figure["pixels"] / cpu["pixels"] / figure["seconds"], 1)
            elif step == "generate":
                row["ratio"] = round(cpu["seconds_per_group"] / figure["seconds_per_group"], 1)
            elif step == "refine":
                row["ratio"] = round(cpu["seconds_per_particle"] / figure["seconds_per_particle"], 1)
            elif "seconds" in figure:
                row["ratio"] = round(cpu["seconds"] / figure["seconds"], 1)
        row["target"] = TARGETS.get(step, "")
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda")
    parser.add_argument("--quick", action="store_true", help="tiny sizes: the plumbing, not figures")
    parser.add_argument("--demo", action="store_true", help="also time a whole `napari-lbs demo` (--quick: the quick demo)")
    parser.add_argument("--leg", type=Path, help=argparse.SUPPRESS)  # the CPU leg's child process: the device leg's folder
    parser.add_argument("--out", type=Path)
    parser.add_argument("--profile", action="store_true", help="torch.profiler over the (warm) prediction and the refinement: top ops in results/gpu/profile_*.txt")
    args = parser.parse_args()
    from napari_lbs._core.foundation import process_threads

    process_threads()  # sizes the thread pools and OpenMP's waiting before torch starts its threads
    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA GPU here (use --device cpu for the smoke run)")
    started = time.perf_counter()
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as folder:
        out = args.out or Path(__file__).parent / "results" / "gpu" / f"bench_gpu_{args.device}{'_quick' if args.quick else ''}.json"
        figures = run_leg(args.device, args.quick, Path(folder), shared=args.leg, profile=out.parent if args.profile and not args.leg else None)
        if args.demo and not args.leg:
            figures["demo"] = bench_demo(args.device, args.quick)
        report = {"device": torch.cuda.get_device_name() if args.device == "cuda" else f"cpu ({process_threads()} threads)", "quick": args.quick,
                  "torch": torch.__version__, "load_before": load_before, "figures": figures}
        if not args.leg:
            report["cpu_2_cores"] = cpu_leg(args.quick, Path(folder))
            report["table"] = table(figures, report["cpu_2_cores"])
            report["load_after"] = os.getloadavg()[0]
    report["seconds"] = round(time.perf_counter() - started, 1)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    if args.leg:
        return
    print(f"{report['device']}, {report['seconds']} s, load {report['load_before']:.1f} → {report['load_after']:.1f}; CPU leg: 2 cores of the same machine")
    print(f"{'step':22s} {'device':>12s} {'2 CPU cores':>14s} {'ratio':>7s}  details / target")
    for row in report["table"]:
        figure, cpu = row["device"], row.get("cpu_2_cores", {})
        key = "epoch_seconds" if "epoch_seconds" in figure else "seconds"
        cpu_value = cpu.get("epoch_seconds", cpu.get("seconds"))
        busy = f", GPU busy {figure['gpu_busy_percent']} %" if figure.get("gpu_busy_percent") is not None else ""
        print(f"{row['step']:22s} {figure[key]:>10} s {cpu_value if cpu_value is not None else '':>12} s {row.get('ratio', ''):>6}×  "
              f"{figure.get('size', figure.get('groups', ''))}{busy}  {row['target']}")
    print(f"written: {out}")


if __name__ == "__main__":
    main()
