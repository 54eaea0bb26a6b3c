"""Training a network on a synthetic data set, validated by detection on held-out synthetic groups.

The network, its batches, its loss and its validation come from the formulation, ``focus``
(default) or the seed paper's ``seed`` (`napari_lbs._core.learning._formulations`); the settings
are `TrainingSettings` (`napari_lbs._core.learning._training_settings`).

Either formulation: AdamW with a cosine schedule over the planned epochs, a wall-clock budget (``minutes``),
early stopping on the synthetic validation JI (``patience``), resume.

Validation never looks at real data or test labels: the last ``validation_groups`` groups of
the set are held out, the network's outputs on them go through the same decoding as any
prediction and one-to-one scoring (`score_particles`); the decoding settings (threshold, and for
``focus`` the axial suppression radius) are chosen there, with the best epoch (by its peak JI,
then ER; the threshold kept is the peak's upper edge within a standard error, `_formulations`).
With ``average_last``, the kept network is instead the mean of the last epochs' weights, its
batch-norm statistics measured again on training crops (`_measure_batch_norm`) and its decoding
settings chosen on the same validation groups.

Files written (all atomically, so a stop or a crash never leaves a broken one):

``MODEL.pt``
    the best epoch's (or the epochs' mean's) weights plus everything prediction needs (see `napari_lbs._core.learning._network`);
``MODEL.json``
    the training log: settings, data set, per-epoch loss and validation metrics, timings;
``MODEL.last.pt``
    the last finished epoch with optimizer and random states, for ``resume=True``.

Same seed, same data, same device → the same weights on CPU, under any load: the work is a
fixed number of epochs, the batch order and crops come from the seed, and the CPU kernels the
network uses are deterministic. Their float summation order depends on the thread count, so
bit-identical weights on another machine need the same count (the log's ``threads``;
``NAPARI_LBS_THREADS``, `napari_lbs._core.foundation._threads`) and the same torch build and instruction set. A ``minutes`` budget stops at a time, not a
step: it is a safety stop, the one setting that can end two runs at different epochs, and the
log's ``stop_reason`` says when it did.
"""

from __future__ import annotations

import io
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from napari_lbs import __version__
from napari_lbs._core.foundation import InputError, ProgressCallback, ReportCallback, Steps, StopCallback, Stopped, atomic_write_bytes, check_target, write_json
from napari_lbs._core.foundation import check_resume_matches, load_resume_state, process_threads
from napari_lbs._core.learning._dataset import SyntheticDataset, dataset_summary, open_dataset
from napari_lbs._core.learning._formulations import _FocusFormulation, _SeedFormulation, merge_lateral_um
from napari_lbs._core.learning._network import PRESETS, resolve_device, save_model, weights_sha256
from napari_lbs._core.learning._training_settings import TrainingSettings, training_precision

__all__ = ["TrainingResult", "split_groups", "train_model"]

# Batch losses come to the host (one wait for the device) and are reported at most this often.
_REPORT_S = 0.5
# Training crops the averaged network's batch-norm statistics are measured on (batches; at most an epoch's).
_BATCH_NORM_BATCHES = 64


@dataclass(frozen=True)
class TrainingResult:
    """Where the model went and how training went."""

    model_path: Path
    log: dict
    stopped: bool

    @property
    def best(self) -> dict | None:
        return self.log.get("best")



def split_groups(dataset: SyntheticDataset, *, validation_groups: int = 0) -> tuple[list[int], list[int]]:
    """The data set's training and validation groups: the last ``validation_groups`` (0: an eighth, at least one) are held out."""
    groups = list(dataset.groups)
    n_validation = validation_groups or max(1, len(groups) // 8)
    if len(groups) < n_validation + 1:
        raise InputError(f"{dataset.path}: expected at least {n_validation + 1} groups (training + {n_validation} for validation), got {len(groups)}")
    return groups[:-n_validation], groups[-n_validation:]


def _save_state(path: Path, network, optimizer, schedule, *, epoch: int, log: dict, rng: np.random.Generator, mean: _WeightMean) -> None:
    buffer = io.BytesIO()
    torch.save({
        "state_dict": {k: v.detach().cpu() for k, v in network.state_dict().items()},
        "optimizer": optimizer.state_dict(),
        "schedule": schedule.state_dict(),
        "epoch": epoch,
        "log": json.dumps(log),
        "numpy_rng": json.dumps(rng.bit_generator.state),
        "torch_rng": torch.get_rng_state(),
        **mean.state(),
    }, buffer)
    atomic_write_bytes(path, buffer.getvalue())


class _WeightMean:
    """The running mean of the weights of the epochs from ``first`` on (None: no averaging)."""

    def __init__(self, first: int | None) -> None:
        self.first = first
        self.epochs: list[int] = []
        self.mean: dict[str, torch.Tensor] = {}

    def add(self, epoch: int, network) -> None:
        if self.first is None or epoch < self.first:
            return
        count = len(self.epochs)
        for name, value in network.state_dict().items():
            value = value.detach().cpu()
            # floats averaged in float64 (an exact mean of a few epochs); counters kept as the latest
            if not value.is_floating_point():
                self.mean[name] = value.clone()
            elif count:
                self.mean[name] += (value.double() - self.mean[name]) / (count + 1)
            else:
                self.mean[name] = value.double()
        self.epochs.append(epoch)

    def state(self) -> dict:
        return {"average_epochs": json.dumps(self.epochs), "average_state": self.mean} if self.epochs else {}

    def restore(self, state: dict) -> None:
        """The mean a training state carries, where its epochs all lie in this run's window (else it starts afresh)."""
        epochs = json.loads(state.get("average_epochs", "[]"))
        if self.first is not None and epochs and min(epochs) >= self.first and isinstance(state.get("average_state"), dict):
            self.epochs, self.mean = [int(e) for e in epochs], dict(state["average_state"])

    def network(self, formulation, device: torch.device, precision: str):
        built = formulation.network().to(device)
        built.precision = precision
        reference = built.state_dict()
        built.load_state_dict({name: value.to(reference[name].dtype) for name, value in self.mean.items()})
        return built


def _measure_batch_norm(network, formulation, *, seed: int, batch_size: int, batches: int, device: torch.device, stop: StopCallback) -> bool:
    """Set ``network``'s batch-norm statistics to their means over ``batches`` training batches; False when a stop came first.

    An average of weights is not an average of the activations they produce, so the running
    statistics the epochs' batch norms kept do not fit the mean network; they are measured
    again as `torch.optim.swa_utils.update_bn` does, on crops drawn from their own seed.
    """
    norms = [m for m in network.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    momenta = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # a cumulative mean over the batches
    rng = np.random.default_rng([seed, 1])
    network.train()
    try:
        with torch.no_grad():
            for _ in range(batches):
                if stop():
                    return False
                network(formulation.batch(np.arange(batch_size), rng, device)[0])
    finally:
        for m, momentum in zip(norms, momenta, strict=True):
            m.momentum = momentum
        network.eval()
    return True


def train_model(
    data: str | Path | SyntheticDataset,
    out: str | Path,
    *,
    settings: TrainingSettings = TrainingSettings(),
    resume: bool = False,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
    report: ReportCallback | None = None,
    force: bool = False,
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
        One step per batch. A stop ends training after the current batch, or within one
        validation group during a validation pass (that pass is dropped): the best validated
        model so far stays and no part epoch is validated. The ``minutes`` budget ends it after
        the current batch and validates the part epoch. The log's ``stop_reason`` says which
        ended it ("stopped by you", "time budget reached"; None when training ran its epochs).
    report : callable, optional
        Called with a dict for every batch (``{"epoch", "batch", "loss"}``; the batches' losses
        come at most every half second, several at once, so that the device is not waited for
        at every batch) and after every epoch (``{"epoch", "train_loss", "validation": {...}}``),
        for live plots.
    force : bool
        Replace an existing model and log (a resumed training replaces its own); links,
        FIFOs, devices and folders are refused regardless.

    Raises
    ------
    Stopped
        When a stop came before any epoch was validated: no model is written (``MODEL.last.pt``
        keeps the last finished epoch, if any, for ``resume``).
    """
    dataset = data if isinstance(data, SyntheticDataset) else open_dataset(data)
    out = Path(out)
    if out.suffix != ".pt":
        raise InputError(f"{out}: expected a model file name ending in .pt")
    log_path, state_path = out.with_suffix(".json"), out.with_suffix(".last.pt")
    for path in (out, log_path):
        check_target(path, force=force or resume)
    training, validation = split_groups(dataset, validation_groups=settings.validation_groups)
    config = dataset.config
    size = dataset.spec["tile_size"]
    if settings.patch_size > size:
        raise InputError(f"patch_size: a {settings.patch_size}-pixel patch is larger than the {size}-pixel tiles of {dataset.path}")
    device = resolve_device(settings.device)

    threads = process_threads()
    torch.manual_seed(settings.seed)
    rng = np.random.default_rng(settings.seed)
    formulation = (_FocusFormulation if settings.formulation == "focus" else _SeedFormulation)(dataset, training, settings, device)
    network = formulation.network().to(device)
    network.precision = training_precision(settings.precision, device)
    batches = -(-formulation.samples // settings.batch_size)
    optimizer = torch.optim.AdamW(network.parameters(), lr=settings.rate, weight_decay=1e-4)
    total_steps = settings.epochs * batches
    # cosine decay from the peak rate after a 3 % warm-up, over the planned epochs
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: min(1.0, (step + 1) / max(1, 0.03 * total_steps)) * 0.5 * (1 + math.cos(math.pi * min(step, total_steps) / total_steps)))

    log = {
        "napari_lbs": __version__,
        "settings": asdict(settings),
        "learning_rate": settings.rate,
        "device": str(device),
        "precision": network.precision,
        "threads": threads,
        "dataset": dataset_summary(dataset),
        "training_groups": training,
        "validation_groups": validation,
        "epochs": [],
        "best": None,
        "model": str(out),
    }
    first_epoch = 0
    mean = _WeightMean(max(1, settings.epochs - settings.average_last + 1) if settings.average_last else None)
    if resume and state_path.is_file():
        state = load_resume_state(state_path)  # corrupt, foreign or code-carrying files are refused, naming the file
        check_resume_matches(state, log, name=str(state_path), free=("epochs", "minutes", "patience", "validate_last", "average_last"))
        previous = json.loads(state["log"])
        network.load_state_dict(state["state_dict"])
        optimizer.load_state_dict(state["optimizer"])
        rng.bit_generator.state = json.loads(state["numpy_rng"])
        torch.set_rng_state(state["torch_rng"])
        schedule.load_state_dict(state["schedule"])
        first_epoch = int(state["epoch"])
        log = previous | {"settings": log["settings"]}
        mean.restore(state)

    steps = Steps((settings.epochs - first_epoch) * batches, progress=progress, should_stop=should_stop)
    meta_base = {
        "formulation": formulation.name,
        "preset": settings.preset,
        "widths": list(PRESETS[settings.preset]),
        "tile_size": size,
        "config": config.to_dict(),
        "processing": dataset.spec["processing"],
        "planes_um": dataset.planes_um,
        "merge_lateral_um": merge_lateral_um(config),
        "dataset": dataset_summary(dataset),
        "settings": asdict(settings),
        "precision": network.precision,
        "napari_lbs": __version__,
        **formulation.meta(),
    }
    best_score = tuple(log["best"]["score"]) if log["best"] else (-1.0, -1.0)
    stopped = False
    log["stop_reason"] = None  # or why this run ended early: "stopped by you", "time budget reached"
    start = time.perf_counter()
    deadline = start + 60.0 * settings.minutes if settings.minutes else math.inf
    batch_seconds = 0.0  # the training loop with its sample assembly, for the throughput figure (validation excluded)

    def finish_epoch(epoch: int, losses: list[float], train_seconds: float) -> bool:
        """Validate, keep the model if it is the best, log the epoch; False when a stop ended the validation (nothing recorded)."""
        nonlocal best_score
        validation_metrics = formulation.validate(network, validation, steps.stop_requested)
        if validation_metrics is None:
            return False
        record = {"epoch": epoch, "train_loss": float(np.mean(losses)) if losses else None, "validation": validation_metrics, "seconds": round(time.perf_counter() - start, 2),
                  "train_seconds": round(train_seconds, 3)}
        log["epochs"].append(record)
        # epochs ranked by their validation peak; the kept setting is the peak's upper edge (`_formulations`)
        score = (validation_metrics["peak_ji"], validation_metrics["er"])
        if score > best_score or log["best"] is None:
            best_score = score
            decoding = formulation.decoding(validation_metrics)
            meta = meta_base | decoding | {"epoch": epoch, "validation": {k: v for k, v in validation_metrics.items() if k != "by_threshold"}}
            digest = save_model(out, network, meta)
            log["best"] = {"epoch": epoch, "score": list(score), **decoding, "sha256": digest, "weights_sha256": weights_sha256(network)}
        if report is not None:
            report(record)
        write_json(log_path, log)
        return True

    def out_of_patience() -> bool:
        if not settings.patience or not log["best"]:
            return False
        return log["epochs"][-1]["epoch"] - log["best"]["epoch"] >= settings.patience

    for epoch in range(first_epoch + 1, settings.epochs + 1):
        network.train()
        order = rng.permutation(formulation.samples)
        losses: list[float] = []
        losses_pending: list[torch.Tensor] = []  # the batches' losses still on the device
        flushed = time.perf_counter()
        epoch_start = time.perf_counter()

        def flush(epoch: int = epoch, losses: list[float] = losses, pending: list[torch.Tensor] = losses_pending) -> None:
            """Bring the pending batch losses to the host (one wait for the device) and report them."""
            if not pending:
                return
            values = torch.stack(pending).tolist()
            pending.clear()
            for value in values:
                losses.append(value)
                if report is not None:
                    report({"epoch": epoch, "batch": len(losses), "batches": batches, "loss": value})

        for b in range(batches):
            if steps.stop_requested() or time.perf_counter() > deadline:
                stopped = True
                log["stop_reason"] = "stopped by you" if steps.stop_requested() else "time budget reached"
                break
            x, targets = formulation.batch(order[b * settings.batch_size : (b + 1) * settings.batch_size], rng, device)
            optimizer.zero_grad(set_to_none=True)
            loss = formulation.loss(network(x), targets)
            loss.backward()
            optimizer.step()
            schedule.step()
            losses_pending.append(loss.detach())
            steps.advance()
            if time.perf_counter() - flushed >= _REPORT_S:
                flush()
                flushed = time.perf_counter()
        flush()
        epoch_seconds = time.perf_counter() - epoch_start
        batch_seconds += epoch_seconds
        if stopped:
            if steps.stop_requested():
                # a user's stop: no validation of a part epoch (it would take a validation pass's
                # time and score a half-trained network); the best model so far stays
                break
            # the budget's part epoch is validated like any (the best model may be the latest)
            if losses:
                finish_epoch(epoch, losses, epoch_seconds)
            break
        if not settings.validate_last or epoch > settings.epochs - settings.validate_last:
            if not finish_epoch(epoch, losses, epoch_seconds):
                stopped, log["stop_reason"] = True, "stopped by you"
                break
        else:
            record = {"epoch": epoch, "train_loss": float(np.mean(losses)) if losses else None, "seconds": round(time.perf_counter() - start, 2),
                      "train_seconds": round(epoch_seconds, 3)}
            log["epochs"].append(record)
            if report is not None:
                report(record)
            write_json(log_path, log)
        mean.add(epoch, network)
        _save_state(state_path, network, optimizer, schedule, epoch=epoch, log=log, rng=rng, mean=mean)
        if out_of_patience():
            log["early_stop"] = f"no better validation JI for {settings.patience} epochs"
            break

    if mean.epochs and not stopped and "early_stop" not in log and mean.epochs[-1] == settings.epochs:
        averaged = mean.network(formulation, device, network.precision)
        measured = _measure_batch_norm(averaged, formulation, seed=settings.seed, batch_size=settings.batch_size, batches=min(batches, _BATCH_NORM_BATCHES),
                                       device=device, stop=steps.stop_requested)
        validation_metrics = formulation.validate(averaged, validation, steps.stop_requested) if measured else None
        if validation_metrics is None:  # a stop: the best validated epoch stays
            stopped, log["stop_reason"] = True, "stopped by you"
        else:
            decoding = formulation.decoding(validation_metrics)
            meta = meta_base | decoding | {"epoch": settings.epochs, "averaged_epochs": mean.epochs,
                                           "validation": {k: v for k, v in validation_metrics.items() if k != "by_threshold"}}
            digest = save_model(out, averaged, meta)
            log["average"] = {"epochs": mean.epochs, "validation": validation_metrics}
            log["best"] = {"epoch": settings.epochs, "averaged_epochs": mean.epochs, "score": [validation_metrics["peak_ji"], validation_metrics["er"]], **decoding,
                           "sha256": digest, "weights_sha256": weights_sha256(averaged)}
    log["stopped"] = stopped
    log["seconds"] = round(time.perf_counter() - start, 2)
    log["planes_per_second"] = round(steps.done * settings.batch_size / max(batch_seconds, 1e-9), 2)
    write_json(log_path, log)
    if log["best"] is None:
        done = len(log["epochs"])
        kept = f"; {state_path.name} holds epoch {log['epochs'][-1]['epoch']} (train again with resume to go on)" if done else ""
        raise Stopped(f"training stopped before any epoch was validated: no model written{kept}")
    return TrainingResult(out, log, stopped)
