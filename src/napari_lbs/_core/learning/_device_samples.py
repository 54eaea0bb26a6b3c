"""Training samples assembled where the network runs: crops, dihedral turns, targets and augmentation as a few batched tensor operations.

The host draws each sample's choices (`numpy.random.Generator`, so a seed fixes them on any
device); everything with a pixel count — cutting the crops from the cached stack, turning and
flipping them, drawing the targets' Gaussians, the augmentation's arithmetic and its noise —
runs as tensor operations on the training device, a batch at once, with no copy of image
data between host and device and no wait for the device. On the CPU the same operations run
on the CPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from napari_lbs._core.learning._heatmaps import FocusMarks

__all__ = ["dihedral_crops", "render_marks", "augment_planes"]


def dihedral_crops(source: torch.Tensor, first: np.ndarray, planes: np.ndarray, r0: np.ndarray, c0: np.ndarray, turns: np.ndarray, flip: np.ndarray, *,
                   size: int, device: torch.device) -> torch.Tensor:
    """Square crops of ``source`` turned and flipped as ``np.rot90(crop, turns)[..., ::-1]`` (when ``flip``), float32 ``(B, C, size, size)``.

    Parameters
    ----------
    source : (N, P, rows, cols) tensor on ``device``, contiguous
        Planes of any dtype (the training stack in float16).
    first : (B,) int array
        Flat index ``n * P`` of each crop's first plane.
    planes : (B, C) int array
        Plane indices (0 … P-1) of each crop's channels.
    r0, c0 : (B,) int arrays
        Top-left pixel of each crop.
    turns, flip : (B,) int and bool arrays
        Quarter turns (counter-clockwise, as `numpy.rot90`) and then a left-right flip.
    size : int
    device : torch.device
    """
    rows_total, cols_total = source.shape[-2:]
    count = len(r0)
    choice = torch.from_numpy(np.stack([np.asarray(v, np.int64) for v in (r0, c0, turns, flip)], axis=1)).to(device)
    leading = torch.from_numpy(np.asarray(first, np.int64)[:, None] + np.asarray(planes, np.int64)).to(device)
    axis = torch.arange(size, device=device)
    i = axis.view(1, -1, 1).expand(count, size, size)
    j = torch.where(choice[:, 3].view(-1, 1, 1) > 0, size - 1 - axis, axis).view(count, 1, size).expand(count, size, size)
    # output (i, j) of a counter-clockwise turn by k reads the crop at (seq[k], seq[k + 1]) of this cycle
    cycle = torch.stack([i, j, size - 1 - i, size - 1 - j], dim=1)
    k = choice[:, 2].view(-1, 1, 1, 1).expand(count, 1, size, size)
    row = cycle.gather(1, k)[:, 0] + choice[:, 0].view(-1, 1, 1)
    col = cycle.gather(1, (k + 1) % 4)[:, 0] + choice[:, 1].view(-1, 1, 1)
    index = leading[:, :, None, None] * (rows_total * cols_total) + (row * cols_total + col)[:, None]
    return source.view(-1)[index].float()


def render_marks(marks: Sequence[FocusMarks], *, size: int, device: torch.device) -> torch.Tensor:
    """Dense targets of a batch from its `FocusMarks`: float32 ``(B, 4, size, size)``, channels heat, offset, diameter, positive (0/1)."""
    count, pixels = len(marks), size * size
    base = [b * 4 * pixels for b in range(count)]

    def joined(name: str, dtype, offset: bool) -> np.ndarray:
        return np.concatenate([np.zeros(0, dtype)] + [getattr(m, name).astype(dtype) + (b0 if offset else 0) for m, b0 in zip(marks, base, strict=True)])

    heat_index, peak_index = joined("heat_index", np.int64, True), joined("peak_index", np.int64, True)
    # one copy each of the indices and the values to the device; slices at sizes the host knows
    index = torch.from_numpy(np.concatenate([heat_index, peak_index])).to(device)
    values = torch.from_numpy(np.concatenate([joined(name, np.float32, False) for name in ("heat_value", "offset", "diameter")])).to(device)
    heats, peaks = heat_index.size, peak_index.size
    heat_t, peak_t = index[:heats], index[heats:]
    out = torch.zeros(count * 4 * pixels, dtype=torch.float32, device=device)
    out.scatter_reduce_(0, heat_t, values[:heats], "amax")
    out[peak_t] = 1.0
    out[peak_t + pixels] = values[heats : heats + peaks]
    out[peak_t + 2 * pixels] = values[heats + peaks :]
    out[peak_t + 3 * pixels] = 1.0
    return out.view(count, 4, size, size)


def augment_planes(x: torch.Tensor, parameters: torch.Tensor, *, seed: int) -> torch.Tensor:
    """Gamma, contrast about the mean, Gaussian noise and 8-bit quantisation of ``(n, C, rows, cols)`` planes in [0, 1], kept in [0, 1].

    ``parameters`` (n, 4): gamma, contrast factor, noise level, quantise (0 or 1). The noise
    comes from a generator on the planes' device seeded with ``seed``.
    """
    generator = torch.Generator(device=x.device)
    generator.manual_seed(seed)
    gamma, contrast, sigma, quantise = (parameters[:, k].view(-1, 1, 1, 1) for k in range(4))
    x = x.clamp(0.0, 1.0) ** gamma
    mean = x.mean(dim=(-2, -1), keepdim=True)
    x = mean + contrast * (x - mean)
    x = x + sigma * torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
    x = torch.where(quantise > 0, torch.round(x * 255.0) / 255.0, x)
    return x.clamp(0.0, 1.0)
