"""Training a network on a synthetic data set, validated by detection on held-out synthetic groups.

Two formulations (`napari_lbs._core.learning._network`):

``focus`` (default)
    input: the context planes around a depth; output: centre probability, depth offset and
    diameter (`napari_lbs._core.learning._heatmaps`). Loss: the penalty-reduced focal loss of CenterNet
    (Zhou et al. 2019) on the heat — positives are the peak voxels, every other voxel is a
    negative weighted by ``(1 - heat)^4`` so that planes just beside a focus cost less than far
    ones — plus L1 on offset and (weighted ``diameter_weight``, 4) diameter at the peaks only. Samples: 128² (``patch_size``)
    crops, half of them holding a particle at or near its focal plane (the hard negatives are
    the planes 1–3 away), half anywhere; dihedral flips and, with ``augment``, gamma, contrast,
    noise and 8-bit quantisation.
``seed``
    the seed paper's: one plane in, 3x3 label squares out, (foreground-weighted) MSE.

Both: AdamW with a cosine schedule over the planned epochs, a wall-clock budget (``minutes``),
early stopping on the synthetic validation JI (``patience``), resume.

Validation never looks at real data or test labels: the last ``validation_groups`` groups of
the set are held out, the network's outputs on them go through the same decoding as any
prediction and one-to-one scoring (`score_particles`); the decoding settings (threshold, and for
``focus`` the axial suppression radius) are chosen there, with the best epoch (by JI, then ER).

Files written (all atomically, so a stop or a crash never leaves a broken one):

``MODEL.pt``
    the best epoch's weights plus everything prediction needs (see `napari_lbs._core.learning._network`);
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
from napari_lbs._core.learning._dataset import SyntheticDataset, dataset_summary, open_dataset
from napari_lbs._core.learning._detection import PeakDecoder, PlaneLinker, suppress
from napari_lbs._core.learning._device_samples import augment_planes, dihedral_crops, render_marks
from napari_lbs._core.learning._heatmaps import FocusSpec, context_indices, focus_marks
from napari_lbs._core.foundation import atomic_write_bytes, check_target, write_json
from napari_lbs._core.foundation import InputError
from napari_lbs._core.learning._metrics import depth_errors_um, diameter_errors_um, score_particles
from napari_lbs._core.learning._network import FORMULATIONS, PRESETS, build_network, focus_maps, network_outputs, resolve_device, resolve_precision, save_model, weights_sha256
from napari_lbs._core.foundation import ProgressCallback, ReportCallback, Steps, StopCallback, Stopped
from napari_lbs._core.physics import LABEL_SCALE
from napari_lbs._core.foundation import process_threads
from napari_lbs._core.foundation import check_resume_matches, load_resume_state

__all__ = ["TrainingSettings", "TrainingResult", "train_model", "THRESHOLD_FRACTIONS", "FOCUS_THRESHOLDS"]

# Detection thresholds tried on validation: seed formulation, fractions of the smallest label
# value; focus formulation, probabilities.
THRESHOLD_FRACTIONS = (0.15, 0.25, 0.35, 0.5, 0.65)
FOCUS_THRESHOLDS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
_AXIAL_PLANES = (2.0, 5.0, 1e6)  # axial suppression radii tried on validation, in planes (1e6: any depth)
_DEFAULT_RATE = {"paper": 3e-4, "medium": 1e-3, "small": 2e-3}
_FOCAL_ALPHA, _FOCAL_BETA = 2.0, 4.0
# Batch losses come to the host (one wait for the device) and are reported at most this often.
_REPORT_S = 0.5


def training_precision(precision: str, device: torch.device) -> str:
    """The network's arithmetic for training: `resolve_precision`, except that ``auto`` is float32 on a CPU.

    On a CPU with native bfloat16, training in it learned more slowly (docs/learning.md,
    "Arithmetic precision"); on a CUDA GPU, ``auto`` is bfloat16 where it is native, the
    tensor cores' fast path.
    """
    return "float32" if precision == "auto" and device.type == "cpu" else resolve_precision(precision, device)


@dataclass(frozen=True)
class TrainingSettings:
    """How to train.

    Attributes
    ----------
    formulation : {"focus", "seed"}
        See the module docstring; ``seed`` is the seed paper's, kept for comparison.
    preset : {"small", "medium", "paper"}
    epochs, batch_size : int
    learning_rate : float or None
        AdamW's peak rate; None → 3e-4 ``paper``, 1e-3 ``medium``, 2e-3 ``small``.
    device : {"auto", "cpu", "cuda"}
    seed : int
        Seeds the weights, the batch order, the crops and the augmentation.
    validation_groups : int
        Groups held out (the last ones); 0 → one eighth of the set, at least one.
    patch_size : int
        Train on square crops of this size (0 = whole tiles; ``focus`` default 128). The network
        is fully convolutional, so it still predicts on whole tiles.
    foreground_weight : float
        ``seed``: weight of label pixels in the MSE (1 = the seed's plain MSE).
    context : tuple of int
        ``focus``: plane offsets fed as channels (`FocusSpec`).
    minutes : float
        Wall-clock budget of the training loop (0 = none); the best model so far is kept.
    patience : int
        Stop after this many epochs without a better validation JI (0 = never).
    validate_last : int
        Validate (and keep the best of) only the last this many epochs; 0 = every epoch. A
        validation pass costs about a fifth of an epoch, and with the cosine decay the best
        epoch is nearly always among the last.
    precision : {"float32", "auto", "bfloat16"}
        The network's arithmetic (`training_precision`: ``auto`` is bfloat16 on a CUDA GPU that
        has it natively and float32 on a CPU). Training in bfloat16 ran 1.6x faster per
        epoch on an AMX CPU but learned more slowly (demo recipe, two runs: training loss 4-5 %
        higher at every epoch, validation JI 0.90 instead of 0.95 after 5 epochs), so float32
        is the default; prediction runs bfloat16 where it is native (the same detections).
    augment : bool
        ``focus``: random gamma, contrast, noise and quantisation of the inputs.
    diameter_weight : float
        ``focus``: weight of the diameter's L1 term in the loss. The diameter is regressed as
        d / diameter_max_um, so a 1 µm error is 0.03 of a unit: weighted 1, like the depth
        offset, it barely moved once unlabelled distractors made the heat harder to learn
        (pseudo-real diameter correlation 0.07 after 5 epochs; 0.95 with 4, docs/learning.md).
    """

    formulation: str = "focus"
    preset: str = "small"
    epochs: int = 10
    batch_size: int = 8
    learning_rate: float | None = None
    device: str = "auto"
    seed: int = 0
    validation_groups: int = 0
    patch_size: int = 0
    foreground_weight: float = 1.0
    context: tuple[int, ...] = FocusSpec().context
    minutes: float = 0.0
    patience: int = 0
    validate_last: int = 0
    augment: bool = True
    diameter_weight: float = 4.0
    precision: str = "float32"

    def __post_init__(self) -> None:
        if self.formulation not in FORMULATIONS:
            raise InputError(f"formulation: expected one of {', '.join(FORMULATIONS)}, got {self.formulation!r}")
        if self.preset not in PRESETS:
            raise InputError(f"preset: expected one of {', '.join(PRESETS)}, got {self.preset!r}")
        for name in ("epochs", "batch_size"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: expected a positive integer, got {getattr(self, name)!r}")
        if self.learning_rate is not None and not 0 < self.learning_rate < 1:
            raise InputError(f"learning_rate: expected a value in (0, 1), got {self.learning_rate}")
        if self.validation_groups < 0 or self.patch_size < 0 or (0 < self.patch_size < 16):
            raise InputError(f"validation_groups / patch_size: expected >= 0 (patch >= 16), got {self.validation_groups} / {self.patch_size}")
        if not 0 < self.diameter_weight < 1e3:
            raise InputError(f"diameter_weight: expected a value in (0, 1000), got {self.diameter_weight}")
        if self.foreground_weight < 1:
            raise InputError(f"foreground_weight: expected >= 1, got {self.foreground_weight}")
        if self.minutes < 0 or self.patience < 0 or self.validate_last < 0:
            raise InputError(f"minutes / patience / validate_last: expected >= 0, got {self.minutes} / {self.patience} / {self.validate_last}")
        FocusSpec(context=tuple(self.context))
        training_precision(self.precision, resolve_device(self.device))

    @property
    def rate(self) -> float:
        return self.learning_rate if self.learning_rate is not None else _DEFAULT_RATE[self.preset]


@dataclass(frozen=True)
class TrainingResult:
    """Where the model went and how training went."""

    model_path: Path
    log: dict
    stopped: bool

    @property
    def best(self) -> dict | None:
        return self.log.get("best")


def merge_lateral_um(config) -> float:
    """Detections closer than half the smallest trained diameter are one particle."""
    return 0.5 * config.particles.diameter_min_um


def _metrics(totals: dict) -> dict:
    n_truth = totals["tp"] + totals["fn"]
    matched = totals["tp"] + totals["fp"] + totals["fn"]
    return {**totals, "er": 1.0 - totals["fn"] / n_truth if n_truth else 1.0, "ji": totals["tp"] / matched if matched else 1.0}


class _SeedFormulation:
    """The seed paper's: single planes in, 3x3 label squares (4 x diameter) out, MSE."""

    name = "seed"

    def __init__(self, dataset: SyntheticDataset, training: list[int], settings: TrainingSettings, device: torch.device = torch.device("cpu")) -> None:
        config = dataset.config
        self.settings = settings
        self.dataset = dataset
        self.output_scale = LABEL_SCALE * config.particles.diameter_max_um
        self.full_value = LABEL_SCALE * config.particles.diameter_min_um
        inputs, labels, _ = dataset.arrays(training)
        self.inputs = inputs.reshape((-1,) + inputs.shape[2:])
        self.targets = labels.reshape(self.inputs.shape) / np.float32(self.output_scale)
        self.samples = len(self.inputs)
        self.patch = settings.patch_size or dataset.spec["tile_size"]
        # cached on the device once (on the CPU, views of the arrays): a batch is an index, not a copy from the host
        self.inputs_t, self.targets_t = torch.from_numpy(self.inputs).to(device), torch.from_numpy(self.targets).to(device)

    def network(self):
        return build_network(self.settings.preset)

    def batch(self, order: np.ndarray, rng: np.random.Generator, device) -> tuple[torch.Tensor, tuple]:
        size = self.inputs.shape[-1]
        index = np.sort(order)
        r0, c0 = (rng.integers(0, size - self.patch + 1, 2) if self.patch < size else (0, 0))
        index = torch.from_numpy(index).to(device)
        x = self.inputs_t[index, r0 : r0 + self.patch, c0 : c0 + self.patch][:, None]
        y = self.targets_t[index, r0 : r0 + self.patch, c0 : c0 + self.patch][:, None]
        return x.contiguous(memory_format=torch.channels_last), (y,)

    def loss(self, prediction: torch.Tensor, targets: tuple) -> torch.Tensor:
        (y,) = targets
        weight = 1.0 + (self.settings.foreground_weight - 1.0) * (y > 0).float()
        return torch.mean(weight * (prediction - y) ** 2)

    def validate(self, network, groups: list[int], stop: StopCallback) -> dict | None:
        config = self.dataset.config
        totals = {fraction: {"tp": 0, "fp": 0, "fn": 0} for fraction in THRESHOLD_FRACTIONS}
        squared, count = 0.0, 0
        for group in groups:
            if stop():
                return None
            inputs, labels, description = self.dataset.read_group(group)
            outputs = network_outputs(network, inputs, output_scale=self.output_scale)
            squared += float(np.sum(((outputs - labels) / self.output_scale) ** 2))
            count += labels.size
            truth = {key: np.asarray(values) for key, values in description["particles"].items()}
            for fraction in THRESHOLD_FRACTIONS:
                linker = PlaneLinker(self.dataset.planes_um, pixel_um=config.optics.pixel_um, threshold=fraction * self.full_value, full_value=self.full_value, merge_lateral_um=merge_lateral_um(config))
                for plane, output in enumerate(outputs):
                    linker.add(plane, output)
                metrics = score_particles(linker.particles(), truth)
                for key in ("tp", "fp", "fn"):
                    totals[fraction][key] += metrics[key]
        by_threshold = [{"threshold": fraction * self.full_value, **_metrics(t)} for fraction, t in totals.items()]
        best = max(by_threshold, key=lambda m: (m["ji"], m["er"]))
        return {"loss": squared / max(count, 1), **best, "by_threshold": by_threshold}

    def meta(self) -> dict:
        return {"output_scale": self.output_scale, "full_value": self.full_value, "in_channels": 1, "out_channels": 1}

    @staticmethod
    def decoding(metrics: dict) -> dict:
        return {"threshold": metrics["threshold"]}


class _FocusFormulation:
    """Context planes in; centre heat, depth offset and diameter out (see the module docstring)."""

    name = "focus"

    def __init__(self, dataset: SyntheticDataset, training: list[int], settings: TrainingSettings, device: torch.device = torch.device("cpu")) -> None:
        layout = dataset.layout
        if layout.kind != "stack":
            raise InputError(f"{dataset.path}: the focus formulation needs a data set of the stack layout (generate --layout stack), this one has {layout.kind}")
        self.spec = FocusSpec(context=tuple(int(o) for o in settings.context))
        if self.spec.reach > layout.context_planes:
            raise InputError(f"context: reaches {self.spec.reach} planes, the data set {dataset.path} has {layout.context_planes} context planes")
        config = dataset.config
        self.settings = settings
        self.dataset = dataset
        self.config = config
        self.step_um = config.volume.z_step_um
        self.diameter_scale_um = config.particles.diameter_max_um
        self.margin = layout.context_planes
        self.planes_um = np.asarray(dataset.planes_um)
        self.centres = np.arange(self.margin, len(self.planes_um) - self.margin)
        inputs, _, self.tables = dataset.arrays(training, dtype=np.float16)
        # the stack cached on the device once, in float16 (on the CPU, a view of the array): crops are cut there
        self.stack = torch.from_numpy(inputs).to(device)
        self.size = dataset.spec["tile_size"]
        self.patch = min(settings.patch_size or 128, self.size)
        self.samples = len(training) * len(self.centres)
        self.lateral_um = merge_lateral_um(config)

    def network(self):
        network = build_network(self.settings.preset, in_channels=len(self.spec.context), out_channels=3)
        with torch.no_grad():  # start at a 1 % centre probability (RetinaNet's prior), not 50 %
            network.head.bias[0] = -math.log(99.0)
        return network

    def _draw(self, rng: np.random.Generator) -> tuple:
        """One sample's random choices: group, centre plane, crop origin, dihedral turn and flip, augmentation (None or its parameters)."""
        group = int(rng.integers(len(self.tables)))
        table = self.tables[group]
        pixel_um = self.config.optics.pixel_um
        if len(table["x_um"]) and rng.random() < 0.5:  # a particle at or near its focal plane
            k = int(rng.integers(len(table["x_um"])))
            nearest = int(np.argmin(np.abs(self.planes_um - table["z_um"][k])))
            jitter = 0 if rng.random() < 0.5 else int(rng.choice([-3, -2, -1, 1, 2, 3]))
            centre = int(np.clip(nearest + jitter, self.centres[0], self.centres[-1]))
            row, col = int(round(table["y_um"][k] / pixel_um)), int(round(table["x_um"][k] / pixel_um))
            r0 = int(np.clip(row - rng.integers(8, self.patch - 8), 0, self.size - self.patch))
            c0 = int(np.clip(col - rng.integers(8, self.patch - 8), 0, self.size - self.patch))
        else:
            centre = int(rng.choice(self.centres))
            r0, c0 = (int(v) for v in rng.integers(0, self.size - self.patch + 1, 2))
        turns, flip = int(rng.integers(4)), bool(rng.integers(2))  # the physics has no preferred lateral direction
        augment = None
        if self.settings.augment and rng.random() < 0.5:
            # gamma, contrast about the mean, noise level, 8-bit quantisation
            augment = (np.exp(rng.uniform(-0.3, 0.3)), rng.uniform(0.8, 1.2), rng.uniform(0.0, 0.03), rng.random() < 0.5)
        return group, centre, r0, c0, turns, flip, augment

    def batch(self, order: np.ndarray, rng: np.random.Generator, device) -> tuple[torch.Tensor, tuple]:
        """A batch of crops and their targets, assembled on ``device`` from the cached stack (the host only draws the choices)."""
        draws = [self._draw(rng) for _ in range(len(order))]
        noise_seed = int(rng.integers(2**62))
        group, centre, r0, c0, turns, flip, _ = (np.array(v) for v in zip(*[d[:6] + (0,) for d in draws], strict=True))
        p, count = self.patch, len(draws)
        marks = [focus_marks(self.tables[g], plane_um=float(self.planes_um[c]), step_um=self.step_um, pixel_um=self.config.optics.pixel_um, shape=(p, p),
                             origin_px=(int(r), int(col)), diameter_scale_um=self.diameter_scale_um, spec=self.spec)
                 for g, c, r, col in zip(group, centre, r0, c0, strict=True)]
        x = dihedral_crops(self.stack, group * self.stack.shape[1], context_indices(centre, self.spec.context, len(self.planes_um)), r0, c0, turns, flip,
                           size=p, device=device)
        maps = dihedral_crops(render_marks(marks, size=p, device=device), np.arange(count) * 4, np.tile(np.arange(4), (count, 1)), np.zeros(count, np.int64),
                              np.zeros(count, np.int64), turns, flip, size=p, device=device)
        augmented = [i for i, d in enumerate(draws) if d[6] is not None]
        if augmented:
            parameters = np.array([draws[i][6] for i in augmented], np.float64).astype(np.float32)
            x[augmented] = augment_planes(x[augmented], torch.from_numpy(parameters).to(device), seed=noise_seed)
        return x.contiguous(memory_format=torch.channels_last), tuple(maps.unbind(1))

    def loss(self, prediction: torch.Tensor, targets: tuple) -> torch.Tensor:
        heat, offset, diameter, positive = targets
        # masks, not boolean indexing: the loss has the same shape whatever the batch holds, so the
        # host never waits for the device to count its particles
        positive = positive > 0
        zero = torch.zeros((), dtype=torch.float32, device=prediction.device)
        logit = prediction[:, 0].float()
        log_p, log_not_p = torch.nn.functional.logsigmoid(logit), torch.nn.functional.logsigmoid(-logit)
        p = torch.sigmoid(logit)
        positive_loss = -torch.where(positive, (1 - p) ** _FOCAL_ALPHA * log_p, zero).sum()
        negative_loss = -torch.where(positive, zero, (1 - heat) ** _FOCAL_BETA * p**_FOCAL_ALPHA * log_not_p).sum()
        count = positive.sum().clamp(min=1)
        offset_l1 = torch.where(positive, (prediction[:, 1].float() - offset).abs(), zero).sum()
        diameter_l1 = torch.where(positive, (torch.nn.functional.softplus(prediction[:, 2].float()) - diameter).abs(), zero).sum()
        # with no particle in the batch the L1 sums are 0: only the heat is learnt from it
        return (positive_loss + negative_loss + offset_l1 + self.settings.diameter_weight * diameter_l1) / count

    def candidates(self, network, stack: np.ndarray) -> dict[str, np.ndarray]:
        """Decoded candidates of one group's stack (all centre planes)."""
        decoder = PeakDecoder(self.planes_um, pixel_um=self.config.optics.pixel_um, step_um=self.step_um)
        for centre, probability, offset, diameter in focus_maps(network, stack, self.centres, context=self.spec.context, diameter_scale_um=self.diameter_scale_um):
            decoder.add(int(centre), probability, offset, diameter)
        return decoder.candidates()

    def validate(self, network, groups: list[int], stop: StopCallback) -> dict | None:
        settings = [(t, a) for t in FOCUS_THRESHOLDS for a in _AXIAL_PLANES]
        totals = {key: {"tp": 0, "fp": 0, "fn": 0} for key in settings}
        depth_errors = {key: [] for key in settings}
        diameter_errors = {key: [] for key in settings}
        for group in groups:
            if stop():
                return None
            stack, _, description = self.dataset.read_group(group)
            truth = {key: np.asarray(values) for key, values in description["particles"].items()}
            candidates = self.candidates(network, stack)
            for threshold, axial in settings:
                found = suppress(candidates, threshold=threshold, lateral_um=self.lateral_um, axial_um=axial * self.step_um)
                metrics = score_particles(found, truth)
                for key in ("tp", "fp", "fn"):
                    totals[(threshold, axial)][key] += metrics[key]
                depth_errors[(threshold, axial)].extend(depth_errors_um(found, truth))
                diameter_errors[(threshold, axial)].extend(diameter_errors_um(found, truth))
        by_setting = [
            {"threshold": t, "axial_um": a * self.step_um if a < 1e5 else None, **_metrics(totals[(t, a)]),
             "median_abs_dz_um": float(np.median(np.abs(depth_errors[(t, a)]))) if depth_errors[(t, a)] else None,
             "median_abs_dd_um": float(np.median(np.abs(diameter_errors[(t, a)]))) if diameter_errors[(t, a)] else None}
            for t, a in settings
        ]
        best = max(by_setting, key=lambda m: (m["ji"], m["er"], -(m["axial_um"] or 1e9)))
        return {**best, "by_threshold": by_setting}

    def meta(self) -> dict:
        return {
            "in_channels": len(self.spec.context),
            "out_channels": 3,
            "context": list(self.spec.context),
            "step_um": self.step_um,
            "diameter_scale_um": self.diameter_scale_um,
            "lateral_um": self.lateral_um,
        }

    @staticmethod
    def decoding(metrics: dict) -> dict:
        return {"threshold": metrics["threshold"], "axial_um": metrics["axial_um"]}


def _save_state(path: Path, network, optimizer, schedule, *, epoch: int, log: dict, rng: np.random.Generator) -> None:
    buffer = io.BytesIO()
    torch.save({
        "state_dict": {k: v.detach().cpu() for k, v in network.state_dict().items()},
        "optimizer": optimizer.state_dict(),
        "schedule": schedule.state_dict(),
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
    groups = list(dataset.groups)
    n_validation = settings.validation_groups or max(1, len(groups) // 8)
    if len(groups) < n_validation + 1:
        raise InputError(f"{dataset.path}: expected at least {n_validation + 1} groups (training + {n_validation} for validation), got {len(groups)}")
    validation, training = groups[-n_validation:], groups[:-n_validation]
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
    if resume and state_path.is_file():
        state = load_resume_state(state_path)  # corrupt, foreign or code-carrying files are refused, naming the file
        check_resume_matches(state, log, name=str(state_path), free=("epochs", "minutes", "patience", "validate_last"))
        previous = json.loads(state["log"])
        network.load_state_dict(state["state_dict"])
        optimizer.load_state_dict(state["optimizer"])
        rng.bit_generator.state = json.loads(state["numpy_rng"])
        torch.set_rng_state(state["torch_rng"])
        schedule.load_state_dict(state["schedule"])
        first_epoch = int(state["epoch"])
        log = previous | {"settings": log["settings"]}

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
        score = (validation_metrics["ji"], validation_metrics["er"])
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
        _save_state(state_path, network, optimizer, schedule, epoch=epoch, log=log, rng=rng)
        if out_of_patience():
            log["early_stop"] = f"no better validation JI for {settings.patience} epochs"
            break

    log["stopped"] = stopped
    log["seconds"] = round(time.perf_counter() - start, 2)
    log["planes_per_second"] = round(steps.done * settings.batch_size / max(batch_seconds, 1e-9), 2)
    write_json(log_path, log)
    if log["best"] is None:
        done = len(log["epochs"])
        kept = f"; {state_path.name} holds epoch {log['epochs'][-1]['epoch']} (train again with resume to go on)" if done else ""
        raise Stopped(f"training stopped before any epoch was validated: no model written{kept}")
    return TrainingResult(out, log, stopped)
