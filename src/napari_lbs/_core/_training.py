"""Training the U-Net on a synthetic data set, validated by detection on held-out synthetic groups.

Validation never looks at real data or test labels: the last ``validation_groups`` groups of
the set are held out, the network's outputs on them go through the same decoding
(`PlaneLinker`) and one-to-one scoring (`score_particles`) as any prediction, and the
detection threshold is chosen there, among a fixed grid, with the best epoch (by JI, then ER).

Files written (all atomically, so a stop or a crash never leaves a broken one):

``MODEL.pt``
    the best epoch's weights plus everything prediction needs (see `napari_lbs._core._network`);
``MODEL.json``
    the training log: settings, data set, per-epoch loss and validation metrics, timings;
``MODEL.last.pt``
    the last finished epoch with optimizer and random states, for ``resume=True``.

Same seed, same data, same device → the same weights on CPU.
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from napari_lbs import __version__
from napari_lbs._core._dataset import SyntheticDataset, dataset_summary, open_dataset
from napari_lbs._core._detection import PlaneLinker
from napari_lbs._core._io import InputError, atomic_write_bytes, write_json
from napari_lbs._core._metrics import score_particles
from napari_lbs._core._network import PRESETS, build_network, network_outputs, resolve_device, save_model
from napari_lbs._core._progress import ProgressCallback, Steps, StopCallback
from napari_lbs._core._synthesis import LABEL_SCALE

__all__ = ["TrainingSettings", "TrainingResult", "train_model", "THRESHOLD_FRACTIONS"]

# Detection thresholds tried on validation, as fractions of the smallest trained label value.
THRESHOLD_FRACTIONS = (0.15, 0.25, 0.35, 0.5, 0.65)
_DEFAULT_RATE = {"paper": 1e-4, "small": 1e-3}
ReportCallback = Callable[[dict], None]


@dataclass(frozen=True)
class TrainingSettings:
    """How to train.

    Attributes
    ----------
    preset : {"small", "paper"}
    epochs, batch_size : int
    learning_rate : float or None
        Adam's rate; None → 1e-4 for ``paper`` (the seed's) and 1e-3 for ``small``.
    device : {"auto", "cpu", "cuda"}
    seed : int
        Seeds the weights, the batch order and the patch positions.
    validation_groups : int
        Groups held out (the last ones); 0 → one eighth of the set, at least one.
    patch_size : int
        Train on random square crops of this size (0 = whole tiles). The network is fully
        convolutional, so it still predicts on whole tiles.
    foreground_weight : float
        Weight of label pixels in the MSE (1 = the seed's plain MSE); >1 counters the
        sparsity of the 3x3 squares.
    """

    preset: str = "small"
    epochs: int = 10
    batch_size: int = 8
    learning_rate: float | None = None
    device: str = "auto"
    seed: int = 0
    validation_groups: int = 0
    patch_size: int = 0
    foreground_weight: float = 1.0

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise InputError(f"preset: expected one of {', '.join(PRESETS)}, got {self.preset!r}")
        for name in ("epochs", "batch_size"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: expected a positive integer, got {getattr(self, name)!r}")
        if self.learning_rate is not None and not 0 < self.learning_rate < 1:
            raise InputError(f"learning_rate: expected a value in (0, 1), got {self.learning_rate}")
        if self.validation_groups < 0 or self.patch_size < 0 or (0 < self.patch_size < 16):
            raise InputError(f"validation_groups / patch_size: expected >= 0 (patch >= 16), got {self.validation_groups} / {self.patch_size}")
        if self.foreground_weight < 1:
            raise InputError(f"foreground_weight: expected >= 1, got {self.foreground_weight}")
        resolve_device(self.device)

    @property
    def rate(self) -> float:
        return self.learning_rate if self.learning_rate is not None else _DEFAULT_RATE[self.preset]


@dataclass
class TrainingResult:
    """Where the model went and how training went."""

    model_path: Path
    log: dict
    stopped: bool

    @property
    def best(self) -> dict | None:
        return self.log.get("best")


def merge_lateral_um(config) -> float:
    """Detections closer than half the smallest trained diameter are one particle (`PlaneLinker`)."""
    return 0.5 * config.particles.diameter_min_um


def _validate(network, dataset: SyntheticDataset, groups: list[int], *, output_scale: float, full_value: float) -> dict:
    """Loss and, for each threshold of the grid, one-to-one metrics summed over the groups."""
    config = dataset.config
    totals = {fraction: {"tp": 0, "fp": 0, "fn": 0} for fraction in THRESHOLD_FRACTIONS}
    squared, count = 0.0, 0
    for group in groups:
        inputs, labels, description = dataset.read_group(group)
        outputs = network_outputs(network, inputs, output_scale=output_scale)
        squared += float(np.sum(((outputs - labels) / output_scale) ** 2))
        count += labels.size
        truth = {key: np.asarray(values) for key, values in description["particles"].items()}
        for fraction in THRESHOLD_FRACTIONS:
            linker = PlaneLinker(dataset.planes_um, pixel_um=config.optics.pixel_um, threshold=fraction * full_value, full_value=full_value, merge_lateral_um=merge_lateral_um(config))
            for plane, output in enumerate(outputs):
                linker.add(plane, output)
            metrics = score_particles(linker.particles(), truth)
            for key in ("tp", "fp", "fn"):
                totals[fraction][key] += metrics[key]
    by_threshold = []
    for fraction, t in totals.items():
        n_truth = t["tp"] + t["fn"]
        by_threshold.append({
            "threshold": fraction * full_value,
            **t,
            "er": 1.0 - t["fn"] / n_truth if n_truth else 1.0,
            "ji": t["tp"] / (t["tp"] + t["fp"] + t["fn"]) if (t["tp"] + t["fp"] + t["fn"]) else 1.0,
        })
    best = max(by_threshold, key=lambda m: (m["ji"], m["er"]))
    return {"loss": squared / max(count, 1), **best, "by_threshold": by_threshold}


def _save_state(path: Path, network, optimizer, *, epoch: int, log: dict, rng: np.random.Generator) -> None:
    buffer = io.BytesIO()
    torch.save({
        "state_dict": {k: v.detach().cpu() for k, v in network.state_dict().items()},
        "optimizer": optimizer.state_dict(),
        "epoch": epoch,
        "log": json.dumps(log),
        "numpy_rng": json.dumps(rng.bit_generator.state),
        "torch_rng": torch.get_rng_state(),
    }, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def train_model(
    data: str | Path | SyntheticDataset,
    out: str | Path,
    *,
    settings: TrainingSettings = TrainingSettings(),
    resume: bool = False,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
    report: ReportCallback | None = None,
) -> TrainingResult:
    """Train a network on a data set folder (the `napari-lbs train` step).

    Parameters
    ----------
    data : path or SyntheticDataset
    out : path
        The model file (``.pt``); the log goes to the same name with ``.json``.
    settings : TrainingSettings
    resume : bool
        Continue from ``MODEL.last.pt`` if it exists (same settings and data required).
    progress, should_stop
        One step per batch. A stop ends training after the current batch; the best model so
        far stays (if no epoch had finished, the current weights are validated and saved).
    report : callable, optional
        Called with a dict after every batch (``{"epoch", "batch", "loss"}``) and after every
        epoch (``{"epoch", "train_loss", "validation": {...}}``), for live plots.
    """
    dataset = data if isinstance(data, SyntheticDataset) else open_dataset(data)
    out = Path(out)
    if out.suffix != ".pt":
        raise InputError(f"{out}: expected a model file name ending in .pt")
    log_path, state_path = out.with_suffix(".json"), out.with_suffix(".last.pt")
    groups = list(dataset.groups)
    n_validation = settings.validation_groups or max(1, len(groups) // 8)
    if len(groups) < n_validation + 1:
        raise InputError(f"{dataset.path}: expected at least {n_validation + 1} groups (training + {n_validation} for validation), got {len(groups)}")
    validation, training = groups[-n_validation:], groups[:-n_validation]
    config = dataset.config
    size = dataset.spec["tile_size"]
    if settings.patch_size > size:
        raise InputError(f"patch_size: a {settings.patch_size}-pixel patch is larger than the {size}-pixel tiles of {dataset.path}")
    output_scale = LABEL_SCALE * config.particles.diameter_max_um
    full_value = LABEL_SCALE * config.particles.diameter_min_um
    device = resolve_device(settings.device)

    torch.manual_seed(settings.seed)
    rng = np.random.default_rng(settings.seed)
    network = build_network(settings.preset).to(device)
    optimizer = torch.optim.Adam(network.parameters(), lr=settings.rate)
    inputs, labels = dataset.arrays(training)
    targets = labels / np.float32(output_scale)

    log = {
        "napari_lbs": __version__,
        "settings": asdict(settings),
        "learning_rate": settings.rate,
        "device": str(device),
        "dataset": dataset_summary(dataset),
        "training_groups": training,
        "validation_groups": validation,
        "epochs": [],
        "best": None,
        "model": str(out),
    }
    first_epoch = 0
    if resume and state_path.is_file():
        state = torch.load(state_path, map_location="cpu", weights_only=True)
        previous = json.loads(state["log"])
        if previous["settings"] | {"epochs": 0} != log["settings"] | {"epochs": 0} or previous["dataset"] != log["dataset"]:
            raise InputError(f"{state_path}: was made with other settings or data; train afresh or delete it")
        network.load_state_dict(state["state_dict"])
        optimizer.load_state_dict(state["optimizer"])
        rng.bit_generator.state = json.loads(state["numpy_rng"])
        torch.set_rng_state(state["torch_rng"])
        first_epoch = int(state["epoch"])
        log = previous | {"settings": log["settings"]}

    patch = settings.patch_size or size
    batches = -(-len(inputs) // settings.batch_size)
    steps = Steps((settings.epochs - first_epoch) * batches, progress=progress, should_stop=should_stop)
    meta_base = {
        "preset": settings.preset,
        "widths": list(PRESETS[settings.preset]),
        "tile_size": size,
        "config": config.to_dict(),
        "processing": dataset.spec["processing"],
        "planes_um": dataset.planes_um,
        "output_scale": output_scale,
        "full_value": full_value,
        "merge_lateral_um": merge_lateral_um(config),
        "dataset": dataset_summary(dataset),
        "settings": asdict(settings),
        "napari_lbs": __version__,
    }
    best_score = tuple(log["best"]["score"]) if log["best"] else (-1.0, -1.0)
    stopped = False
    start = time.perf_counter()
    batch_seconds = 0.0  # training steps alone, for the throughput figure (validation excluded)

    def finish_epoch(epoch: int, losses: list[float]) -> None:
        nonlocal best_score
        validation_metrics = _validate(network, dataset, validation, output_scale=output_scale, full_value=full_value)
        record = {"epoch": epoch, "train_loss": float(np.mean(losses)) if losses else None, "validation": validation_metrics, "seconds": round(time.perf_counter() - start, 2)}
        log["epochs"].append(record)
        score = (validation_metrics["ji"], validation_metrics["er"])
        if score > best_score or log["best"] is None:
            best_score = score
            meta = meta_base | {"threshold": validation_metrics["threshold"], "epoch": epoch, "validation": {k: v for k, v in validation_metrics.items() if k != "by_threshold"}}
            digest = save_model(out, network, meta)
            log["best"] = {"epoch": epoch, "score": list(score), "threshold": validation_metrics["threshold"], "sha256": digest}
        if report is not None:
            report(record)
        write_json(log_path, log)

    for epoch in range(first_epoch + 1, settings.epochs + 1):
        network.train()
        order = rng.permutation(len(inputs))
        losses: list[float] = []
        for b in range(batches):
            if steps.stop_requested():
                stopped = True
                break
            index = np.sort(order[b * settings.batch_size : (b + 1) * settings.batch_size])
            r0, c0 = (rng.integers(0, size - patch + 1, 2) if patch < size else (0, 0))
            x = torch.from_numpy(inputs[index, r0 : r0 + patch, c0 : c0 + patch])[:, None].to(device).contiguous(memory_format=torch.channels_last)
            y = torch.from_numpy(targets[index, r0 : r0 + patch, c0 : c0 + patch])[:, None].to(device)
            batch_start = time.perf_counter()
            optimizer.zero_grad(set_to_none=True)
            prediction = network(x)
            weight = 1.0 + (settings.foreground_weight - 1.0) * (y > 0).float()
            loss = torch.mean(weight * (prediction - y) ** 2)
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
            batch_seconds += time.perf_counter() - batch_start
            steps.advance()
            if report is not None:
                report({"epoch": epoch, "batch": b + 1, "batches": batches, "loss": losses[-1]})
        if stopped:
            if log["best"] is None:  # nothing saved yet: keep what there is, validated like any epoch
                finish_epoch(epoch, losses)
            break
        finish_epoch(epoch, losses)
        _save_state(state_path, network, optimizer, epoch=epoch, log=log, rng=rng)

    log["stopped"] = stopped
    log["seconds"] = round(time.perf_counter() - start, 2)
    log["planes_per_second"] = round(steps.done * settings.batch_size / max(batch_seconds, 1e-9), 2)
    write_json(log_path, log)
    return TrainingResult(out, log, stopped)
