"""Recordings: how many true tracks a uniform flow keeps, with each background estimate.

A short recording of slowly moving particles is where a background estimated from the
frames themselves can fail: a particle that moves less than its hologram's extent over the
recording leaves part of its fringes in every frame's median, and dividing by that median
takes part of the particle away. This benchmark measures it on the case users check:

- **the recording**: ``--frames`` (8) frames of ``--size``² (256²) pixels with the default config
  (`load_config(None)`: 2.2 µm pixels, 0.66 µm light, depths 1800–4800 µm, opaque discs of
  20–30 µm), ``--particles`` (12) particles moving with the package's ``uniform`` flow
  (`flow_positions`: ``speed × (0.6, 0.48, 0.64)`` µm per frame in x, y, z, so a lateral step
  of ``0.768 × speed``), each frame simulated by `simulate_hologram` exactly as
  `simulate_sequence` does. The particles start far enough from the window's edges and the
  volume's ends that none leaves during the recording: there are exactly ``--particles``
  true tracks, each seen in every frame.
- **the prediction**: `predict_sequence` with the model and the background mode asked for,
  everything else at its default.
- **the tracks**: `link_tracks` with the `napari-lbs track` defaults (a 60 µm search range in
  3-D, memory 0).
- **a true track is recovered** when one predicted track holds at least ``--recovered-links``
  (6) detections matched to it: in each frame the predicted particles are matched one to
  one to the true ones (`match_particles`, docs/formats.md tolerances: 10 µm laterally, 100 µm
  along z), and a predicted track counts the frames in which its detection matched that
  true track. The figure reported is the number of true tracks recovered (of 12).

Seeds split the cases: development seeds (``--seeds``, default 1 2 3) are for choosing
methods; the final check is seed 0 (``--seeds 0``), run once the choice is made.

Run: python benchmarks/bench_flow.py --model MODEL.pt [--speeds 4 8 16 32] [--seeds 1 2 3]
[--backgrounds auto global flat none] [--pattern] [--workers 1 2] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import psutil

from napari_lbs._core import ParticleField, link_tracks, load_config, load_model, match_particles, open_frames, predict_sequence, simulate_hologram
from napari_lbs._core.recordings._background import choose_background
from napari_lbs._core.recordings._flow import _UNIFORM_DIRECTION, flow_positions


def uniform_flow(config, *, frames: int, size: int, particles: int, speed_um: float, seed: int):
    """``(frames, truth)`` of a uniform flow in which no particle leaves the window or the volume."""
    rng = np.random.default_rng(seed)
    pixel_um = config.optics.pixel_um
    travel_um = speed_um * (frames - 1) * _UNIFORM_DIRECTION  # the whole recording's displacement (x, y, z)
    margin_um = config.particles.diameter_max_um  # a whole particle inside the window at every frame
    width_um = (size - 1) * pixel_um
    x = rng.uniform(margin_um, width_um - margin_um - travel_um[0], particles)
    y = rng.uniform(margin_um, width_um - margin_um - travel_um[1], particles)
    z = rng.uniform(config.volume.z_min_um, config.volume.z_max_um - travel_um[2], particles)
    diameter = rng.uniform(config.particles.diameter_min_um, config.particles.diameter_max_um, particles)
    start = ParticleField(x, y, z, diameter, (size, size), pixel_um)
    truth = flow_positions(start, flow="uniform", frames=frames, speed_um=speed_um, z_range_um=(config.volume.z_min_um, config.volume.z_max_um))
    assert len(np.unique(truth["track"])) == particles  # nothing left the window or the volume
    holograms = np.empty((frames, size, size), np.float32)
    for frame in range(frames):
        here = truth["frame"] == frame
        field = ParticleField(truth["x_um"][here], truth["y_um"][here], truth["z_um"][here], truth["diameter_um"][here], (size, size), pixel_um)
        holograms[frame] = simulate_hologram(field, wavelength_um=config.optics.wavelength_um, medium_index=config.optics.medium_index)
    return holograms, truth


def static_pattern(size: int) -> np.ndarray:
    """Static fringes (periods of 31 and 44 px, ±30 %) on a vignetting ramp (0.6–0.7): what a setup's optics add to every frame."""
    rows, cols = np.indices((size, size))
    return (0.6 + 0.3 * np.sin(rows / 5.0) * np.cos(cols / 7.0) + 0.1 * (cols / size)).astype(np.float32)


def recovered_tracks(linked: dict, truth: dict, *, frames: int, needed: int) -> dict:
    """True tracks recovered (a predicted track holds ≥ ``needed`` detections matched to it) and per-frame detection counts."""
    true_track_of = np.full(linked["x_um"].size, -1)
    tp = fp = fn = 0
    for frame in range(frames):
        pred_rows, truth_rows = np.flatnonzero(linked["frame"] == frame), np.flatnonzero(truth["frame"] == frame)
        pairs = match_particles({k: linked[k][pred_rows] for k in ("x_um", "y_um", "z_um", "diameter_um")}, {k: truth[k][truth_rows] for k in ("x_um", "y_um", "z_um", "diameter_um")})
        for i, j in pairs:
            true_track_of[pred_rows[i]] = truth["track"][truth_rows[j]]
        tp, fp, fn = tp + len(pairs), fp + len(pred_rows) - len(pairs), fn + len(truth_rows) - len(pairs)
    recovered = 0
    for track in np.unique(truth["track"]):
        mine = true_track_of == track
        counts = np.bincount(linked["track"][mine]) if mine.any() else np.zeros(1, int)
        recovered += int(counts.max() >= needed)
    return {"recovered": recovered, "true_tracks": len(np.unique(truth["track"])), "tp": tp, "fp": fp, "fn": fn,
            "predicted_tracks": int(linked["track"].max() + 1) if linked["track"].size else 0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--particles", type=int, default=12)
    parser.add_argument("--speeds", type=float, nargs="+", default=[4.0, 8.0, 16.0, 32.0], help="flow speed (µm per frame, 3-D; lateral step 0.768 × speed)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3], help="development seeds (default 1 2 3); the final check is seed 0")
    parser.add_argument("--backgrounds", nargs="+", default=["auto", "global", "flat", "none"])
    parser.add_argument("--recovered-links", type=int, default=6, help="matched detections a predicted track needs to recover a true track (default 6)")
    parser.add_argument("--pattern", action="store_true", help="multiply every frame by a static pattern of fringes and vignetting (what a real setup adds)")
    parser.add_argument("--measures-only", action="store_true", help="only print auto's measures (choose_background) for each case, no prediction")
    parser.add_argument("--workers", type=int, nargs="+", default=[], help="also run every case on a LocalCluster of N worker processes and record whether its table is the local one's, value for value")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    config = load_config(None)
    model = load_model(args.model, device="cpu")
    report = {"model": str(args.model), "model_sha256": model.sha256, "frames": args.frames, "size": args.size, "particles": args.particles,
              "recovered_links": args.recovered_links, "load_average_at_start": [round(v, 2) for v in psutil.getloadavg()],
              "threads": os.environ.get("NAPARI_LBS_THREADS"), "cases": []}
    totals: dict[str, list[int]] = {mode: [] for mode in args.backgrounds}
    for speed in args.speeds:
        for seed in args.seeds:
            frames, truth = uniform_flow(config, frames=args.frames, size=args.size, particles=args.particles, speed_um=speed, seed=seed)
            if args.pattern:
                frames *= static_pattern(args.size)
            if args.measures_only:
                mode, _, measures = choose_background(open_frames(frames))
                case = {"speed_um": speed, "seed": seed, "frames": args.frames, "pattern": args.pattern, "auto": mode, **measures}
                report["cases"].append(case)
                print(json.dumps(case), flush=True)
                continue
            for mode in args.backgrounds:
                start, cpu = time.perf_counter(), psutil.Process().cpu_times()
                result = predict_sequence(frames, model, config, background=mode)
                after = psutil.Process().cpu_times()
                linked = link_tracks(result.particles, search_range_um=60.0)
                case = {"speed_um": speed, "lateral_step_um": round(speed * float(np.hypot(*_UNIFORM_DIRECTION[:2])), 2), "seed": seed, "background": mode,
                        "background_used": result.provenance.get("background_used"), "background_measures": result.provenance.get("background_measures"),
                        **recovered_tracks(linked, truth, frames=args.frames, needed=args.recovered_links),
                        "seconds": round(time.perf_counter() - start, 2), "core_seconds": round(after.user + after.system - cpu.user - cpu.system, 2)}
                for workers in args.workers:
                    other = predict_sequence(frames, model, config, background=mode, workers=workers)
                    case[f"identical_with_{workers}_workers"] = set(other.particles) == set(result.particles) and all(
                        np.array_equal(other.particles[name], result.particles[name]) for name in result.particles)
                totals[mode].append(case["recovered"])
                report["cases"].append(case)
                print(json.dumps(case), flush=True)
    if args.measures_only:
        totals = {}
    report["summary"] = {mode: {"recovered": values, "min": min(values), "total": sum(values), "of": args.particles * len(values)} for mode, values in totals.items()}
    report["load_average_at_end"] = [round(v, 2) for v in psutil.getloadavg()]
    print(json.dumps(report["summary"], indent=1))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
