"""The settings of a training: formulation, network, schedule, stopping rules, arithmetic, checked when made."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from napari_lbs._core.foundation import InputError
from napari_lbs._core.learning._heatmaps import FocusSpec
from napari_lbs._core.learning._network import FORMULATIONS, PRESETS, resolve_device, resolve_precision

__all__ = ["TrainingSettings", "training_precision"]

_DEFAULT_RATE = {"paper": 3e-4, "medium": 1e-3, "small": 2e-3}


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
        See `napari_lbs._core.learning._formulations`; ``seed`` is the seed paper's, kept for comparison.
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
    average_last : int
        Keep the mean of the last this many epochs' weights (at most all of them) instead of
        the best validated epoch; 0 = off. The mean's batch-norm statistics are measured
        again on training crops, and it is validated for its decoding settings like an
        epoch. Averaging the end of a training finds a flatter optimum (stochastic weight
        averaging: Izmailov et al., UAI 2018): epochs that synthetic validation cannot tell
        apart transfer very differently to holograms of another forward model, and on a
        frozen check their mean scored higher than the validated epoch in 4 of 6 trainings
        and tests and lower in 1, by 0.030, so it is not the default (docs/learning.md). It
        needs the planned epochs: a stop, the ``minutes`` budget or ``patience`` keeps the
        best validated epoch.
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
    average_last: int = 0
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
        if self.minutes < 0 or self.patience < 0 or self.validate_last < 0 or self.average_last < 0:
            raise InputError(f"minutes / patience / validate_last / average_last: expected >= 0, got {self.minutes} / {self.patience} / {self.validate_last} / {self.average_last}")
        FocusSpec(context=tuple(self.context))
        training_precision(self.precision, resolve_device(self.device))

    @property
    def rate(self) -> float:
        return self.learning_rate if self.learning_rate is not None else _DEFAULT_RATE[self.preset]

