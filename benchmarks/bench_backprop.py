"""Back-propagation speed and memory on the seed's real 1024² hologram.

Prints, measured in this run: wall time and peak memory of `backpropagate` for the whole
hologram to 61 planes (1800–4800 µm) and for 16 tiles of 256² x 61 planes; the ratio to the
bare FFT floor (the same number of complex64 inverse FFTs on the same padded grid, alone;
target <= 1.5x) and the speed-up over a naive per-plane loop that rebuilds a complex128 kernel
for each plane (what the seed's code and PyHoloscope do; target >= 5x); and the cold cost of
the 61 transfer functions, built on the non-negative quarter of the frequencies and mirrored
(`transfer_function`) against phase, cos and sin at every frequency (the previous build).

Run: python benchmarks/bench_backprop.py
"""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import scipy.fft

from napari_lbs._core import backpropagate, load_config, load_sample_hologram
from napari_lbs._core.physics._optics import _phase_rate, padded_shape, set_transfer_cache_limit, transfer_function
from napari_lbs._core.foundation._threads import process_threads

CONFIG = load_config(None)
OPTICS = {"wavelength_um": CONFIG.optics.wavelength_um, "pixel_um": CONFIG.optics.pixel_um}
Z_UM = np.asarray(CONFIG.volume.planes_um())


def timed(function, repeats=3):
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def peak_mib(function):
    tracemalloc.start()
    function()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def fft_floor(shape, planes):
    grid = padded_shape(shape, z_max_um=Z_UM.max(), **OPTICS)
    block = (np.random.default_rng(0).random((min(planes, 8),) + grid) + 0j).astype(np.complex64)

    def run():
        for start in range(0, planes, block.shape[0]):
            scipy.fft.ifft2(block[: min(block.shape[0], planes - start)], axes=(-2, -1), workers=process_threads(), overwrite_x=False)

    return run


def naive(hologram):
    """Per plane: rebuild a complex128 kernel, one complex128 FFT pair (same padded grid)."""
    grid = padded_shape(hologram.shape, z_max_um=Z_UM.max(), **OPTICS)
    lam, pixel = OPTICS["wavelength_um"], OPTICS["pixel_um"]

    def run():
        padded = np.full(grid, hologram.mean(), dtype=np.complex128)
        padded[: hologram.shape[0], : hologram.shape[1]] = hologram
        out = np.empty((Z_UM.size,) + hologram.shape, np.float32)
        for i, z in enumerate(Z_UM):
            fy = np.fft.fftfreq(grid[0], pixel)[:, None]
            fx = np.fft.fftfreq(grid[1], pixel)[None, :]
            kernel = np.exp(-1j * 2 * np.pi * z * np.sqrt(np.maximum(1 / lam**2 - fx**2 - fy**2, 0)))
            out[i] = np.abs(np.fft.ifft2(np.fft.fft2(padded) * kernel))[: hologram.shape[0], : hologram.shape[1]]
        return out

    return run


def kernels(grid, *, mirrored: bool):
    """The 61 kernels of a cold scan: `transfer_function` (mirrored) or phase, cos and sin at every frequency."""
    rate = _phase_rate(grid, OPTICS["wavelength_um"], OPTICS["pixel_um"], 1.0)[0]

    def every_frequency():
        for z in -Z_UM:
            phase = rate * z
            phase -= 2.0 * np.pi * np.round(phase / (2.0 * np.pi))
            phase = phase.astype(np.float32)
            kernel = np.empty(grid, np.complex64)
            np.cos(phase, out=kernel.real)
            np.sin(phase, out=kernel.imag)
            kernel[np.isnan(rate)] = 0.0

    def quarter():
        for z in -Z_UM:
            transfer_function(grid, float(z), **OPTICS, cache=False)

    return quarter if mirrored else every_frequency


def main():
    hologram = load_sample_hologram()
    tiles = [hologram[r : r + 256, c : c + 256] for r in range(0, 1024, 256) for c in range(0, 1024, 256)]
    whole = lambda: backpropagate(hologram, Z_UM, **OPTICS)  # noqa: E731
    tiled = lambda: [backpropagate(t, Z_UM, **OPTICS) for t in tiles]  # noqa: E731

    set_transfer_cache_limit(0)
    cold = timed(whole, repeats=1)
    set_transfer_cache_limit(2 * 2**30)
    whole()  # fill the cache
    rows = []
    t_whole, t_floor = timed(whole), timed(fft_floor(hologram.shape, Z_UM.size))
    t_naive = timed(naive(hologram), repeats=1)
    tiled()
    t_tiled, t_tiled_floor = timed(tiled), timed(fft_floor((256, 256), 16 * Z_UM.size))
    m_whole, m_tiled = peak_mib(whole), peak_mib(tiled)
    grid = padded_shape(hologram.shape, z_max_um=Z_UM.max(), **OPTICS)
    tile_grid = padded_shape((256, 256), z_max_um=Z_UM.max(), **OPTICS)
    rows.append(f"1024² x 61 planes (padded {grid[0]}²): {t_whole:.2f} s warm, {cold:.2f} s cold (kernels built), peak {m_whole:.0f} MiB (output {hologram.size * 61 * 4 / 2**20:.0f} MiB)")
    rows.append(f"  ratio to bare complex64 IFFT floor ({t_floor:.2f} s): {t_whole / t_floor:.2f}x   (target <= 1.5x)")
    rows.append(f"  speed-up over naive per-plane complex128 loop ({t_naive:.2f} s): {t_naive / t_whole:.1f}x   (target >= 5x)")
    t_quarter, t_every = timed(kernels(grid, mirrored=True)), timed(kernels(grid, mirrored=False))
    rows.append(f"  the 61 kernels of a cold scan: {t_quarter:.2f} s mirrored from the quarter, {t_every:.2f} s at every frequency: {t_every / t_quarter:.2f}x")
    rows.append(f"16 tiles of 256² x 61 planes (padded {tile_grid[0]}²): {t_tiled:.2f} s warm, peak {m_tiled:.0f} MiB")
    rows.append(f"  ratio to bare complex64 IFFT floor ({t_tiled_floor:.2f} s): {t_tiled / t_tiled_floor:.2f}x")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
