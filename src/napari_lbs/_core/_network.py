"""The seed's modified U-Net (Sec. 2.3, Fig. 4) and the model file that carries it.

Presets
-------
``paper``
    VGG-style encoder 64-128-256-512-512 (two 3x3 convolutions with batch norm and ReLU per
    level, 2x2 max pooling between levels), a decoder that up-samples (nearest, as Keras'
    ``UpSampling2D``) and concatenates the encoder's skip connection at every level, and a
    1x1 convolution to one output channel. Trained with MSE and Adam, as the seed.
``small``
    The same shape with an eighth of the channels, 8-16-32-64-64: trains on a CPU in minutes
    and predicts a 256² plane in about 25 ms on two cores.

Both are fully convolutional: any input size works (inputs are padded by edge replication to
a multiple of 2^(levels-1) and the output is cropped back), so a network trained on 256²
tiles or on smaller patches runs on any tile.

Model file (``.pt``): a plain dict of tensors and strings,
``{"format", "version", "state_dict", "meta"}`` with ``meta`` a JSON string (preset, tile size,
config, input processing, output scale, detection settings, training summary). It is read
with ``torch.load(..., weights_only=True)``: loading never executes code.

This module imports torch; `napari_lbs._core` imports it lazily.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from napari_lbs._core._config import ExperimentConfig
from napari_lbs._core._io import InputError, atomic_write_bytes

__all__ = ["PRESETS", "UNet", "build_network", "save_model", "load_model", "LoadedModel", "resolve_device", "check_model_matches", "network_outputs", "MODEL_FORMAT"]

MODEL_FORMAT = "napari-lbs-model"
_MODEL_VERSION = 1
PRESETS: dict[str, tuple[int, ...]] = {"paper": (64, 128, 256, 512, 512), "small": (8, 16, 32, 64, 64)}


def _conv_block(in_channels: int, out_channels: int) -> nn.Sequential:
    layers = []
    for channels in (in_channels, out_channels):
        layers += [nn.Conv2d(channels, out_channels, 3, padding=1, bias=False), nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class UNet(nn.Module):
    """U-Net with ``widths[i]`` channels at level ``i``; one input and one output channel."""

    def __init__(self, widths: tuple[int, ...]) -> None:
        super().__init__()
        if len(widths) < 2:
            raise InputError(f"widths: expected at least two levels, got {widths}")
        self.widths = tuple(int(w) for w in widths)
        self.encoder = nn.ModuleList(_conv_block(c_in, c_out) for c_in, c_out in zip((1,) + self.widths[:-1], self.widths, strict=True))
        self.decoder = nn.ModuleList(_conv_block(self.widths[i + 1] + self.widths[i], self.widths[i]) for i in reversed(range(len(self.widths) - 1)))
        self.head = nn.Conv2d(self.widths[0], 1, 1)
        self.pool = nn.MaxPool2d(2)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows, cols = x.shape[-2:]
        multiple = 2 ** (len(self.widths) - 1)
        pad_rows, pad_cols = -rows % multiple, -cols % multiple
        if pad_rows or pad_cols:
            x = nn.functional.pad(x, (0, pad_cols, 0, pad_rows), mode="replicate")
        skips = []
        for level, block in enumerate(self.encoder):
            x = block(x if level == 0 else self.pool(x))
            skips.append(x)
        for block, skip in zip(self.decoder, reversed(skips[:-1]), strict=True):
            x = block(torch.cat([self.up(x), skip], dim=1))
        return self.head(x)[..., :rows, :cols]


def build_network(preset: str) -> UNet:
    """A fresh network of a preset (``paper`` or ``small``)."""
    if preset not in PRESETS:
        raise InputError(f"preset: expected one of {', '.join(PRESETS)}, got {preset!r}")
    # channels-last runs the convolutions about twice as fast on CPU (oneDNN)
    return UNet(PRESETS[preset]).to(memory_format=torch.channels_last)


def resolve_device(device: str) -> torch.device:
    """``auto`` → CUDA when available, else CPU; ``cuda`` without a GPU is an error."""
    if device not in ("auto", "cpu", "cuda"):
        raise InputError(f"device: expected auto, cpu or cuda, got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise InputError("device: cuda requested but no CUDA GPU is available (use --device cpu or auto)")
    return torch.device("cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available()) else "cpu")


@dataclass
class LoadedModel:
    """A network ready for inference with its description and file hash."""

    network: UNet
    meta: dict
    sha256: str
    path: Path | None = None

    @property
    def config(self) -> ExperimentConfig:
        return ExperimentConfig.from_dict(self.meta["config"])


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
    if not isinstance(payload, dict) or payload.get("format") != MODEL_FORMAT or payload.get("version") != _MODEL_VERSION:
        raise InputError(f"{path}: expected a {MODEL_FORMAT} version {_MODEL_VERSION} file")
    meta = json.loads(payload["meta"])
    network = UNet(tuple(meta["widths"])).to(memory_format=torch.channels_last)
    try:
        network.load_state_dict(payload["state_dict"])
    except RuntimeError as error:
        raise InputError(f"{path}: weights do not fit the {meta.get('preset')} network ({str(error).splitlines()[0]})") from None
    network.to(resolve_device(device)).eval()
    return LoadedModel(network, meta, hashlib.sha256(data).hexdigest(), path)


def check_model_matches(meta: dict, config: ExperimentConfig, *, planes_um) -> None:
    """Refuse a model trained for other optics, another tile size or depths outside its training range.

    Raises
    ------
    InputError
        Naming the first mismatch, e.g. ``model: trained for optics.wavelength_um=0.532, the config says 0.66``.
    """
    trained = ExperimentConfig.from_dict(meta["config"])
    for key in ("wavelength_um", "pixel_um", "medium_index"):
        a, b = getattr(trained.optics, key), getattr(config.optics, key)
        if not math.isclose(a, b, rel_tol=1e-6):
            raise InputError(f"model: trained for optics.{key}={a:g}, the config says {b:g}; train a model for these optics")
    if trained.tile.size != config.tile.size:
        raise InputError(f"model: trained for tile.size={trained.tile.size}, the config says {config.tile.size}")
    layers = meta["planes_um"]
    step = (max(layers) - min(layers)) / max(len(layers) - 1, 1)
    low, high = min(layers) - step, max(layers) + step
    outside = [z for z in planes_um if not low <= z <= high]
    if outside:
        raise InputError(f"volume: depths {outside[0]:g} um and beyond lie outside the model's training range {min(layers):g}-{max(layers):g} um")


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
