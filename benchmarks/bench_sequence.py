"""Recordings: throughput on dask, and tracks of a simulated vortex against its truth.

Simulates a vortex recording with the default config (`simulate_sequence`: particles turning
about the window's centre at ``--speed-um`` per frame on the inscribed circle), then measures:

- the single-hologram rate: `predict_particles` on one frame, warm (model loaded, kernels cached);
- frames per second of `predict_sequence` (global median background) on the local threaded
  scheduler (all frames), and on long-lived ``LocalCluster``s of the ``--workers`` counts
  asked for (warmed on two frames, then timed on ``--rate-frames`` frames with the same
  background), counted while the workers run (start-up and the background estimate apart);
  the ratio to ``workers x single-frame rate``, the peak resident memory of each worker
  process, and whether every table is identical to the local scheduler's;
- the CPU time (user + system, this process and its workers) per frame in each case:
  core-seconds, which other jobs on a shared machine barely change, so the rate an idle
  machine of C cores would reach is about C / core-seconds per frame;
- detection per frame (one-to-one ER and JI, docs/formats.md tolerances), then the tracks
  (`link_tracks`): the fraction of predicted links that join two detections of the same true
  particle in consecutive frames, the fraction of true links recovered, and the velocity
  error of the correct links (median relative error of the lateral velocity, and median
  absolute 3-D error in µm per frame).

Run: python benchmarks/bench_sequence.py --model MODEL.pt [--frames 20] [--size 512] [--workers 1 2] [--json OUT.json]
Throughput of a long recording: ``--frames 200 --size 1024 --workers 2 --rate-frames 200
--local-frames 20 --throughput-only`` times the cluster on all frames and the local scheduler on the first 20.
MODEL.pt: a ``focus`` model for the default config (e.g. from ``napari-lbs demo`` or
``bench_learning.py``); without ``--model`` a ``small`` one is trained first for ``--train-minutes``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

from napari_lbs._core import (
    DatasetLayout,
    TrainingSettings,
    generate_dataset,
    link_tracks,
    load_config,
    load_model,
    match_particles,
    open_frames,
    predict_particles,
    predict_sequence,
    score_particles,
    sequence_background,
    simulate_sequence,
    train_model,
)
from napari_lbs._core.recordings._sequence import local_cluster


class PeakMemory:
    """Samples the resident memory of this process and of its children (the cluster's workers) every 0.1 s."""

    def __init__(self) -> None:
        self.peak_bytes: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        me = psutil.Process()
        while not self._stop.is_set():
            for process in [me, *me.children(recursive=True)]:
                try:
                    self.peak_bytes[process.pid] = max(self.peak_bytes.get(process.pid, 0), process.memory_info().rss)
                except psutil.Error:
                    pass
            self._stop.wait(0.1)

    def __enter__(self) -> PeakMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def workers_mib(self, own_pid: int) -> list[float]:
        """Peak RSS (MiB) of the child processes that ran at least 200 MiB (the workers, not the nanny's helpers)."""
        return sorted(round(v / 2**20) for pid, v in self.peak_bytes.items() if pid != own_pid and v > 200 * 2**20)


def cpu_seconds() -> float:
    """CPU time (user + system, s) used so far by this process and its live children: core-seconds, which other jobs on a shared machine barely change."""
    total = 0.0
    for process in [psutil.Process(), *psutil.Process().children(recursive=True)]:
        try:
            times = process.cpu_times()
            total += times.user + times.system
        except psutil.Error:
            pass
    return total


def trained_model(folder: Path, minutes: float) -> Path:
    config = load_config(None)
    data = generate_dataset(folder / "data", config, groups=48, layout=DatasetLayout(kind="stack"), seed=0)
    return train_model(data, folder / "model.pt", settings=TrainingSettings(epochs=6, minutes=minutes, seed=0)).model_path


def link_quality(linked: dict, truth: dict) -> dict:
    """Correct-link fractions and velocity errors of a linked prediction against the true tracks."""
    frames = np.unique(truth["frame"]).astype(int)
    true_track_of = np.full(linked["x_um"].size, -1)  # truth track of each detection (-1: a false positive)
    true_row_of = np.full(linked["x_um"].size, -1)
    for frame in frames:
        pred_rows, truth_rows = np.flatnonzero(linked["frame"] == frame), np.flatnonzero(truth["frame"] == frame)
        pred = {k: linked[k][pred_rows] for k in ("x_um", "y_um", "z_um", "diameter_um")}
        true = {k: truth[k][truth_rows] for k in ("x_um", "y_um", "z_um", "diameter_um")}
        for i, j in match_particles(pred, true):
            true_track_of[pred_rows[i]], true_row_of[pred_rows[i]] = truth["track"][truth_rows[j]], truth_rows[j]
    order = np.lexsort((linked["frame"], linked["track"]))
    a, b = order[:-1], order[1:]
    link = linked["track"][a] == linked["track"][b]
    a, b = a[link], b[link]
    correct = (true_track_of[a] >= 0) & (true_track_of[a] == true_track_of[b]) & (linked["frame"][b] == linked["frame"][a] + 1)
    truth_order = np.lexsort((truth["frame"], truth["track"]))
    true_links = int(np.sum(truth["track"][truth_order][1:] == truth["track"][truth_order][:-1]))
    steps = (linked["frame"][b] - linked["frame"][a])[correct][:, None]
    predicted_v = np.stack([linked[k][b] - linked[k][a] for k in ("x_um", "y_um", "z_um")], axis=1)[correct] / steps
    ta, tb = true_row_of[a][correct], true_row_of[b][correct]
    true_v = np.stack([truth[k][tb] - truth[k][ta] for k in ("x_um", "y_um", "z_um")], axis=1) / steps
    lateral_speed = np.hypot(true_v[:, 0], true_v[:, 1])
    moving = lateral_speed > 1.0  # relative errors only where the true lateral speed exceeds 1 µm per frame
    return {
        "predicted_links": int(link.sum()),
        "correct_links": int(correct.sum()),
        "true_links": true_links,
        "correct_fraction": float(correct.sum() / max(link.sum(), 1)),
        "recovered_fraction": float(correct.sum() / max(true_links, 1)),
        "lateral_velocity_relative_error_median": float(np.median(np.hypot(*(predicted_v - true_v)[moving, :2].T) / lateral_speed[moving])) if moving.any() else None,
        "velocity_error_um_per_frame_median_3d": float(np.median(np.linalg.norm(predicted_v - true_v, axis=1))) if correct.any() else None,
        "velocity_error_um_per_frame_median_z": float(np.median(np.abs(predicted_v[:, 2] - true_v[:, 2]))) if correct.any() else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path)
    parser.add_argument("--train-minutes", type=float, default=6.0)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--particles", type=int, default=40)
    parser.add_argument("--speed-um", type=float, default=8.0)
    parser.add_argument("--search-range-um", type=float, default=20.0, help="lateral search range of the tracks (µm)")
    parser.add_argument("--axial-search-range-um", type=float, default=100.0, help="axial search range of the tracks (µm)")
    parser.add_argument("--workers", type=int, nargs="*", default=[1, 2], help="LocalCluster sizes to time (default: 1 2)")
    parser.add_argument("--rate-frames", type=int, default=8, help="frames the clusters are timed on (default 8)")
    parser.add_argument("--local-frames", type=int, help="frames the local scheduler is timed on (default: all; the clusters' tables are compared on these)")
    parser.add_argument("--throughput-only", action="store_true", help="skip detection and tracks")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    config = load_config(None)
    folder = Path(tempfile.mkdtemp(prefix="bench-sequence-"))
    model_path = args.model or trained_model(folder, args.train_minutes)
    model = load_model(model_path, device="cpu")
    start = time.perf_counter()
    recording = simulate_sequence(config, frames=args.frames, flow="vortex", size=args.size, count=args.particles, speed_um=args.speed_um, seed=0)
    report = {"frames": args.frames, "size": args.size, "particles": args.particles, "speed_um": args.speed_um, "planes": len(config.volume.planes_um()),
              "cpu_count": psutil.cpu_count(), "load_average_at_start": list(psutil.getloadavg()), "simulate_seconds": round(time.perf_counter() - start, 2)}

    background = sequence_background(open_frames(recording.frames))  # the global background predict_sequence uses
    predict_particles(recording.frames[0], model, background=background)  # warm-up: kernels and threads
    seconds, cpu_start = [], cpu_seconds()
    for frame in recording.frames[1:4]:  # as `napari-lbs predict` runs one hologram: torch on every core
        start = time.perf_counter()
        predict_particles(frame, model, background=background)
        seconds.append(time.perf_counter() - start)
    single = float(np.median(seconds))
    report["single_frame_seconds"] = round(single, 3)
    report["single_frame_core_seconds"] = round((cpu_seconds() - cpu_start) / 3, 2)

    runs = {}
    local_frames = min(args.local_frames or args.frames, args.frames)
    cpu_start = cpu_seconds()
    # the global background of the whole recording, as `predict_sequence` would estimate it on all frames
    result = predict_sequence(recording.frames[:local_frames], model, background=background if local_frames < args.frames else "global")
    reference = result.particles
    runs["local"] = {"scheduler": result.provenance["scheduler"], "frames": local_frames, "frames_per_second": result.provenance["frames_per_second"],
                     "seconds_total": round(result.seconds, 2), "ratio_to_single": round(result.provenance["frames_per_second"] * single, 3),
                     "core_seconds_per_frame": round((cpu_seconds() - cpu_start) / local_frames, 2)}
    print("local", runs["local"], flush=True)
    rate_frames = recording.frames[: args.rate_frames]
    for workers in args.workers:
        # a long-lived cluster, as a campaign would use: warmed on two frames (imports, model, kernels), then timed
        with local_cluster(workers) as cluster, PeakMemory() as memory:
            predict_sequence(recording.frames[:2], model, background=background, scheduler=cluster.scheduler_address)
            cpu_start = cpu_seconds()
            result = predict_sequence(rate_frames, model, background=background, scheduler=cluster.scheduler_address)
            core_seconds = (cpu_seconds() - cpu_start) / len(rate_frames)
        rate = result.provenance["frames_per_second"]
        compared = min(len(rate_frames), local_frames)  # frames both tables hold
        same = all(np.array_equal(reference[k][reference["frame"] < compared], result.particles[k][result.particles["frame"] < compared]) for k in reference)
        runs[f"cluster{workers}"] = {"frames": len(rate_frames), "frames_per_second": rate, "ratio_to_workers_x_single": round(rate * single / workers, 3),
                                     "core_seconds_per_frame": round(core_seconds, 2),
                                     "peak_worker_rss_mib": memory.workers_mib(psutil.Process().pid), "identical_to_local": same, "frames_compared": compared}
        print(f"cluster{workers}", runs[f"cluster{workers}"], flush=True)
    report["runs"] = runs

    if not args.throughput_only:
        # the simulated light is uniform: detection and tracks also without the median background, which
        # takes out the particles near the vortex's centre (they barely move)
        plain = predict_sequence(recording.frames, model, background="none").particles
        for name, table in (("global_background", reference), ("no_background", plain)):
            report[name] = evaluate(table, recording.truth, frames=args.frames, search_range_um=args.search_range_um, axial_search_range_um=args.axial_search_range_um)
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")


def evaluate(table: dict, truth: dict, *, frames: int, search_range_um: float, axial_search_range_um: float) -> dict:
    """Detection per frame and track quality of a predicted table."""
    scores = [score_particles({k: table[k][table["frame"] == f] for k in table}, {k: truth[k][truth["frame"] == f] for k in truth}) for f in range(frames)]
    detection = {"er_median": float(np.median([s["er"] for s in scores])), "ji_median": float(np.median([s["ji"] for s in scores])),
                 "ji_min": float(min(s["ji"] for s in scores)), "tp": sum(s["tp"] for s in scores), "fp": sum(s["fp"] for s in scores), "fn": sum(s["fn"] for s in scores)}
    linked = link_tracks(table, search_range_um=search_range_um, axial_search_range_um=axial_search_range_um)
    tracks = {"search_range_um": [search_range_um, axial_search_range_um], "tracks": int(linked["track"].max() + 1) if linked["track"].size else 0, **link_quality(linked, truth)}
    return {"detection": detection, "tracks": tracks}


if __name__ == "__main__":
    main()
