"""The U-Net (the seed's, Sec. 2.3, Fig. 4, and its multi-plane variant) and the model file that carries it.

Two formulations share the network body:

``seed``
    one reconstruction plane in, one label plane out (3x3 squares of 4 x diameter), MSE.
``focus``
    the planes around a depth in (``context`` offsets, as channels: the network sees how a
    particle's image changes through focus), and three maps out for the centre plane: a
    particle-centre logit, the sub-plane depth offset and the diameter (see `_heatmaps`).

Presets
-------
``paper``
    VGG-style encoder 64-128-256-512-512 (two 3x3 convolutions with batch norm and ReLU per
    level, 2x2 max pooling between levels), a decoder that up-samples (nearest, as Keras'
    ``UpSampling2D``) and concatenates the encoder's skip connection at every level, and a
    1x1 convolution to one output channel. Trained with MSE and Adam, as the seed.
``medium``
    A quarter of the channels, 16-32-64-128-128 (1.2 M parameters).
``small``
    The same shape with an eighth of the channels, 8-16-32-64-64: trains on a CPU in minutes
    and predicts a 256² plane in about 25 ms on two cores.

Both are fully convolutional: any input size works (inputs are padded by edge replication to
a multiple of 2^(levels-1) and the output is cropped back), so a network trained on 256²
tiles or on smaller patches runs on any tile.

Model file (``.pt``): a plain dict of tensors and strings,
``{"format", "version", "state_dict", "meta"}`` with ``meta`` a JSON string (formulation,
preset, channels, tile size, config, input processing, detection settings, training summary).
It is read with ``torch.load(..., weights_only=True)``: loading never executes code. Version
1 files (before the ``focus`` formulation) load as the ``seed`` formulation they are.

This module imports torch; `napari_lbs._core` imports it lazily.
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.learning._heatmaps import context_indices
from napari_lbs._core.foundation import atomic_write_bytes
from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import check_model_payload

__all__ = ["PRESETS", "FORMULATIONS", "UNet", "build_network", "save_model", "load_model", "LoadedModel", "resolve_device", "resolve_precision", "PRECISIONS", "weights_sha256", "check_model_matches", "model_mismatches", "network_outputs", "focus_maps", "inference_network", "MODEL_FORMAT"]

MODEL_FORMAT = "napari-lbs-model"
_MODEL_VERSION = 2
_READABLE_VERSIONS = (1, 2)
PRESETS: dict[str, tuple[int, ...]] = {"paper": (64, 128, 256, 512, 512), "medium": (16, 32, 64, 128, 128), "small": (8, 16, 32, 64, 64)}
FORMULATIONS = ("focus", "seed")
PRECISIONS = ("auto", "float32", "bfloat16")


def _conv_block(in_channels: int, out_channels: int) -> nn.Sequential:
    layers = []
    for channels in (in_channels, out_channels):
        layers += [nn.Conv2d(channels, out_channels, 3, padding=1, bias=False), nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class UNet(nn.Module):
    """U-Net with ``widths[i]`` channels at level ``i``, ``in_channels`` inputs and ``out_channels`` outputs."""

    def __init__(self, widths: tuple[int, ...], *, in_channels: int = 1, out_channels: int = 1) -> None:
        super().__init__()
        if len(widths) < 2:
            raise InputError(f"widths: expected at least two levels, got {widths}")
        self.widths = tuple(int(w) for w in widths)
        self.encoder = nn.ModuleList(_conv_block(c_in, c_out) for c_in, c_out in zip((int(in_channels),) + self.widths[:-1], self.widths, strict=True))
        self.decoder = nn.ModuleList(_conv_block(self.widths[i + 1] + self.widths[i], self.widths[i]) for i in reversed(range(len(self.widths) - 1)))
        self.head = nn.Conv2d(self.widths[0], int(out_channels), 1)
        self.pool = nn.MaxPool2d(2)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        # a run-time choice (`resolve_precision`), not part of the model: weights stay float32
        self.precision = "float32"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows, cols = x.shape[-2:]
        multiple = 2 ** (len(self.widths) - 1)
        pad_rows, pad_cols = -rows % multiple, -cols % multiple
        if pad_rows or pad_cols:
            x = nn.functional.pad(x, (0, pad_cols, 0, pad_rows), mode="replicate")
        # The first convolution in float32: bfloat16's 8-bit mantissa would round the input planes
        # (values in [0, 1]) to about their 8-bit steps, and the small differences between
        # context planes with them. It is 5 % of the small network's multiplications.
        x = self.encoder[0][0](x)
        skips = []
        with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=self.precision == "bfloat16"):
            for level, block in enumerate(self.encoder):
                x = block[1:](x) if level == 0 else block(self.pool(x))
                skips.append(x)
            for block, skip in zip(self.decoder, reversed(skips[:-1]), strict=True):
                x = block(torch.cat([self.up(x), skip], dim=1))
        # the 1x1 head in float32: the maps' values (depth offsets, diameters) keep full precision
        return self.head(x.float())[..., :rows, :cols]


def build_network(preset: str, *, in_channels: int = 1, out_channels: int = 1) -> UNet:
    """A fresh network of a preset (``paper``, ``medium`` or ``small``)."""
    if preset not in PRESETS:
        raise InputError(f"preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
    # channels-last runs the convolutions about twice as fast on CPU (oneDNN)
    return UNet(PRESETS[preset], in_channels=in_channels, out_channels=out_channels).to(memory_format=torch.channels_last)


def resolve_device(device: str) -> torch.device:
    """``auto`` → CUDA when available, else CPU; ``cuda`` without a GPU is an error."""
    if device not in ("auto", "cpu", "cuda"):
        raise InputError(f"device: expected auto, cpu or cuda, got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise InputError("device: cuda requested but no CUDA GPU is available (use --device cpu or auto)")
    return torch.device("cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available()) else "cpu")


def _native_bfloat16(device: torch.device) -> bool:
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    # oneDNN runs bfloat16 convolutions on AMX tiles or AVX-512 BF16 instructions; without them it emulates (slower than float32)
    cpu = torch.cpu
    return torch.backends.mkldnn.is_available() and any(getattr(cpu, probe, lambda: False)() for probe in ("_is_amx_tile_supported", "_is_avx512_bf16_supported"))


def resolve_precision(precision: str, device: torch.device) -> str:
    """The network's arithmetic on ``device``: ``float32`` or ``bfloat16``.

    ``bfloat16`` runs the convolutions (and the layers between them) in bfloat16 with float32
    weights, optimiser and loss (``torch.autocast``), and the output layer in float32. ``auto``
    is ``bfloat16`` where the device multiplies it natively (CPUs with AMX or AVX-512 BF16,
    CUDA GPUs that support it) and ``float32`` elsewhere, where bfloat16 is emulated and slower.
    On a 2-core AMX CPU the ``small`` network's training epochs ran 1.6x and its prediction
    2.2x faster in bfloat16.

    Results are reproducible for one precision on one kind of machine; the precision used is
    recorded in training logs, model files and prediction provenance.
    """
    if precision not in PRECISIONS:
        raise InputError(f"precision: expected one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision != "auto":
        return precision
    return "bfloat16" if _native_bfloat16(device) else "float32"


@dataclass(frozen=True)
class LoadedModel:
    """A network ready for inference with its description and file hash."""

    network: UNet
    meta: dict
    sha256: str
    path: Path | None = None
    weights_sha256: str = ""  # `weights_sha256` of ``network``, computed when not given

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights_sha256", self.weights_sha256 or weights_sha256(self.network))  # frozen: set once, here

    @property
    def config(self) -> ExperimentConfig:
        return ExperimentConfig.from_dict(self.meta["config"])

    @property
    def formulation(self) -> str:
        return self.meta.get("formulation", "seed")


def weights_sha256(network: UNet) -> str:
    """SHA-256 of a network's weights alone: each tensor's name, shape and values, in order.

    The model file's hash (`save_model`) also covers its metadata, which records where the
    data set was; two trainings with the same seed and the same weights in different folders
    have the same weights hash and different file hashes.
    """
    digest = hashlib.sha256()
    for name, value in network.state_dict().items():
        digest.update(f"{name}{tuple(value.shape)}".encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def _model_bytes(network: UNet, meta: dict) -> bytes:
    state = {key: value.detach().cpu() for key, value in network.state_dict().items()}
    buffer = io.BytesIO()
    torch.save({"format": MODEL_FORMAT, "version": _MODEL_VERSION, "state_dict": state, "meta": json.dumps(meta)}, buffer)
    return buffer.getvalue()


def save_model(path: str | Path, network: UNet, meta: dict) -> str:
    """Write a model file atomically; return its SHA-256."""
    data = _model_bytes(network, meta)
    atomic_write_bytes(Path(path), data)
    return hashlib.sha256(data).hexdigest()


def load_model(path: str | Path, *, device: str = "cpu") -> LoadedModel:
    """Read a model file without executing code (``weights_only=True``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: model file not found")
    data = path.read_bytes()
    try:
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as error:  # pickles with code, truncated files, other formats: all refused the same way
        raise InputError(f"{path}: not a napari-lbs model file ({type(error).__name__})") from None
    # format, widths (a preset's, so nothing huge is allocated), channels and config before any network is built
    meta = check_model_payload(payload, name=str(path), formats={MODEL_FORMAT: _READABLE_VERSIONS}, presets=PRESETS, formulations=FORMULATIONS)
    state = payload["state_dict"]
    # a network with NaN or infinite weights outputs NaN, which no threshold passes: it would report "0 particles"
    damaged = [name for name, tensor in state.items() if torch.is_tensor(tensor) and tensor.is_floating_point() and not bool(torch.isfinite(tensor).all())] if isinstance(state, dict) else []
    if damaged:
        raise InputError(f"{path}: weights {damaged[0]} hold NaN or infinite values ({len(damaged)} tensors); the model file is damaged (train it again)")
    network = UNet(tuple(meta["widths"]), in_channels=meta["in_channels"], out_channels=meta["out_channels"]).to(memory_format=torch.channels_last)
    try:
        network.load_state_dict(state)
    except RuntimeError as error:
        raise InputError(f"{path}: weights do not fit the {meta.get('preset')} network ({str(error).splitlines()[0]})") from None
    network.to(resolve_device(device)).eval()
    return LoadedModel(network, meta, hashlib.sha256(data).hexdigest(), path)


def inference_network(network: UNet) -> UNet:
    """A copy of ``network`` for inference: each convolution with its batch norm folded in, in eval mode.

    Folding (``torch.nn.utils.fusion.fuse_conv_bn_eval``: the norm's scale and shift become the
    convolution's weights and bias) leaves the outputs equal to float rounding and saves a pass
    over every activation: 12 % of the ``small`` network's time on 2 CPU cores. The original,
    with its batch-norm layers, stays as it is (it is what model files store).
    """
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    fused = copy.deepcopy(network).eval()
    for block in fused.modules():
        if isinstance(block, nn.Sequential):
            for i in range(len(block) - 1):
                if isinstance(block[i], nn.Conv2d) and isinstance(block[i + 1], nn.BatchNorm2d):
                    block[i], block[i + 1] = fuse_conv_bn_eval(block[i], block[i + 1]), nn.Identity()
    return fused


def model_mismatches(meta: dict, config: ExperimentConfig, *, planes_um, setup: str = "the config") -> list[str]:
    """Where a model's setup differs from a hologram's: its optics (wavelength, pixel, medium) and depths outside its training range.

    Parameters
    ----------
    meta : dict
        The model's metadata (`LoadedModel.meta`).
    config : ExperimentConfig
        The hologram's setup.
    planes_um : sequence of float
        The depths to reconstruct (µm).
    setup : str
        What ``config`` is called in the lines (e.g. "the hologram" when its pixel size is the layer's).

    Returns
    -------
    list of str
        One line per mismatch naming both values, e.g. ``model: trained for
        optics.pixel_um=3.45, the config says 2.2``; empty when the model fits.
    """
    trained = ExperimentConfig.from_dict(meta["config"])
    found = []
    for key in ("wavelength_um", "pixel_um", "medium_index"):
        a, b = getattr(trained.optics, key), getattr(config.optics, key)
        if not math.isclose(a, b, rel_tol=1e-6):
            found.append(f"model: trained for optics.{key}={a:g}, {setup} says {b:g}")
    layers = meta["planes_um"]
    step = (max(layers) - min(layers)) / max(len(layers) - 1, 1)
    low, high = min(layers) - step, max(layers) + step
    outside = [z for z in planes_um if not low <= z <= high]
    if outside:
        found.append(f"volume: depths {outside[0]:g} µm and beyond lie outside the model's training range {min(layers):g}-{max(layers):g} µm")
    return found


def check_model_matches(meta: dict, config: ExperimentConfig, *, planes_um, force: bool = False) -> None:
    """Refuse a model for another tile size, and unless ``force``, one for other optics or depths (`model_mismatches`).

    Raises
    ------
    InputError
        Naming the first mismatch, e.g. ``model: trained for optics.wavelength_um=0.532, the config says 0.66``.
    """
    trained = ExperimentConfig.from_dict(meta["config"])
    if trained.tile.size != config.tile.size:
        raise InputError(f"model: trained for tile.size={trained.tile.size}, the config says {config.tile.size}")
    found = [] if force else model_mismatches(meta, config, planes_um=planes_um)
    if found:
        raise InputError(f"{found[0]}; train a model for this setup, or run it anyway (--force)")


def network_outputs(network: UNet, planes: np.ndarray, *, output_scale: float, batch_size: int = 8) -> np.ndarray:
    """Run ``network`` (in eval mode, on its own device) on ``(n, rows, cols)`` input planes; outputs in label units, float32."""
    network.eval()
    device = next(network.parameters()).device
    outputs = np.empty(planes.shape, np.float32)
    with torch.inference_mode():
        for start in range(0, len(planes), batch_size):
            batch = torch.from_numpy(np.ascontiguousarray(planes[start : start + batch_size], dtype=np.float32))[:, None]
            batch = batch.to(device).contiguous(memory_format=torch.channels_last)
            outputs[start : start + batch_size] = network(batch)[:, 0].float().cpu().numpy() * output_scale
    return outputs


def focus_maps(network: UNet, stack: np.ndarray, centres, *, context, diameter_scale_um: float, batch_size: int = 8):
    """Run a ``focus`` network on the centre planes of a normalised stack.

    Parameters
    ----------
    network : UNet
        Three output channels (centre logit, depth offset in planes, diameter / scale).
    stack : (planes, rows, cols) array
        Input planes as the network sees them (normalised, [0, 1]); any float dtype.
    centres : sequence of int
        Indices of the planes to decode; each needs its whole ``context`` inside the stack.
    context : sequence of int
        Plane offsets fed as channels.
    diameter_scale_um : float
        Multiplies the diameter channel.

    Yields
    ------
    (centre, probability, offset, diameter_um) for each centre in order, float32 ``(rows, cols)``.
    """
    network.eval()
    device = next(network.parameters()).device
    centres = list(centres)
    indices = context_indices(centres, context, len(stack))
    with torch.inference_mode():
        for start in range(0, len(centres), batch_size):
            batch = torch.from_numpy(np.ascontiguousarray(stack[indices[start : start + batch_size]], dtype=np.float32))
            outputs = network(batch.to(device).contiguous(memory_format=torch.channels_last)).float()
            probability = torch.sigmoid(outputs[:, 0]).cpu().numpy()
            offset = outputs[:, 1].cpu().numpy()
            diameter = (nn.functional.softplus(outputs[:, 2]) * diameter_scale_um).cpu().numpy()
            for k in range(len(probability)):
                yield centres[start + k], probability[k], offset[k], diameter[k]
