"""The training formulations: the network each trains, its batches, its loss and its validation by detection.

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

A formulation validates a network on held-out groups: their outputs go through the same
decoding as any prediction and one-to-one scoring (`score_particles`), at every decoding
setting tried (threshold, and for ``focus`` the axial suppression radius). The kept setting is
the upper edge of the best one's plateau (`_upper_edge`); it is returned with the peak's JI and
the scores of all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from napari_lbs._core.foundation import InputError, StopCallback
from napari_lbs._core.learning._dataset import SyntheticDataset
from napari_lbs._core.learning._detection import PeakDecoder, PlaneLinker, suppress
from napari_lbs._core.learning._device_samples import augment_planes, dihedral_crops, render_marks
from napari_lbs._core.learning._heatmaps import FocusSpec, context_indices, focus_marks
from napari_lbs._core.learning._metrics import depth_errors_um, diameter_errors_um, score_particles
from napari_lbs._core.learning._network import build_network, focus_maps, network_outputs
from napari_lbs._core.learning._training_settings import TrainingSettings
from napari_lbs._core.physics import LABEL_SCALE

__all__ = ["THRESHOLD_FRACTIONS", "FOCUS_THRESHOLDS", "merge_lateral_um"]

# Detection thresholds tried on validation: seed formulation, fractions of the smallest label
# value; focus formulation, every hundredth of a probability from the decoder's floor (0.05):
# a short training's peak scores crowd into a tenth (a microscope network's true peaks lay at
# 0.2-0.3), where a grid of tenths picks its edge and ranks the epochs by it.
THRESHOLD_FRACTIONS = (0.15, 0.25, 0.35, 0.5, 0.65)
FOCUS_THRESHOLDS = tuple(round(0.05 + 0.01 * step, 2) for step in range(91))
# the validation log's table of settings: the thresholds at every twentieth, and the chosen one
_LOGGED_THRESHOLDS = frozenset(round(0.05 * step, 2) for step in range(1, 20))
_AXIAL_PLANES = (2.0, 5.0, 1e6)  # axial suppression radii tried on validation, in planes (1e6: any depth)
_FOCAL_ALPHA, _FOCAL_BETA = 2.0, 4.0


def merge_lateral_um(config) -> float:
    """Detections closer than half the smallest trained diameter are one particle."""
    return 0.5 * config.particles.diameter_min_um


def _at_least(found: dict[str, np.ndarray], threshold: float) -> dict[str, np.ndarray]:
    """The rows of ``found`` scoring at least ``threshold``."""
    keep = found["score"] >= threshold
    return {name: values[keep] for name, values in found.items()}


def _metrics(totals: dict) -> dict:
    n_truth = totals["tp"] + totals["fn"]
    matched = totals["tp"] + totals["fp"] + totals["fn"]
    return {**totals, "er": 1.0 - totals["fn"] / n_truth if n_truth else 1.0, "ji": totals["tp"] / matched if matched else 1.0}


def _upper_edge(ji_by_threshold: Sequence[float], best: int, *, counted: int) -> int:
    """The highest threshold index reached from ``best`` upwards without the JI falling a standard error below it.

    The one-standard-error rule (Hastie, Tibshirani & Friedman, *The Elements of Statistical
    Learning*, 2nd ed., §7.10): of the settings validation cannot tell from the best, the one
    that detects least. Validation is synthetic; a real hologram adds structure the network
    never saw, and its false candidates score in the middle of the range, so the upper edge
    of the validation plateau keeps fewer of them for the same true ones. ``counted`` is the
    best setting's TP + FP + FN; the error is the binomial one of its JI.
    """
    ji = ji_by_threshold[best]
    tolerance = math.sqrt(ji * (1.0 - ji) / counted) if counted else 0.0
    edge = best
    while edge + 1 < len(ji_by_threshold) and ji_by_threshold[edge + 1] >= ji - tolerance:
        edge += 1
    return edge


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
        best = max(range(len(by_threshold)), key=lambda i: (by_threshold[i]["ji"], by_threshold[i]["er"]))
        counted = sum(by_threshold[best][key] for key in ("tp", "fp", "fn"))
        chosen = by_threshold[_upper_edge([m["ji"] for m in by_threshold], best, counted=counted)]
        return {"loss": squared / max(count, 1), **chosen, "peak_threshold": by_threshold[best]["threshold"], "peak_ji": by_threshold[best]["ji"], "by_threshold": by_threshold}

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
        kept_by_group = []
        for group in groups:
            if stop():
                return None
            stack, _, description = self.dataset.read_group(group)
            truth = {key: np.asarray(values) for key, values in description["particles"].items()}
            candidates = self.candidates(network, stack)
            # greedy suppression keeps a candidate whatever scores below it: the detections at a
            # threshold are those at the lowest one that reach it
            kept = {axial: suppress(candidates, threshold=FOCUS_THRESHOLDS[0], lateral_um=self.lateral_um, axial_um=axial * self.step_um) for axial in _AXIAL_PLANES}
            kept_by_group.append((kept, truth))
            for threshold, axial in settings:
                metrics = score_particles(_at_least(kept[axial], threshold), truth)
                for key in ("tp", "fp", "fn"):
                    totals[(threshold, axial)][key] += metrics[key]
        by_setting = [{"threshold": t, "axial_um": a * self.step_um if a < 1e5 else None, **_metrics(totals[(t, a)])} for t, a in settings]

        def rank(i: int) -> tuple:
            return by_setting[i]["ji"], by_setting[i]["er"], -(by_setting[i]["axial_um"] or 1e9)

        peak = max(range(len(settings)), key=rank)
        axial = settings[peak][1]
        # along the peak's suppression radius, the upper edge of the thresholds within a standard error of it
        along = [i for i in range(len(settings)) if settings[i][1] == axial]
        counted = sum(by_setting[peak][key] for key in ("tp", "fp", "fn"))
        best_index = along[_upper_edge([by_setting[i]["ji"] for i in along], along.index(peak), counted=counted)]
        threshold = settings[best_index][0]
        depth_errors, diameter_errors = [], []
        for kept, truth in kept_by_group:
            found = _at_least(kept[axial], threshold)
            depth_errors.extend(depth_errors_um(found, truth))
            diameter_errors.extend(diameter_errors_um(found, truth))
        best = {**by_setting[best_index], "peak_threshold": settings[peak][0], "peak_ji": by_setting[peak]["ji"],
                "median_abs_dz_um": float(np.median(np.abs(depth_errors))) if depth_errors else None,
                "median_abs_dd_um": float(np.median(np.abs(diameter_errors))) if diameter_errors else None}
        logged = [m for i, m in enumerate(by_setting) if settings[i][0] in _LOGGED_THRESHOLDS or settings[i][0] == threshold]
        return {**best, "by_threshold": logged}

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

