"""Learning benchmarks: training throughput, prediction time, the seed's simulation experiment.

Sub-commands (each prints ratios against a baseline measured in the same run):

``throughput``
    Training planes per second (256² planes, batch 8, forward + backward + Adam) for both
    presets, channels-last (what `train_model` uses) against the default memory layout.
``predict [--model M] [--hologram H]``
    `predict_particles` on the real 1024² hologram (or H) at 61 planes (1800–4800 µm), each
    setting in a fresh process: wall time and the process's peak resident memory, for one
    1024² window (``window_px=1024``) beside the default (256² windows, the tile size, with
    32-pixel margins), their ratio, how many particles the two tables share (within 2 µm),
    and back-propagation alone (the floor). Targets: <= 30 s, <= 2 GB.
    Without ``--model`` a token model is trained first (3 groups, 1 epoch; its accuracy is
    irrelevant here, only the time).
``real PARTICLES.csv [--figure PNG]``
    What can be seen of a prediction on the built-in real hologram without its reference:
    count, pairs within 22 µm laterally, scores, depths, and the detections over the hologram.
``sim [--groups G] [--minutes T] [--preset P] [--device D] [--formulation focus|seed] [--workers W] [--out DIR]``
    The seed's simulation experiment (Sec. 3.1): 60 particles of 20–30 µm per 256² group on 63
    layers 30 µm apart (1800–3660 µm), Holo-processing (0, 0, 1). Trains on G groups for at
    most T minutes (the stop keeps the best epoch by synthetic validation), printing the
    learning curve (held-out synthetic validation ER/JI against training minutes), then tests
    on a 768² field of 3x3 groups (540 particles, ppp 0.136 at 26.82 µm voxels) simulated as
    one hologram, with one-to-one scoring, the median depth error and, beside them, the seed's
    scoring. The seed reports ER 97.21 %, JI 0.97 (with its own scoring and a GPU).

Run: python benchmarks/bench_learning.py throughput|predict|real|sim [options]
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from napari_lbs._core import (
    DatasetLayout,
    ExperimentConfig,
    InputProcessing,
    TrainingSettings,
    generate_dataset,
    load_config,
    load_sample_hologram,
    predict_particles,
    random_particle_field,
    score_particles,
    simulate_hologram,
    train_model,
)
from napari_lbs._core.learning._metrics import depth_errors_um, seed_scores
from napari_lbs._core.physics._synthesis import count_for_ppp

SIM_CONFIG = ExperimentConfig.from_dict({
    "volume": {"z_min_um": 1800.0, "z_max_um": 3660.0, "z_step_um": 30.0},
    "particles": {"diameter_min_um": 20.0, "diameter_max_um": 30.0, "per_tile": 60, "layer_step_um": 30.0},
    "tile": {"size": 256},
})


def throughput() -> None:
    import torch

    from napari_lbs._core.learning._network import build_network

    for preset in ("small", "paper"):
        rates = {}
        for layout in ("contiguous", "channels_last"):
            network = build_network(preset)
            fmt = torch.channels_last if layout == "channels_last" else torch.contiguous_format
            network = network.to(memory_format=fmt)
            optimizer = torch.optim.Adam(network.parameters(), 1e-3)
            x = torch.rand(8, 1, 256, 256).contiguous(memory_format=fmt)
            y = torch.rand(8, 1, 256, 256)
            best = np.inf
            for _ in range(3 if preset == "small" else 2):
                start = time.perf_counter()
                optimizer.zero_grad()
                loss = ((network(x) - y) ** 2).mean()
                loss.backward()
                optimizer.step()
                best = min(best, time.perf_counter() - start)
            rates[layout] = 8 / best
        print(f"{preset:5s}: {rates['channels_last']:6.2f} planes/s channels-last, {rates['contiguous']:6.2f} contiguous (x{rates['channels_last'] / rates['contiguous']:.2f})")


def _token_model(folder: Path) -> Path:
    config = load_config(None)
    dataset = generate_dataset(folder / "data", config, groups=3, seed=0)
    return train_model(dataset, folder / "token.pt", settings=TrainingSettings(epochs=1, patch_size=64, validation_groups=1, foreground_weight=30.0)).model_path


def _predict_once(model: str, hologram_path: str | None, window_px: int, out_csv: str) -> None:
    """One prediction in this (fresh) process; prints a JSON line with its time and peak memory."""
    from napari_lbs._core import read_hologram, write_particles

    hologram = read_hologram(hologram_path) if hologram_path else load_sample_hologram()
    result = predict_particles(hologram, model, load_config(None), device="cpu", window_px=window_px)
    write_particles(out_csv, result.particles)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"window_px": window_px, "seconds": round(result.seconds, 2), "peak_rss_mib": round(peak_mib), "particles": len(result.particles["x_um"])}))


def predict(model: str | None, hologram_path: str | None) -> None:
    import subprocess
    import sys

    from napari_lbs._core import backpropagate, read_particles

    config = load_config(None)
    with tempfile.TemporaryDirectory() as folder:
        model_path = Path(model) if model else _token_model(Path(folder))
        runs = {}
        for window in (1024, 256):  # the default, then the former 256² tiles
            csv = str(Path(folder) / f"w{window}.csv")
            command = [sys.executable, __file__, "predict-once", "--model", str(model_path), "--window", str(window), "--csv", csv] + (["--hologram", hologram_path] if hologram_path else [])
            runs[window] = json.loads(subprocess.run(command, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1])
            runs[window]["table"] = read_particles(csv)
        hologram = load_sample_hologram()
        start = time.perf_counter()
        backpropagate(hologram, config.volume.planes_um(), wavelength_um=config.optics.wavelength_um, pixel_um=config.optics.pixel_um)
        floor = time.perf_counter() - start
    new, old = runs[1024], runs[256]
    shared = 0
    if len(old["table"]["x_um"]) and len(new["table"]["x_um"]):
        from scipy.spatial import cKDTree

        points = lambda t: np.column_stack([t["x_um"], t["y_um"], t["z_um"] / 25.0])  # noqa: E731 (2 µm laterally ~ 50 µm in depth)
        distances, _ = cKDTree(points(old["table"])).query(points(new["table"]))
        shared = int(np.sum(distances <= 2.0))
    for run in (new, old):
        print(f"window {run['window_px']:4d}: {run['seconds']:.1f} s, peak RSS {run['peak_rss_mib']} MiB, {run['particles']} particles")
    print(f"one 1024² window vs 256² windows (the default): x{old['seconds'] / new['seconds']:.2f} as fast; {shared} of {new['particles']} particles shared within 2 um "
          f"(targets: <= 30 s, <= 2 GB); back-propagation alone {floor:.2f} s ({100 * floor / new['seconds']:.0f} %)")


def sim(groups: int, minutes: float, preset: str, device: str, patch: int, epochs: int, formulation: str, workers: int, batch: int, out: str | None) -> None:
    folder = Path(out or tempfile.mkdtemp(prefix="napari-lbs-sim-"))
    start = time.perf_counter()
    layout = DatasetLayout(kind="stack", depths="layers") if formulation == "focus" else DatasetLayout(kind="layers")
    dataset = generate_dataset(folder / "data", SIM_CONFIG, groups=groups, processing=InputProcessing(), layout=layout, seed=0, workers=workers)
    generate_seconds = time.perf_counter() - start
    settings = TrainingSettings(formulation=formulation, preset=preset, epochs=epochs, batch_size=batch, device=device, patch_size=patch, foreground_weight=30.0,
                                validation_groups=max(2, groups // 8), minutes=minutes)
    curve = []

    def record(entry: dict) -> None:
        if "validation" in entry:
            v = entry["validation"]
            curve.append({"epoch": entry["epoch"], "minutes": round(entry["seconds"] / 60, 2), "er": round(v["er"], 4), "ji": round(v["ji"], 4)})
            print(f"epoch {entry['epoch']:3d} at {entry['seconds'] / 60:6.2f} min: validation ER {100 * v['er']:.2f} %, JI {v['ji']:.3f}", flush=True)

    trained = train_model(dataset, folder / "sim.pt", settings=settings, report=record)
    # Test field: 3x3 groups of 60 particles each, one hologram (the seed spliced 9 groups).
    truth = random_particle_field((768, 768), count=9 * 60, diameter_min_um=20, diameter_max_um=30, layers_um=SIM_CONFIG.layer_depths_um(), pixel_um=2.2, seed=12345)
    ppp = 9 * 60 / count_for_ppp(1.0, (768, 768), pixel_um=2.2, voxel_um=26.82)
    hologram = simulate_hologram(truth, wavelength_um=0.66)
    result = predict_particles(hologram, trained.model_path, SIM_CONFIG, device=device)
    one_to_one = score_particles(result.particles, truth.table())
    seed_style = seed_scores(result.particles, truth.table())
    dz = depth_errors_um(result.particles, truth.table())
    report = {
        "formulation": formulation,
        "groups": groups,
        "preset": preset,
        "patch_size": patch,
        "device": trained.log["device"],
        "generate_seconds": round(generate_seconds, 1),
        "train_seconds": trained.log["seconds"],
        "samples_per_second": trained.log["planes_per_second"],
        "epochs_done": len(trained.log["epochs"]),
        "stopped_by_budget": trained.stopped,
        "best": trained.log["best"],
        "learning_curve": curve,
        "predict_seconds": round(result.seconds, 1),
        "ppp": round(ppp, 4),
        "one_to_one": one_to_one,
        "median_abs_dz_um": float(np.median(np.abs(dz))) if dz.size else None,
        "seed_scoring": seed_style,
    }
    (folder / "report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
    print(f"sim experiment ({formulation}, {preset}): ER {100 * one_to_one['er']:.2f} %, JI {one_to_one['ji']:.3f} one-to-one "
          f"(seed's scoring: ER {100 * seed_style['er']:.2f} %, JI {seed_style['ji']:.3f}); the seed reports ER 97.21 %, JI 0.97")


def real(particles_csv: str, figure: str | None) -> None:
    """What can be seen of a prediction on the real hologram without its reference table."""
    from scipy.spatial import cKDTree

    from napari_lbs._core import read_particles

    table = read_particles(particles_csv)
    xy = np.column_stack([table["x_um"], table["y_um"]])
    pairs = cKDTree(xy).query_pairs(22.0) if len(xy) else set()
    score = np.asarray(table.get("score", np.ones(len(xy))))
    print(f"{len(xy)} particles; {len(pairs)} pairs within 22 um laterally (one sphere reported twice?); "
          f"score median {np.median(score):.2f}, {int(np.sum(score >= 0.9))} with score >= 0.9; "
          f"z {np.min(table['z_um']):.0f}-{np.max(table['z_um']):.0f} um (median {np.median(table['z_um']):.0f}); "
          f"diameter {np.min(table['diameter_um']):.1f}-{np.max(table['diameter_um']):.1f} um")
    if figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        hologram = load_sample_hologram()
        pixel = 2.2
        fig, ax = plt.subplots(figsize=(8, 7))
        ax.imshow(hologram, cmap="gray", extent=(-pixel / 2, (hologram.shape[1] - 0.5) * pixel, (hologram.shape[0] - 0.5) * pixel, -pixel / 2))
        depth = matplotlib.colors.Normalize(float(np.min(table["z_um"])), float(np.max(table["z_um"])))
        colours = matplotlib.colormaps["viridis"](depth(table["z_um"]))
        ax.scatter(table["x_um"], table["y_um"], s=(np.asarray(table["diameter_um"]) / 2) ** 2, facecolors="none", edgecolors=colours, linewidths=1.2)
        fig.colorbar(matplotlib.cm.ScalarMappable(depth, "viridis"), ax=ax, label="z (µm)")
        ax.set(xlabel="x (µm)", ylabel="y (µm)", title=f"{len(xy)} particles found by napari-lbs demo (focus formulation)")
        fig.savefig(figure, dpi=110, bbox_inches="tight")
        print(f"figure -> {figure}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("throughput")
    p = sub.add_parser("predict")
    p.add_argument("--model")
    p.add_argument("--hologram")
    p = sub.add_parser("predict-once")
    p.add_argument("--model", required=True)
    p.add_argument("--hologram")
    p.add_argument("--window", type=int, required=True)
    p.add_argument("--csv", required=True)
    p = sub.add_parser("real")
    p.add_argument("particles")
    p.add_argument("--figure")
    p = sub.add_parser("sim")
    p.add_argument("--groups", type=int, default=24)
    p.add_argument("--minutes", type=float, default=22.0)
    p.add_argument("--preset", default="small")
    p.add_argument("--device", default="auto")
    p.add_argument("--patch", type=int, default=128)
    p.add_argument("--epochs", type=int, default=100)
    p.add_argument("--formulation", default="focus", choices=("focus", "seed"))
    p.add_argument("--workers", type=int, default=1, help="processes simulating the training groups")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--out", help="keep the data, model and report.json here (default: a temporary folder)")
    args = parser.parse_args()
    if args.command == "throughput":
        throughput()
    elif args.command == "predict":
        predict(args.model, args.hologram)
    elif args.command == "predict-once":
        _predict_once(args.model, args.hologram, args.window, args.csv)
    elif args.command == "real":
        real(args.particles, args.figure)
    else:
        sim(args.groups, args.minutes, args.preset, args.device, args.patch, args.epochs, args.formulation, args.workers, args.batch, args.out)


if __name__ == "__main__":
    main()
