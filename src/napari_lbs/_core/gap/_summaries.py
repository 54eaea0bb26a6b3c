"""Tile summaries: one code path for real and simulated tiles, none needing the two scenes to be aligned.

Per spatial-frequency band (radial power spectrum, and the power at the experiment's
strongest static-fringe frequency), per depth (contrast and relative sharpness of 8
back-propagated planes, sharpness-weighted depth), per image region (illumination tilt and
curvature within a tile, the field-wide envelope around it), intensity statistics (quantiles,
moments, clipped fraction), noise character (residual std, the noise variance's elasticity
to the local intensity, distinct levels, how peaked the high band's spectrum is: noise is
flat, aliased light a few chirps)
and particle appearance through focus (brightest focal spots and darkest cores over all
planes, dark-core area, autocorrelation of the fringes).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import scipy.fft
from scipy import ndimage

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.physics import EFFECTS
from napari_lbs._core.physics import transfer_function
from napari_lbs._core.foundation import process_threads, thread_pool

__all__ = ["tile_summaries", "SUMMARY_GROUPS", "MIN_TILE_PX"]

SUMMARY_GROUPS = ("band", "depth", "region", "intensity", "noise", "appearance")
_BANDS = np.geomspace(1 / 64, 0.5, 9)  # cycles per pixel: 8 bands
_LAGS = (1, 2, 4, 8, 16)
MIN_TILE_PX = 64  # the lowest frequency band (1/64 cycle per pixel) is empty in smaller tiles


def _depths(config: ExperimentConfig, count: int = 8) -> np.ndarray:
    """``count`` planes spread evenly inside the volume (µm)."""
    return np.linspace(config.volume.z_min_um, config.volume.z_max_um, count + 2)[1:-1]


def tile_summaries(
    tile: np.ndarray,
    *,
    config: ExperimentConfig,
    fringe_frequency: tuple[float, float] | None = None,
    field_mean: float | None = None,
    surroundings: np.ndarray | None = None,
) -> tuple[np.ndarray, list[tuple[str, str]]]:
    """Summary vector of one hologram tile and the (name, group) of each entry.

    ``fringe_frequency`` (cycles/px, (fy, fx)): where to measure the power of a static fringe,
    e.g. the experiment's strongest spectral peak; real and simulated
    tiles must be summarised with the same one. Default: this tile's own strongest peak.

    ``field_mean`` (the mean of the whole image the tile was cut from; default the tile's own)
    and ``surroundings`` (`field_surroundings`: the field around the tile, twice its size,
    NaN outside the field; default none: tilt and curvature 0) give the field-wide envelope: the tile's
    brightness against the field's, and the tilt and curvature of the log brightness fitted
    over the surroundings. A smooth vignetting has nearly the same curvature at every tile,
    so it stands out of the particles' tile-to-tile fluctuation where a tile's mean does not.
    """
    # float32 like the camera's counts and the simulation: filters and quantiles of half the
    # bytes run twice as fast; sums and moments accumulate in float64
    image = np.asarray(tile, np.float32)
    tile_mean = float(image.mean(dtype=np.float64))
    image = image / np.float32(tile_mean)
    rows, cols = image.shape
    values: list[float] = []
    names: list[tuple[str, str]] = []

    def add(name, group, value):
        values.append(float(value))
        names.append((name, group))

    # band: radially averaged power of the Hann-windowed fluctuation, 8 log bands
    power = _power_spectrum(image)
    radius, band_of, band_sizes = _frequency_grid(rows, cols)
    band_power = np.bincount(band_of, weights=power.ravel(), minlength=len(_BANDS) + 1)[1 : len(_BANDS)]
    for low, high, total, size in zip(_BANDS[:-1], _BANDS[1:], band_power, band_sizes, strict=True):
        add(f"log power {low:.3f}-{high:.3f} cyc/px", "band", np.log10(total / size + 1e-12))
    # a static (etalon) fringe stands out of the ring of its own spatial frequency: power at the
    # fringe's frequency over the median of that ring (a particle's rings spread over all angles)
    fy, fx = fringe_frequency if fringe_frequency is not None else _peak_frequency(power)
    row, col = int(round(fy * rows)) % rows, int(round(fx * cols)) % cols
    ring = power[np.abs(radius - radius[row, col]) < 1.5 / min(rows, cols)]
    # the 3x3 bins around it: the window spreads a fringe over neighbouring bins, and nine bins fluctuate less than one
    near = np.take(np.take(power, np.arange(row - 1, row + 2) % rows, axis=0), np.arange(col - 1, col + 2) % cols, axis=1)
    add("log power at the fringe frequency / its ring's median", "band", np.log10(near.mean() / (np.median(ring) + 1e-12)))
    # depth: planes of the back-propagated tile, per plane (never only the depth average)
    optics = {"wavelength_um": config.optics.wavelength_um, "pixel_um": config.optics.pixel_um, "medium_index": config.optics.medium_index}
    depths = _depths(config)
    planes = np.abs(_periodic_planes(image, -depths, **optics))
    planes = planes / _quantiles(planes.reshape(len(depths), -1), (0.5,), axis=-1).astype(planes.dtype)[:, :1, None]  # background ≈ 1 in every plane
    for z, contrast in zip(depths, planes.std(axis=(1, 2)), strict=True):
        add(f"contrast at {z:.0f} um", "depth", contrast)
    # edge energy: largest where the particles of that depth are in focus
    gradient_y, gradient_x = np.gradient(planes, axis=(1, 2))
    sharpness = np.mean(gradient_y**2 + gradient_x**2, axis=(1, 2), dtype=np.float64)
    for z, value in zip(depths, sharpness / sharpness.mean(), strict=True):
        add(f"relative sharpness at {z:.0f} um", "depth", value)
    add("sharpness-weighted depth / volume", "depth", float(np.sum(sharpness * depths) / sharpness.sum()) / config.volume.z_max_um)
    # appearance through focus: brightest focal spots and darkest cores anywhere in the volume
    brightest, darkest = planes.max(axis=0), planes.min(axis=0)
    for q, value in zip((0.99, 0.999), _quantiles(brightest, (0.99, 0.999)), strict=True):
        add(f"focal spots: q{q} of the brightest plane", "appearance", value)
    for q, value in zip((0.001, 0.01), _quantiles(darkest, (0.001, 0.01)), strict=True):
        add(f"dark cores: q{q} of the darkest plane", "appearance", value)
    add("dark-core area: fraction below half the background", "appearance", np.mean(darkest < 0.5))
    # region: smooth illumination over the tile (tilt and curvature of a quadratic fit)
    smooth = ndimage.uniform_filter(image, size=max(rows // 8, 3))
    coefficients = _illumination_projector(rows, cols) @ smooth.ravel()
    add("illumination tilt |grad|", "region", np.hypot(coefficients[1], coefficients[2]))
    add("illumination curvature", "region", coefficients[3])
    # field-wide envelope: the tile's brightness against the whole image's, and how it varies
    # across the field (a vignetting spans tiles; within one tile it is only a slight tilt)
    field_mean = field_mean if field_mean is not None else tile_mean
    add("field envelope: |log tile mean / field mean|", "region", abs(np.log(tile_mean / field_mean)))
    # without surroundings (tiles not cut from one field) there is no field-wide envelope to fit:
    # within the tile, the illumination tilt and curvature above already see it
    tilt, curvature = _envelope(surroundings, field_mean) if surroundings is not None else (0.0, 0.0)
    add("field envelope: log-brightness tilt around the tile (per tile edge)", "region", tilt)
    add("field envelope: log-brightness curvature around the tile (per tile edge²)", "region", curvature)
    # intensity statistics
    quantiles = (0.005, 0.05, 0.25, 0.5, 0.75, 0.95, 0.995)
    for q, value in zip(quantiles, _quantiles(image, quantiles), strict=True):
        add(f"quantile {q}", "intensity", value)
    # the population (biased) moments, as scipy.stats' skew and kurtosis give them, without their per-call overhead
    deviation = image - image.mean()
    squared = deviation * deviation
    variance = squared.mean()
    add("skewness", "intensity", (squared * deviation).mean() / variance**1.5)
    add("log kurtosis", "intensity", np.log10((squared * squared).mean() / variance**2))
    add("clipped fraction", "intensity", np.mean(image >= image.max() - 1e-9 * abs(image.max())))
    # noise character
    residual = image - ndimage.gaussian_filter(image, 1.0)
    add("log residual std", "noise", np.log10(residual.std() + 1e-12))
    add("noise variance's elasticity to the local intensity", "noise", _noise_elasticity(image))
    smooth = ndimage.gaussian_filter(image, 2.0)
    dark, bright = _quantiles(smooth, (0.25, 0.75))
    # photon noise grows with the signal: residual variance in the bright quarter over the dark quarter
    add("log residual variance bright/dark", "noise", np.log10((residual[smooth >= bright].var() + 1e-12) / (residual[smooth <= dark].var() + 1e-12)))
    add("log distinct levels", "noise", np.log10(np.unique(np.round(image / (image.std() + 1e-12), 6)).size))
    add(f"log high-band spectral peakedness ({_PEAKEDNESS_BLOCK_PX}-px blocks)", "noise", _high_band_peakedness(image))
    # appearance: autocorrelation of the fringes at a few lags
    centred = image - 1.0
    norm = (centred**2).mean() + 1e-12
    for lag in _LAGS:
        add(f"autocorrelation at {lag} px", "appearance", 0.5 * ((centred[lag:] * centred[:-lag]).mean() + (centred[:, lag:] * centred[:, :-lag]).mean()) / norm)
    return np.asarray(values), names


def _tiles_summaries(
    tiles: Sequence[np.ndarray],
    *,
    config: ExperimentConfig,
    fringe_frequency: tuple[float, float] | None,
    field_means: Sequence[float | None],
    surroundings: Sequence[np.ndarray | None],
) -> tuple[np.ndarray, list[tuple[str, str]]]:
    """`tile_summaries` of several tiles, each with its own field mean and surroundings: ((tiles, K) array, names).

    The tiles are summarised on a pool of threads, one per core: their FFTs, sorts, filters
    and array arithmetic run without Python's global lock. Each tile's summary is computed as alone, so the result
    does not depend on the threads.
    """
    def one(args):
        with np.errstate(all="ignore"):  # a flat (e.g. fully saturated) tile has no moments: NaN, which the caller handles
            return tile_summaries(args[0], config=config, fringe_frequency=fringe_frequency, field_mean=args[1], surroundings=args[2])

    done = list(thread_pool("summaries").map(one, zip(tiles, field_means, surroundings, strict=True)))
    return np.stack([values for values, _ in done]), done[0][1]


_ELASTICITY_WINDOW_PX = 6  # even: after the one-pixel shift below, the window is centred on a 2 × 2 block's centre


def _noise_elasticity(image: np.ndarray) -> float:
    """d ln(noise variance) / d ln(intensity) over a tile (dimensionless): 1 for photon noise, 0 for read noise.

    ``image``: the 2-D tile divided by its mean (float32).

    Every pixel's noise is measured by the second difference of its 2 × 2 block,
    ``d = (x₀₀ − x₀₁ − x₁₀ + x₁₁) / 2`` (whose variance is one pixel's white-noise variance;
    smooth light, up to a tilt, cancels), and ``d²`` is regressed on the block's local mean
    intensity ``m`` (a 6-px window) by least squares over the whole tile: elasticity =
    slope · mean(m) / mean(d²). Every pixel's fringe-scale brightness is leverage, where the
    16-px block means of a coarser summary would average the fringes away: on absorbing
    Lorenz–Mie scenes at 120 photons, 16 tiles of 128² tell Poisson from Gaussian noise of
    the same variance at z = 10–18, where 16-px blocks gave 4–7. Where the noise is small against fine
    fringes, their leak into ``d`` sets the value (0.9–1.2 in that suite's controls, read
    noise 1 % of the light), alike in real and simulated tiles of the same fringes: the
    summary tells the noises apart where noise dominates ``d``.
    """
    d = 0.5 * (image[:-1, :-1] - image[:-1, 1:] - image[1:, :-1] + image[1:, 1:])
    squared = (d * d).astype(np.float64)
    local = ndimage.uniform_filter(image, _ELASTICITY_WINDOW_PX)[1:, 1:].astype(np.float64)  # pixels j-2 … j+3: centred on the block's centre, as d
    centred = local - local.mean()
    local_sum_of_squares = float(np.sum(centred * centred))
    if local_sum_of_squares <= 0.0 or squared.mean() <= 0.0:  # a flat tile, or one whose 2 × 2 differences all vanish: no slope to measure
        return 0.0
    return float(np.sum(centred * squared) / local_sum_of_squares * local.mean() / squared.mean())


_PEAKEDNESS_BLOCK_PX = 32
_PEAKEDNESS_BAND = (0.25, 0.5)  # cycles per pixel


def _high_band_peakedness(image: np.ndarray) -> float:
    """Mean over 32-px blocks of log10(mean(P²) / mean(P)²) of the periodogram P at 0.25-0.5 cycles/px.

    White noise (read or photon) gives exponentially distributed periodogram values, a ratio
    of 2 (log 0.30) whatever its power. Fringes are a few chirps, each narrow in a block:
    a few strong bins, a larger ratio. So this tells added light from added noise where the
    band's power cannot: light a transparent sphere refracts beyond the sensor's bandwidth
    arrives aliased, as power at every high frequency like noise, but as chirps. Photon or
    doubled read noise lowers it by 4-11 tile-to-tile spreads, transparent spheres raise it
    by 0.3-1 (measured on 128² tiles of Lorenz–Mie scenes).
    """
    block = _PEAKEDNESS_BLOCK_PX
    rows, cols = (image.shape[0] // block) * block, (image.shape[1] // block) * block
    blocks = image[:rows, :cols].reshape(rows // block, block, cols // block, block).swapaxes(1, 2).reshape(-1, block, block)
    blocks = (blocks - blocks.mean(axis=(1, 2), keepdims=True)) * _hann(block, block).astype(image.dtype)
    power = np.abs(scipy.fft.fft2(blocks, workers=process_threads())) ** 2
    values = power[:, _peakedness_bins(block)].astype(np.float64)
    return float(np.mean(np.log10(np.mean(values**2, axis=1) / (np.mean(values, axis=1) ** 2 + 1e-300) + 1e-12)))


@functools.lru_cache(maxsize=2)
def _peakedness_bins(block: int) -> np.ndarray:
    """Boolean mask of a block's FFT bins in `_PEAKEDNESS_BAND`, one of each Hermitian pair (non-negative fx)."""
    fy, fx = np.meshgrid(np.fft.fftfreq(block), np.fft.fftfreq(block), indexing="ij")
    radius = np.hypot(fy, fx)
    mask = (radius >= _PEAKEDNESS_BAND[0]) & (radius <= _PEAKEDNESS_BAND[1]) & (fx >= 0)
    mask.flags.writeable = False
    return mask


_ENVELOPE_BLOCKS = 16  # blocks per axis of a tile's surroundings (8 per tile edge)
_CENTRES = (np.arange(_ENVELOPE_BLOCKS) + 0.5) / _ENVELOPE_BLOCKS * 2.0 - 1.0  # block centres in tile edges from the tile's centre
_BLOCK_Y, _BLOCK_X = (a.ravel() for a in np.meshgrid(_CENTRES, _CENTRES, indexing="ij"))
# the envelope's design matrix (1, x, y, x², y²) over the blocks, in row-major block order
_ENVELOPE_DESIGN = np.stack([np.ones_like(_BLOCK_X), _BLOCK_X, _BLOCK_Y, _BLOCK_X**2, _BLOCK_Y**2], axis=1)


def _envelope(surroundings: np.ndarray, field_mean: float) -> tuple[float, float]:
    """Tilt |∇| and curvature (∂²/∂x² + ∂²/∂y²)/2 of log brightness over a tile's surroundings, in tile edges.

    The surroundings are averaged in 16 × 16 blocks (blocks holding NaN, outside the field,
    are left out) and ``log(block mean / field_mean)`` is fitted with 1, x, y, x², y² about the
    tile's centre.
    """
    rows, cols = surroundings.shape
    blocks = surroundings[: rows - rows % _ENVELOPE_BLOCKS, : cols - cols % _ENVELOPE_BLOCKS].reshape(_ENVELOPE_BLOCKS, rows // _ENVELOPE_BLOCKS, _ENVELOPE_BLOCKS, cols // _ENVELOPE_BLOCKS).mean(axis=(1, 3))
    valid = np.isfinite(blocks) & (blocks > 0)
    coefficients = np.linalg.lstsq(_ENVELOPE_DESIGN[valid.ravel()], np.log(blocks[valid] / field_mean), rcond=None)[0]
    return float(np.hypot(coefficients[1], coefficients[2])), float(coefficients[3] + coefficients[4])


@functools.lru_cache(maxsize=8)
def _frequency_grid(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radial frequency (cycles/px) of each FFT bin, its band label (1-8 within `_BANDS`, 0 below, 9 above; flattened) and each band's bin count."""
    radius = np.hypot(*np.meshgrid(np.fft.fftfreq(rows), np.fft.fftfreq(cols), indexing="ij"))
    band_of = np.digitize(radius.ravel(), _BANDS)  # band i holds _BANDS[i-1] <= radius < _BANDS[i]
    sizes = np.bincount(band_of, minlength=len(_BANDS) + 1)[1 : len(_BANDS)]
    for array in (radius, band_of, sizes):
        array.flags.writeable = False  # shared by every call
    return radius, band_of, sizes


@functools.lru_cache(maxsize=8)
def _illumination_projector(rows: int, cols: int) -> np.ndarray:
    """(4, rows·cols) least-squares projector onto 1, x, y, x² + y² over the tile (x, y from -0.5 to 0.5)."""
    y, x = np.mgrid[-0.5 : 0.5 : rows * 1j, -0.5 : 0.5 : cols * 1j]
    return np.linalg.pinv(np.stack([np.ones(rows * cols), x.ravel(), y.ravel(), (x**2 + y**2).ravel()], axis=1))


@functools.lru_cache(maxsize=8)
def _plane_kernels(shape: tuple[int, int], distances_um: tuple[float, ...], wavelength_um: float, pixel_um: float, medium_index: float) -> np.ndarray:
    """(planes, rows, cols) complex64 transfer functions on the tile's own grid, band-limited to a spread of half the tile."""
    spread_limit_um = 0.5 * min(shape) * pixel_um
    return np.stack([transfer_function(shape, z, wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index, spread_limit_um=spread_limit_um, cache=False) for z in distances_um])


def _periodic_planes(image: np.ndarray, distances_um: np.ndarray, *, wavelength_um: float, pixel_um: float, medium_index: float) -> np.ndarray:
    """The tile propagated to each distance on its own (periodic) grid, complex64 (planes, rows, cols).

    Summaries need the same planes for real and simulated tiles, not light that left the tile:
    without `propagate`'s padding (a 128² tile is padded to 512² for 4.5 mm) the planes cost
    16 × less. Each kernel is band-limited to a spread of half the tile, so it is sampled
    finely enough and nothing wraps more than half way round.
    """
    kernels = _plane_kernels(image.shape, tuple(float(z) for z in distances_um), wavelength_um, pixel_um, medium_index)
    return scipy.fft.ifft2(scipy.fft.fft2(image.astype(np.complex64))[None] * kernels, workers=process_threads(), overwrite_x=True)


def _power_spectrum(image: np.ndarray) -> np.ndarray:
    """Power of the Hann-windowed fluctuation of a mean-normalised image (in the image's precision)."""
    window = _hann(*image.shape).astype(image.dtype, copy=False)
    return np.abs(scipy.fft.fft2((image - 1) * window, workers=process_threads())) ** 2 / window.sum(dtype=np.float64)


@functools.lru_cache(maxsize=8)
def _hann(rows: int, cols: int) -> np.ndarray:
    window = np.outer(np.hanning(rows), np.hanning(cols))
    window.flags.writeable = False
    return window


def _quantiles(values: np.ndarray, quantiles: Sequence[float], *, axis: int | None = None) -> np.ndarray:
    """``np.quantile``'s default (linear) quantiles of ``values`` (all of it, or along the last axis with ``axis=-1``), from one sort.

    numpy sorts float32 with vectorised kernels an order of magnitude faster than the
    partitions ``np.quantile`` does for several quantiles, above all on integer counts with
    many ties, where a partition degrades: the quantiles were a third of a summary's time.
    """
    ordered = np.sort(values.ravel() if axis is None else values, axis=-1)
    position = np.asarray(quantiles, np.float64) * (ordered.shape[-1] - 1)
    low = np.floor(position).astype(np.intp)
    high = np.minimum(low + 1, ordered.shape[-1] - 1)
    fraction = position - low
    return ordered[..., low] + (ordered[..., high] - ordered[..., low]) * fraction


def _peak_frequency(power: np.ndarray) -> tuple[float, float]:
    """(fy, fx) in cycles/px of the bin that stands out most from its ring's median power,
    within the `parasitic_fringes` period bounds (a particle scene's power falls steeply with
    frequency, so the absolute maximum would sit at the longest period)."""
    rows, cols = power.shape
    fy, fx = np.meshgrid(np.fft.fftfreq(rows), np.fft.fftfreq(cols), indexing="ij")
    shortest, longest = EFFECTS["parasitic_fringes"].bounds["period_px"]
    radius = np.hypot(fy, fx)
    ring = np.round(radius * min(rows, cols)).astype(int)
    ring_median = ndimage.median(power, labels=ring, index=np.arange(ring.max() + 1))
    contrast = np.where((radius >= 1 / longest) & (radius <= 1 / shortest), power / (np.asarray(ring_median)[ring] + 1e-30), -np.inf)
    peak = np.unravel_index(np.argmax(contrast), power.shape)
    return float(fy[peak]), float(fx[peak])
