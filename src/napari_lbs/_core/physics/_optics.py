"""Angular-spectrum propagation of scalar fields between parallel planes.

Convention
----------
Time dependence ``exp(-i ω t)``; a plane wave travelling toward +z is ``exp(+i k z)``. Fields
are expressed *relative to the unscattered plane wave*: the carrier ``exp(i k z)`` is removed,
so a uniform field of ones is unchanged by propagation and a hologram normalised by its
background is directly the field at the sensor. The transfer function for a distance ``z``
(µm, positive = downstream) is

    H(fx, fy; z) = exp(i 2π z (sqrt(1/λm² - fx² - fy²) - 1/λm)),   λm = λ / n,

on the `numpy.fft.fftfreq` grid, with the evanescent part (fx² + fy² > 1/λm²) set to zero.
The phase is evaluated in float64 as ``-2π z/λm · q / (sqrt(1 - q) + 1)`` with
``q = λm² (fx² + fy²)`` (no cancellation) and the kernel stored as complex64 for float32 input.

Aliasing
--------
Fields are padded (continuing them with the mean of their border, i.e. the unobstructed
light) to a size ``W`` large enough that light leaving the window at the widest sampled angle
over the largest distance does not wrap around onto it, and the kernel is band-limited per
axis to the frequencies whose geometric spread ``z tanθ`` stays within ``min(W/2, W - n)``
(Matsushima & Shimobaba, Opt. Express 17, 19662 (2009)). Light that would wrap is dropped
instead of aliased.

Pitch finer than half the medium wavelength
-------------------------------------------
Behind a microscope objective the pitch at the sample can be below ``λ/(2n)`` (0.0851 µm for
660 nm in water, whose ``λ/(2n)`` is 0.248 µm). The grid then holds frequencies beyond the
medium's cutoff ``n/λ``: they are evanescent and the kernel is zero there, so the angular
spectrum is band-limited at ``n/λ`` by the propagation itself. Every propagating angle, up to
grazing, is then sampled: the padding stops at its cap (4 n per axis, `padded_shape`) and the
band limit above drops the widest angles, whose light would wrap, as at any pitch.

References
----------
J. W. Goodman, *Introduction to Fourier Optics*, 3rd ed., Sec. 3.10.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from functools import lru_cache

import numpy as np
import scipy.fft

from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback
from napari_lbs._core.foundation import process_threads, thread_pool
from napari_lbs._core.foundation import check_memory, check_number

__all__ = [
    "padded_shape",
    "propagation_grid",
    "superpose",
    "transfer_function",
    "propagate",
    "backpropagate",
    "backpropagated_blocks",
    "set_transfer_cache_limit",
]

_WORKING_BYTES = 512 * 2**20  # working memory for one batch of padded planes
_MAX_PAD_FACTOR = 4


def _check_optics(wavelength_um: float, pixel_um: float, medium_index: float) -> None:
    """Refuse optics no propagation can use (a zero pitch divides by zero, a negative wavelength makes NaN), naming the argument."""
    check_number(wavelength_um, key="wavelength_um", low=0.0, high=100.0, above=True)
    check_number(pixel_um, key="pixel_um", low=0.0, high=1e4, above=True)
    check_number(medium_index, key="medium_index", low=0.0, high=10.0, above=True)


def _medium_wavelength(wavelength_um: float, medium_index: float) -> float:
    return wavelength_um / medium_index


def _spread_px(z_um: float, *, wavelength_um: float, pixel_um: float, medium_index: float) -> float:
    """Lateral distance (px) that light at the grid's widest propagating angle travels over ``z_um``."""
    # below a pitch of λ/(2n) the widest angle is grazing and the spread unbounded: 0.999 makes it
    # exceed any window, so the padding takes its cap and the band limit does the rest
    sin_theta = min(_medium_wavelength(wavelength_um, medium_index) / (2.0 * pixel_um), 0.999)
    return abs(z_um) * sin_theta / np.sqrt(1.0 - sin_theta**2) / pixel_um


def padded_shape(shape: tuple[int, int], *, z_max_um: float, wavelength_um: float, pixel_um: float, medium_index: float = 1.0) -> tuple[int, int]:
    """FFT size that keeps light within ``z_max_um`` from wrapping onto a ``shape`` window.

    Each axis is padded to ``max(n + s, 2 s)`` (``s``: spread at the widest sampled angle,
    px), at most ``4 n``, rounded up to a fast FFT length. Beyond the cap the band limit of
    `transfer_function` drops the widest angles instead of letting them alias.
    """
    _check_optics(wavelength_um, pixel_um, medium_index)
    spread = _spread_px(z_max_um, wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index)
    out = []
    for n in shape:
        needed = int(np.ceil(max(n + spread, 2.0 * spread, n)))
        out.append(scipy.fft.next_fast_len(min(needed, _MAX_PAD_FACTOR * n)))
    return tuple(out)


@lru_cache(maxsize=8)
def _phase_rate(shape: tuple[int, int], wavelength_um: float, pixel_um: float, medium_index: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``kz - k`` (rad/µm, float64, NaN where evanescent) and the fftfreq axes (1/µm)."""
    lam = _medium_wavelength(wavelength_um, medium_index)
    fy = np.fft.fftfreq(shape[0], d=pixel_um)
    fx = np.fft.fftfreq(shape[1], d=pixel_um)
    q = lam**2 * (fy[:, None] ** 2 + fx[None, :] ** 2)
    with np.errstate(invalid="ignore"):
        rate = -2.0 * np.pi / lam * q / (np.sqrt(1.0 - q) + 1.0)
    rate[q > 1.0] = np.nan
    for array in (rate, fy, fx):
        array.setflags(write=False)
    return rate, fy, fx


class _BoundedCache:
    """Least-recently-used cache bounded by the bytes of the arrays it holds (thread-safe)."""

    def __init__(self, limit_bytes: int) -> None:
        self.limit_bytes = int(limit_bytes)
        self._items: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: tuple) -> np.ndarray | None:
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, key: tuple, value: np.ndarray) -> None:
        with self._lock:
            if key in self._items or value.nbytes > self.limit_bytes:
                return
            self._items[key] = value
            self._bytes += value.nbytes
            while self._bytes > self.limit_bytes:
                _, evicted = self._items.popitem(last=False)
                self._bytes -= evicted.nbytes

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0


# Holding a kernel costs its first touch (page faults: 1.5 s of system time for the 61 kernels
# of a 1024² scan, 0.9 GB) where building it again costs 3 ms: only scans of small grids
# (training tiles, calibration fields), which repeat, are worth keeping.
_TRANSFER_CACHE = _BoundedCache(256 * 2**20)


def set_transfer_cache_limit(limit_bytes: int) -> None:
    """Bound the memory the transfer-function cache may hold (bytes; 0 disables caching)."""
    _TRANSFER_CACHE.clear()
    _TRANSFER_CACHE.limit_bytes = int(limit_bytes)


def transfer_function(
    shape: tuple[int, int],
    z_um: float,
    *,
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
    spread_limit_um: float | None = None,
    dtype: np.dtype | type = np.complex64,
    cache: bool = True,
) -> np.ndarray:
    """Angular-spectrum transfer function for one distance, on the unshifted fftfreq grid.

    Parameters
    ----------
    shape : (int, int)
        Grid (rows, cols), usually the padded size.
    z_um : float
        Propagation distance (µm); negative propagates upstream.
    wavelength_um, pixel_um : float
        Vacuum wavelength and grid pitch (µm).
    medium_index : float
        Refractive index of the medium.
    spread_limit_um : float or None
        Band-limit each axis to the frequencies whose lateral spread ``|z| tanθ`` is at most
        this (µm). None keeps every propagating frequency.
    dtype : complex dtype
        complex64 (default) or complex128.
    cache : bool
        Keep the kernel in the bounded LRU cache (keyed on grid, optics and distance); a
        cached kernel is returned either way.

    Returns
    -------
    ndarray, read-only.
    """
    dtype = np.dtype(dtype)
    key = (tuple(shape), float(z_um), float(wavelength_um), float(pixel_um), float(medium_index), spread_limit_um, dtype.str)
    cached = _TRANSFER_CACHE.get(key)
    if cached is not None:
        return cached
    rate, fy, fx = _phase_rate(tuple(shape), float(wavelength_um), float(pixel_um), float(medium_index))
    # The kernel depends on |fy| and |fx| alone, and fftfreq's negative frequencies are the
    # positive ones negated exactly: built on the non-negative quarter and mirrored, it is the
    # same kernel for a quarter of the trigonometry, which dominated a cold scan's time.
    rows, cols = shape[0] // 2 + 1, shape[1] // 2 + 1
    rate = rate[:rows, :cols]
    phase = rate * float(z_um)  # float64: up to ~1e3 rad at 5 mm, exact to ~1e-12 rad
    # Wrapped to [-π, π] in float64 first, the phase loses nothing (< 2e-7 rad) in the real
    # dtype of the kernel, where cos and sin are cheapest.
    phase -= 2.0 * np.pi * np.round(phase / (2.0 * np.pi))
    phase = phase.astype(np.float32 if dtype == np.complex64 else np.float64)
    quarter = np.empty((rows, cols), dtype=dtype)
    np.cos(phase, out=quarter.real)
    np.sin(phase, out=quarter.imag)
    blocked = np.isnan(rate)
    if spread_limit_um is not None and z_um != 0.0:
        lam = _medium_wavelength(wavelength_um, medium_index)
        limit = 1.0 / (lam * np.sqrt((float(z_um) / spread_limit_um) ** 2 + 1.0))
        blocked |= (np.abs(fy[:rows])[:, None] > limit) | (np.abs(fx[:cols])[None, :] > limit)
    quarter[blocked] = 0.0
    kernel = np.empty(shape, dtype=dtype)
    kernel[:rows, :cols] = quarter
    kernel[:rows, cols:] = quarter[:, shape[1] - cols : 0 : -1]  # column n - k is column k
    kernel[rows:] = kernel[shape[0] - rows : 0 : -1]
    kernel.setflags(write=False)
    if cache:
        _TRANSFER_CACHE.put(key, kernel)
    return kernel


def _complex_dtype(array: np.ndarray) -> np.dtype:
    return np.dtype(np.complex128) if array.dtype in (np.float64, np.complex128) else np.dtype(np.complex64)


def _border_mean(field: np.ndarray) -> complex:
    border = np.concatenate([field[0], field[-1], field[1:-1, 0], field[1:-1, -1]])
    return complex(border.mean())


def _distances(z_um: float | Sequence[float]) -> np.ndarray:
    distances = np.atleast_1d(np.asarray(z_um, dtype=np.float64))
    if distances.ndim != 1 or distances.size == 0:
        raise InputError(f"z_um: expected a depth or a non-empty list of depths, got {z_um!r}")
    if not np.all(np.isfinite(distances)):
        raise InputError(f"z_um: expected finite depths, got {z_um!r}")
    return distances


def propagation_grid(shape: tuple[int, int], *, z_max_um: float, wavelength_um: float, pixel_um: float, medium_index: float = 1.0) -> tuple[tuple[int, int], float]:
    """Padded FFT grid for a ``shape`` window and the band limit's spread (µm) that keeps it alias-free.

    The spread limit is ``min(W/2, W - n)``: the kernel is sampled finely enough (W/2,
    Matsushima & Shimobaba 2009) and light leaving the window does not wrap onto it (W - n).
    """
    grid = padded_shape(shape, z_max_um=z_max_um, wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index)
    spread_limit_um = min(min(g / 2.0, g - n) for g, n in zip(grid, shape, strict=True)) * pixel_um
    return grid, spread_limit_um


def _propagated_batches(field, distances, *, wavelength_um, pixel_um, medium_index, steps):
    """Yield ``(start, stop, block)``: the field propagated to ``distances[start:stop]``, cropped."""
    rows, cols = field.shape
    dtype = _complex_dtype(field)
    grid, spread_limit_um = propagation_grid(field.shape, z_max_um=float(np.max(np.abs(distances))), wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index)
    padded = np.full(grid, _border_mean(field), dtype=dtype)
    padded[:rows, :cols] = field
    spectrum = scipy.fft.fft2(padded, workers=process_threads(), overwrite_x=True)
    batch = max(1, _WORKING_BYTES // (spectrum.nbytes * 2))
    # An LRU cache smaller than a scan's kernels never hits on the next scan (each kernel is
    # evicted before its turn comes again), so such a scan does not fill it: a 1024² hologram
    # to 77 depths would otherwise hold 1 GiB of kernels for nothing.
    cache = distances.size * spectrum.nbytes <= _TRANSFER_CACHE.limit_bytes
    block = np.empty((min(batch, distances.size),) + grid, dtype=dtype)
    for start in range(0, distances.size, batch):
        steps.check()
        stop = min(start + batch, distances.size)
        work = block[: stop - start]
        def multiply(j, z):
            kernel = transfer_function(grid, float(z), wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index, spread_limit_um=spread_limit_um, dtype=dtype, cache=cache)
            np.multiply(spectrum, kernel, out=work[j])

        # numpy releases the GIL: the memory-bound products run on all cores like the FFTs do.
        list(thread_pool("asm").map(multiply, range(stop - start), distances[start:stop]))
        scipy.fft.ifft2(work, axes=(-2, -1), workers=process_threads(), overwrite_x=True)
        yield start, stop, work[:, :rows, :cols]
        steps.advance(stop - start)


def superpose(
    scattered: Sequence[np.ndarray],
    z_um: Sequence[float],
    *,
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
    periodic: bool = False,
    bandwidth_um: float = 0.0,
) -> np.ndarray:
    """Sum of several scattered fields, each propagated by its own distance, at one plane.

    ``sum_l propagate(scattered[l], z_um[l])`` computed with one inverse FFT: the spectra are
    accumulated. The fields are padded with zeros (a scattered field vanishes away from its
    scatterers), so light leaving the window is lost rather than wrapped. With
    ``periodic=True`` the window is one period of an endless field instead (no padding): light
    leaving one side enters the other, so every part of the window has scatterers all around
    it, as a crop of a large sensor does.

    ``bandwidth_um`` (FWHM of a Gaussian source spectrum, vacuum µm): the field averaged over
    the spectrum, as it interferes with the unscattered light. Paraxially, a frequency ``f``
    propagated by ``z`` is delayed against the unscattered wave by ``exp(-iπ λ z f²)``; its
    mean over a Gaussian spectrum of standard deviation σ multiplies it by
    ``exp(-(π σ z f²)² / 2)`` (λ and σ in the medium): fringes of high order (large ``z f²``)
    wash out, exactly, at any bandwidth. The returned field is then the linear term's; the
    scattered light's own intensity ``|s|²`` needs the field at the centre wavelength.

    Returns
    -------
    (rows, cols) complex array (complex64 for float32/complex64 input).
    """
    _check_optics(wavelength_um, pixel_um, medium_index)
    if len(scattered) != len(z_um) or not len(scattered):
        raise InputError(f"scattered: expected one field per depth ({len(z_um)}), got {len(scattered)}")
    shape = np.shape(scattered[0])
    dtype = _complex_dtype(np.asarray(scattered[0]))
    distances = _distances(z_um)
    if periodic:
        grid, spread_limit_um = tuple(shape), None
    else:
        grid, spread_limit_um = propagation_grid(shape, z_max_um=float(np.max(np.abs(distances))), wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index)
    total = np.zeros(grid, dtype=dtype)
    padded = np.zeros(grid, dtype=dtype)
    if bandwidth_um > 0:
        sigma_um = bandwidth_um / (2.0 * np.sqrt(2.0 * np.log(2.0))) / medium_index
        f2 = np.fft.fftfreq(grid[0], d=pixel_um)[:, None] ** 2 + np.fft.fftfreq(grid[1], d=pixel_um)[None, :] ** 2
    for layer, z in zip(scattered, distances, strict=True):
        if np.shape(layer) != shape:
            raise InputError(f"scattered: expected every field of shape {shape}, got {np.shape(layer)}")
        padded[: shape[0], : shape[1]] = layer
        spectrum = scipy.fft.fft2(padded, workers=process_threads())
        kernel = transfer_function(grid, float(z), wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index, spread_limit_um=spread_limit_um, dtype=dtype)
        if bandwidth_um > 0:
            kernel = kernel * np.exp(-0.5 * (np.pi * sigma_um * float(z) * f2) ** 2).astype(kernel.real.dtype)
        total += spectrum * kernel
    return scipy.fft.ifft2(total, workers=process_threads(), overwrite_x=True)[: shape[0], : shape[1]]


def propagate(
    field: np.ndarray,
    z_um: float | Sequence[float],
    *,
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> np.ndarray:
    """Propagate a complex field by each distance in ``z_um``.

    Parameters
    ----------
    field : (rows, cols) array
        Complex (or real) field relative to the plane wave, on a grid of pitch ``pixel_um``.
        float32/complex64 input is computed in complex64, float64/complex128 in complex128.
    z_um : float or sequence of float
        Distances (µm); positive is downstream.
    wavelength_um, pixel_um, medium_index
        Vacuum wavelength (µm), grid pitch (µm) and medium refractive index.
    progress, should_stop
        See `napari_lbs._core.foundation._progress`; one step per plane. Raises `Stopped` when asked.

    Returns
    -------
    (len(z_um), rows, cols) complex array; 2-D if ``z_um`` is a scalar.
    """
    _check_optics(wavelength_um, pixel_um, medium_index)
    field = np.asarray(field)
    if field.ndim != 2:
        raise InputError(f"field: expected a 2-D array, got shape {field.shape}")
    distances = _distances(z_um)
    out = np.empty((distances.size,) + field.shape, dtype=_complex_dtype(field))
    steps = Steps(distances.size, progress=progress, should_stop=should_stop)
    for start, stop, block in _propagated_batches(field, distances, wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index, steps=steps):
        out[start:stop] = block
    return out[0] if np.ndim(z_um) == 0 else out


def _normalised_hologram(hologram: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """The hologram divided by ``background`` or by its own mean, float32 (float64 for float64 input); validated."""
    hologram = np.asarray(hologram)
    if hologram.ndim != 2:
        raise InputError(f"hologram: expected a 2-D image, got shape {hologram.shape}")
    if not np.all(np.isfinite(hologram)):
        raise InputError("hologram: contains NaN or infinite values")
    real_dtype = np.float64 if hologram.dtype == np.float64 else np.float32
    if background is None:
        level = float(hologram.mean())
        if level <= 0.0:
            raise InputError(f"hologram: expected a positive mean intensity, got {level}")
        return hologram.astype(real_dtype) / real_dtype(level)
    background = np.asarray(background, dtype=real_dtype)
    if background.shape != hologram.shape:
        raise InputError(f"background: expected shape {hologram.shape} (the hologram's), got {background.shape}")
    if not np.all(np.isfinite(background)) or np.any(background <= 0):
        raise InputError("background: expected finite, positive values everywhere")
    return hologram.astype(real_dtype) / background


def backpropagated_blocks(
    hologram: np.ndarray,
    z_um: Sequence[float],
    *,
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
    background: np.ndarray | None = None,
    steps: Steps | None = None,
) -> Iterator[tuple[int, int, np.ndarray]]:
    """`backpropagate` one batch of depths at a time, for stacks too large to hold.

    Yields ``(start, stop, field)``: the complex field at depths ``z_um[start:stop]``,
    ``(stop - start, rows, cols)``, whose ``np.abs`` is those planes of `backpropagate`
    bit for bit. The array is reused by the next batch: take what is kept out of it first.
    Batches hold about 512 MiB of padded planes (one plane when a plane is larger).

    Parameters
    ----------
    steps : Steps, optional
        Advanced by each batch's planes and checked before each (a stop raises `Stopped`).
    """
    _check_optics(wavelength_um, pixel_um, medium_index)
    normalised = _normalised_hologram(hologram, background)
    distances = _distances(z_um)
    steps = steps if steps is not None else Steps(distances.size, progress=None, should_stop=None)
    yield from _propagated_batches(normalised, -distances, wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index, steps=steps)


def backpropagate(
    hologram: np.ndarray,
    z_um: Sequence[float],
    *,
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
    background: np.ndarray | None = None,
    out: np.ndarray | None = None,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> np.ndarray:
    """Raw reconstruction: ``|field|`` of a hologram propagated back to each depth.

    The hologram is divided by ``background`` (same shape, taken without particles) or, when
    none is given, by its own mean, so unobstructed light is 1; it is then propagated by
    ``-z`` for each depth. Particles appear dark on a background near 1.

    Parameters
    ----------
    hologram : (rows, cols) float array
        Recorded intensity. The whole image is reconstructed at once, so tiles cut from the
        result keep their true surroundings.
    z_um : sequence of float
        Depths (µm, distance from the object plane to the sensor, positive).
    background : (rows, cols) array, optional
        Background intensity; must be positive everywhere.
    out : (len(z_um), rows, cols) float array, optional
        Where to write the result (e.g. a memory-mapped file) so large stacks need not fit in RAM.

    Returns
    -------
    (len(z_um), rows, cols) array, float32 for float32 input, float64 for float64 input.
    """
    _check_optics(wavelength_um, pixel_um, medium_index)
    normalised = _normalised_hologram(hologram, background)
    real_dtype = normalised.dtype.type
    distances = _distances(z_um)
    expected = (distances.size,) + normalised.shape
    if out is None:
        check_memory(float(np.prod(expected)) * np.dtype(real_dtype).itemsize, what=f"{distances.size} planes of {normalised.shape[0]}x{normalised.shape[1]} pixels",
                     remedy="raise volume.z_step_um, crop the hologram or pass out= (a memory-mapped array)")
        out = np.empty(expected, dtype=real_dtype)
    elif out.shape != expected:
        raise InputError(f"out: expected shape {expected}, got {out.shape}")
    steps = Steps(distances.size, progress=progress, should_stop=should_stop)
    for start, stop, block in _propagated_batches(normalised, -distances, wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index, steps=steps):
        np.abs(block, out=out[start:stop])  # no temporary plane batch
    return out
