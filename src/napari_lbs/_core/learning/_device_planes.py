"""The prediction's reconstruction planes on the network's device: back-propagation with ``torch.fft``.

The angular-spectrum method of `napari_lbs._core.physics.backpropagated_blocks`, with the same
padding (the hologram's border mean, on the grid of `padded_shape`), the same band-limited
transfer functions (`transfer_function`, numpy, each moved to the device once and kept there)
and the FFTs on the device. On a CUDA GPU this takes the back-propagation off the CPU cores;
on the CPU the numpy path (scipy's multi-threaded FFTs and the kernel cache) is what
prediction uses, and this module gives the same planes to float32 rounding.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator, Sequence

import numpy as np
import torch

from napari_lbs._core.foundation import InputError, Steps
from napari_lbs._core.physics import backpropagated_blocks, padded_shape, transfer_function

__all__ = ["device_backpropagated_planes", "backpropagated_planes"]

# Transfer functions kept on each device, by grid, optics and distance (a 1024² hologram's
# 77 kernels on its 1372² grid: 1.1 GiB of complex64).
_KERNEL_BYTES = 2 << 30
_BATCH_BYTES = 512 << 20  # padded planes per batch, as the numpy path
_kernels: OrderedDict[tuple, torch.Tensor] = OrderedDict()


def _device_kernel(grid: tuple[int, int], z_um: float, *, spread_limit_um: float, device: torch.device, **optics) -> torch.Tensor:
    key = (grid, float(z_um), spread_limit_um, str(device), tuple(sorted(optics.items())))
    kernel = _kernels.get(key)
    if kernel is None:
        array = transfer_function(grid, float(z_um), spread_limit_um=spread_limit_um, dtype=np.complex64, cache=False, **optics)
        kernel = torch.from_numpy(np.array(array)).to(device)
        _kernels[key] = kernel
        while sum(k.numel() * k.element_size() for k in _kernels.values()) > _KERNEL_BYTES and len(_kernels) > 1:
            _kernels.popitem(last=False)
    else:
        _kernels.move_to_end(key)
    return kernel


def device_backpropagated_planes(hologram: np.ndarray, z_um: Sequence[float], *, wavelength_um: float, pixel_um: float, medium_index: float = 1.0,
                                 background: np.ndarray | None = None, device: torch.device, steps: Steps | None = None) -> Iterator[tuple[int, int, torch.Tensor]]:
    """Yield ``(start, stop, planes)``: ``|field|`` at depths ``z_um[start:stop]``, float32 ``(stop - start, rows, cols)`` tensors on ``device``.

    The planes of `napari_lbs._core.physics.backpropagate` for a float32 hologram, to float32
    rounding (the FFT library's). ``hologram`` is divided by ``background`` or, without one,
    by its own mean.

    Parameters
    ----------
    hologram : (rows, cols) array
        A checked hologram (finite, positive mean).
    z_um : sequence of float
        Depths (µm, positive).
    wavelength_um, pixel_um, medium_index : float
    background : (rows, cols) array, optional
    device : torch.device
    steps : Steps, optional
        Advanced by each batch's planes and checked before each (a stop raises `Stopped`).
    """
    hologram = np.asarray(hologram)
    distances = -np.asarray(z_um, dtype=np.float64)
    if hologram.ndim != 2 or distances.ndim != 1 or distances.size == 0:
        raise InputError(f"hologram / z_um: expected a 2-D image and a list of depths, got shapes {hologram.shape} / {distances.shape}")
    steps = steps if steps is not None else Steps(distances.size, progress=None, should_stop=None)
    divisor = np.float32(float(hologram.mean())) if background is None else np.asarray(background, np.float32)
    field = hologram.astype(np.float32) / divisor
    rows, cols = field.shape
    optics = {"wavelength_um": wavelength_um, "pixel_um": pixel_um, "medium_index": medium_index}
    grid = padded_shape(field.shape, z_max_um=float(np.max(np.abs(distances))), **optics)
    # as the numpy path: the kernel sampled finely enough and no light wrapping onto the window
    spread_limit_um = min(min(g / 2.0, g - n) for g, n in zip(grid, field.shape, strict=True)) * pixel_um
    border = np.concatenate([field[0], field[-1], field[1:-1, 0], field[1:-1, -1]])
    padded = np.full(grid, complex(border.mean()), dtype=np.complex64)
    padded[:rows, :cols] = field
    spectrum = torch.fft.fft2(torch.from_numpy(padded).to(device))
    batch = max(1, _BATCH_BYTES // (padded.nbytes * 2))
    for start in range(0, distances.size, batch):
        steps.check()
        stop = min(start + batch, distances.size)
        kernels = torch.stack([_device_kernel(grid, z, spread_limit_um=spread_limit_um, device=device, **optics) for z in distances[start:stop]])
        yield start, stop, torch.fft.ifft2(spectrum * kernels)[:, :rows, :cols].abs()
        steps.advance(stop - start)


def backpropagated_planes(hologram: np.ndarray, z_um: Sequence[float], *, wavelength_um: float, pixel_um: float, medium_index: float = 1.0,
                          background: np.ndarray | None = None, device: torch.device, steps: Steps | None = None) -> Iterator[tuple[int, int, np.ndarray]]:
    """Yield ``(start, stop, planes)``: ``|field|`` at depths ``z_um[start:stop]`` as float32 numpy arrays, made where they are fastest.

    On a CUDA device `device_backpropagated_planes` (FFTs on the GPU, the planes copied to
    the host); elsewhere `napari_lbs._core.physics.backpropagated_blocks` (numpy), bit for bit
    the planes of `backpropagate`.
    """
    optics = {"wavelength_um": wavelength_um, "pixel_um": pixel_um, "medium_index": medium_index}
    steps = steps if steps is not None else Steps(len(z_um), progress=None, should_stop=None)
    if device.type == "cuda":
        for start, stop, planes in device_backpropagated_planes(hologram, z_um, background=background, device=device, steps=steps, **optics):
            yield start, stop, planes.cpu().numpy()
        return
    for start, stop, block in backpropagated_blocks(hologram, z_um, background=background, steps=steps, **optics):
        yield start, stop, np.abs(block)
