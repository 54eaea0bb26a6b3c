"""Diagnosing the sim-to-real gap: where it lies, which unmodelled effect causes it, how far it shrinks.

Measurements (`tile_summaries`): one code path for real and simulated tiles, none needing the
two scenes to be aligned — per spatial-frequency band (radial power spectrum, and the power at
the experiment's static-fringe frequency), per depth (contrast and relative sharpness of 8
back-propagated planes, sharpness-weighted depth), per image region (illumination tilt and
curvature within a tile, the field-wide envelope around it; which real tiles differ most), intensity statistics (quantiles,
moments, clipped fraction), noise character (wavelet σ, variance against mean, distinct
levels) and particle appearance through focus (brightest focal spots and darkest cores over
all planes, dark-core area, autocorrelation of the fringes).

The gap between a set of real tiles ``R`` and simulated tiles ``S`` is the excess
standardised χ² over the K summaries::

    z_k = (mean R_k - mean S_k) / sqrt(var R_k / n_R + var S_k / n_S),   gap = max(0, mean_k z_k² - 1)

0 when the two sets are as alike as sampling allows. "Where" tables give, per group, the
rms of ``|Δ_k| / (sqrt 2 · std R_k)``: 1 means "as different as two tiles of the experiment".
(../shared/notes/calibration-and-gap.md: a standardised χ² separated models where a mean
absolute difference failed.)

Attribution (`diagnose_tiles`): fit the baseline (seed's simulator, `EFFECTS` module) to half
of the real tiles, screen every effect by regressing the standardised residual on its
signature, confirm the most significant ones (largest |t|) by adding each and refitting all
parameters, score every model on the other half (tiles never used for a fit), ablate each
confirmed fit (the same parameters with the effect switched off), rank, and name a verdict —
or ``null`` with the reason when no effect removes enough of the gap on the held-out tiles,
against the baseline and against its own ablated fit, with a confidence bound above 0 and a
lead over the runner-up (`resampled_gaps`: bootstrap over the held-out tiles and the
simulation seeds). No refit ends worse than its start on the fitting tiles. What the file
states (`known_sensor`: bit depth and saturation of integer counts) is put into every model
as known (`diagnose_hologram(known=True)`), not diagnosed.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.fft
from scipy import ndimage, optimize, stats

from napari_lbs._core._config import ExperimentConfig
from napari_lbs._core._effects import BASELINE, EFFECTS, OPTICAL_EFFECTS, check_effects, optical_hologram, sensor_image
from napari_lbs._core._io import InputError, as_hologram, atomic_path, atomic_write_bytes, write_json
from napari_lbs._core._optics import transfer_function
from napari_lbs._core._progress import ProgressCallback, Steps, StopCallback
from napari_lbs._core._synthesis import random_particle_field

__all__ = ["tile_summaries", "measured_fringe", "gap_statistic", "real_spread", "write_report", "where_gap", "diagnose_tiles", "diagnose_hologram", "DiagnosisSettings", "Diagnosis", "TileLayout", "field_surroundings", "known_sensor", "adapted_tile_px", "resampled_gaps", "SUMMARY_GROUPS", "MIN_TILE_PX"]

SUMMARY_GROUPS = ("band", "depth", "region", "intensity", "noise", "appearance")
_BANDS = np.geomspace(1 / 64, 0.5, 9)  # cycles per pixel: 8 bands
_LAGS = (1, 2, 4, 8, 16)
# A verdict needs the best effect to remove at least this much excess χ² on held-out tiles
# (refitting a null model to noise removes less: the controls of the suite), both against the
# baseline and against its own fit with the effect switched off, and this share of the gap.
_VERDICT_MIN_REDUCTION = 0.5
_VERDICT_MIN_SHRINK = 0.3
_DESIGN_POINTS = 16  # Sobol points tried by a fit that adds parameters
_MIN_EVALUATIONS = 8  # each fit stage runs at least this many evaluations (see `_fit`)
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
    normally the experiment's strongest spectral peak (`measured_fringe`); real and simulated
    tiles must be summarised with the same one. Default: this tile's own strongest peak.

    ``field_mean`` (the mean of the whole image the tile was cut from; default the tile's own)
    and ``surroundings`` (`field_surroundings`: the field around the tile, twice its size,
    NaN outside the field; default none: tilt and curvature 0) give the field-wide envelope: the tile's
    brightness against the field's, and the tilt and curvature of the log brightness fitted
    over the surroundings. A smooth vignetting has nearly the same curvature at every tile,
    so it stands out of the particles' tile-to-tile fluctuation where a tile's mean does not.
    """
    image = np.asarray(tile, np.float64)
    tile_mean = image.mean()
    image = image / tile_mean
    rows, cols = image.shape
    values: list[float] = []
    names: list[tuple[str, str]] = []

    def add(name, group, value):
        values.append(float(value))
        names.append((name, group))

    # band: radially averaged power of the Hann-windowed fluctuation, 8 log bands
    power = _power_spectrum(image)
    radius = np.hypot(*np.meshgrid(np.fft.fftfreq(rows), np.fft.fftfreq(cols), indexing="ij"))
    for low, high in zip(_BANDS[:-1], _BANDS[1:], strict=True):
        band = power[(radius >= low) & (radius < high)]
        add(f"log power {low:.3f}-{high:.3f} cyc/px", "band", np.log10(band.mean() + 1e-12))
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
    planes = planes / np.median(planes.reshape(len(depths), -1), axis=1)[:, None, None]  # background ≈ 1 in every plane
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
    for q, value in zip((0.99, 0.999), np.quantile(brightest, (0.99, 0.999)), strict=True):
        add(f"focal spots: q{q} of the brightest plane", "appearance", value)
    for q, value in zip((0.001, 0.01), np.quantile(darkest, (0.001, 0.01)), strict=True):
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
    for q, value in zip(quantiles, np.quantile(image, quantiles), strict=True):
        add(f"quantile {q}", "intensity", value)
    add("skewness", "intensity", stats.skew(image.ravel()))
    add("log kurtosis", "intensity", np.log10(stats.kurtosis(image.ravel(), fisher=False)))
    add("clipped fraction", "intensity", np.mean(image >= image.max() - 1e-9 * abs(image.max())))
    # noise character
    residual = image - ndimage.gaussian_filter(image, 1.0)
    add("log residual std", "noise", np.log10(residual.std() + 1e-12))
    blocks = (rows // 16) * 16, (cols // 16) * 16
    block_mean = image[: blocks[0], : blocks[1]].reshape(blocks[0] // 16, 16, blocks[1] // 16, 16).mean(axis=(1, 3)).ravel()
    block_var = residual[: blocks[0], : blocks[1]].reshape(blocks[0] // 16, 16, blocks[1] // 16, 16).var(axis=(1, 3)).ravel()
    slope = np.polyfit(block_mean, block_var, 1)[0] if np.ptp(block_mean) > 0 else 0.0
    add("residual variance vs mean slope", "noise", slope / (block_var.mean() + 1e-12))
    smooth = ndimage.gaussian_filter(image, 2.0)
    dark, bright = np.quantile(smooth, [0.25, 0.75])
    # photon noise grows with the signal: residual variance in the bright quarter over the dark quarter
    add("log residual variance bright/dark", "noise", np.log10((residual[smooth >= bright].var() + 1e-12) / (residual[smooth <= dark].var() + 1e-12)))
    add("log distinct levels", "noise", np.log10(np.unique(np.round(image / (image.std() + 1e-12), 6)).size))
    # appearance: autocorrelation of the fringes at a few lags
    centred = image - 1.0
    norm = (centred**2).mean() + 1e-12
    for lag in _LAGS:
        add(f"autocorrelation at {lag} px", "appearance", 0.5 * ((centred[lag:] * centred[:-lag]).mean() + (centred[:, lag:] * centred[:, :-lag]).mean()) / norm)
    return np.asarray(values), names


_ENVELOPE_BLOCKS = 16  # blocks per axis of a tile's surroundings (8 per tile edge)


def field_surroundings(field: np.ndarray, origin: tuple[int, int], tile_shape: tuple[int, int]) -> np.ndarray:
    """The field around a tile: twice the tile's size, centred on it, NaN outside the field (float64)."""
    rows, cols = tile_shape
    top, left = origin[0] - rows // 2, origin[1] - cols // 2
    region = np.full((2 * rows, 2 * cols), np.nan)
    r0, c0 = max(top, 0), max(left, 0)
    r1, c1 = min(top + 2 * rows, field.shape[0]), min(left + 2 * cols, field.shape[1])
    region[r0 - top : r1 - top, c0 - left : c1 - left] = field[r0:r1, c0:c1]
    return region


def _envelope(surroundings: np.ndarray, field_mean: float) -> tuple[float, float]:
    """Tilt |∇| and curvature (∂²/∂x² + ∂²/∂y²)/2 of log brightness over a tile's surroundings, in tile edges.

    The surroundings are averaged in 16 × 16 blocks (blocks holding NaN, outside the field,
    are left out) and ``log(block mean / field_mean)`` is fitted with 1, x, y, x², y² about the
    tile's centre.
    """
    rows, cols = surroundings.shape
    blocks = surroundings[: rows - rows % _ENVELOPE_BLOCKS, : cols - cols % _ENVELOPE_BLOCKS].reshape(_ENVELOPE_BLOCKS, rows // _ENVELOPE_BLOCKS, _ENVELOPE_BLOCKS, cols // _ENVELOPE_BLOCKS).mean(axis=(1, 3))
    centres = (np.arange(_ENVELOPE_BLOCKS) + 0.5) / _ENVELOPE_BLOCKS * 2.0 - 1.0  # tile edges from the tile's centre
    y, x = np.meshgrid(centres, centres, indexing="ij")
    valid = np.isfinite(blocks) & (blocks > 0)
    design = np.stack([np.ones(valid.sum()), x[valid], y[valid], x[valid] ** 2, y[valid] ** 2], axis=1)
    coefficients = np.linalg.lstsq(design, np.log(blocks[valid] / field_mean), rcond=None)[0]
    return float(np.hypot(coefficients[1], coefficients[2])), float(coefficients[3] + coefficients[4])


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
    return scipy.fft.ifft2(scipy.fft.fft2(image.astype(np.complex64))[None] * kernels, workers=-1, overwrite_x=True)


def _power_spectrum(image: np.ndarray) -> np.ndarray:
    """Power of the Hann-windowed fluctuation of a mean-normalised image."""
    rows, cols = image.shape
    window = np.outer(np.hanning(rows), np.hanning(cols))
    return np.abs(np.fft.fft2((image - 1.0) * window)) ** 2 / window.sum()


def real_spread(real: np.ndarray) -> np.ndarray:
    """Real-vs-real spread of each summary: its std across the experiment's tiles, floored at 1 % of its size."""
    return np.maximum(real.std(axis=0, ddof=1), 0.01 * np.abs(real.mean(axis=0)) + 1e-4)


def gap_statistic(real: np.ndarray, sim: np.ndarray, *, spread: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Excess standardised χ² between two summary matrices (tiles x K) and the per-summary z.

    ``spread`` is the per-summary noise scale (default `real_spread` of ``real``); the
    difference of the two means is divided by ``spread * sqrt(1/n_real + 1/n_sim)``.
    """
    spread = real_spread(real) if spread is None else spread
    z = (real.mean(axis=0) - sim.mean(axis=0)) / (spread * np.sqrt(1.0 / len(real) + 1.0 / len(sim)))
    return max(0.0, float(np.mean(np.minimum(z**2, 1e4))) - 1.0), z


def where_gap(real: np.ndarray, sim: np.ndarray, names: list[tuple[str, str]]) -> dict:
    """Where the gap lies: per group, per band, per depth and per real tile, in real-vs-real units."""
    spread = np.sqrt(2.0) * real_spread(real)
    distance = np.abs(real.mean(axis=0) - sim.mean(axis=0)) / spread
    groups = np.array([g for _, g in names])
    labels = [n for n, _ in names]
    by_group = {g: float(np.sqrt(np.mean(distance[groups == g] ** 2))) for g in SUMMARY_GROUPS if np.any(groups == g)}
    per_tile = np.sqrt(np.mean(((real - sim.mean(axis=0)) / spread) ** 2, axis=1))
    return {
        "by_group": by_group,
        "by_band": [{"band": labels[i], "distance": float(distance[i])} for i in np.flatnonzero(groups == "band")],
        "by_depth": [{"summary": labels[i], "distance": float(distance[i])} for i in np.flatnonzero(groups == "depth")],
        "by_region": [float(v) for v in per_tile],
        "summaries": [{"name": labels[i], "group": groups[i], "real": float(real[:, i].mean()), "sim": float(sim[:, i].mean()), "distance": float(distance[i])} for i in range(len(labels))],
    }


@dataclass(frozen=True)
class DiagnosisSettings:
    """How hard to look.

    ``sim_tiles`` simulated tiles per model; ``evaluations`` per fit; ``confirm`` how many
    effects, in order of screening significance, are refitted (default all: the linear
    screening misses effects the baseline over-compensates, e.g. shot noise absorbed by read
    noise); the others get the best of a coarse off/weak/strong scan; ``resamples`` bootstrap
    draws for the intervals and the verdict's confidence.
    """

    sim_tiles: int = 8
    evaluations: int = 40
    confirm: int = len(EFFECTS)
    resamples: int = 2000
    seed: int = 0

    def __post_init__(self) -> None:
        for name, low in (("sim_tiles", 2), ("evaluations", _MIN_EVALUATIONS), ("confirm", 0), ("resamples", 100), ("seed", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InputError(f"{name}: expected an integer of at least {low}, got {value!r}")


@dataclass
class Diagnosis:
    """The report (CONTRACT.md ``report.json``) plus what the figures need."""

    report: dict
    names: list
    real: np.ndarray = field(repr=False)
    baseline_sim: np.ndarray = field(repr=False)
    seconds: float = 0.0


@dataclass(frozen=True)
class TileLayout:
    """Where the real tiles were cut from one hologram.

    Attributes
    ----------
    field_shape : (int, int)
        The hologram's (rows, cols) in pixels.
    origins : tuple of (int, int)
        Each tile's top-left (row, col) in pixels, in the order of the tiles.
    field_mean : float
        The hologram's mean intensity (the unit of the field-wide envelope summaries).
    """

    field_shape: tuple[int, int]
    origins: tuple[tuple[int, int], ...]
    field_mean: float

    def fitting(self, tile_shape: tuple[int, int]) -> np.ndarray:
        """Which tiles are fitted (True) and which held out: a checkerboard, so both halves span the field."""
        return np.array([(r // tile_shape[0] + c // tile_shape[1]) % 2 == 0 for r, c in self.origins])


class _Model:
    """Simulated tiles of one effect set, with fixed fields and noise (common random numbers).

    With a `TileLayout` the simulation makes whole fields of the hologram's shape (so a
    field-wide envelope spans them as it spans the experiment) and cuts ``sim_tiles`` tiles at
    the real tiles' positions, spread over the field; without one, each simulated tile is a
    field of its own and the "field" is the set of simulated tiles. ``known`` effects (with
    fixed parameters: what the file states) are part of every model.
    """

    def __init__(self, config: ExperimentConfig, *, shape, count: int, settings: DiagnosisSettings, fringe_frequency: tuple[float, float], layout: TileLayout | None, known: dict) -> None:
        self.config = config
        self.fringe_frequency = fringe_frequency
        self.known = known
        self.shape = tuple(shape)
        field_shape = tuple(layout.field_shape) if layout is not None else self.shape
        if layout is not None:
            picked = np.round(np.linspace(0, len(layout.origins) - 1, min(settings.sim_tiles, len(layout.origins)))).astype(int)
            places = [layout.origins[i] for i in picked]
        else:
            places = [(0, 0)]
        fields = -(-settings.sim_tiles // len(places))
        self.cuts = [(index // len(places), places[index % len(places)]) for index in range(settings.sim_tiles)]
        self.whole_fields = layout is not None
        field_count = max(1, round(count * field_shape[0] * field_shape[1] / (self.shape[0] * self.shape[1])))
        rng = np.random.default_rng([settings.seed, 11])
        self.fields = [
            random_particle_field(field_shape, count=field_count, diameter_min_um=config.particles.diameter_min_um, diameter_max_um=config.particles.diameter_max_um, layers_um=config.layer_depths_um(), pixel_um=config.optics.pixel_um, seed=rng)
            for _ in range(fields)
        ]
        self.noise = [rng.standard_normal(field_shape).astype(np.float32) for _ in range(fields)]
        self._optical: dict[tuple, list[np.ndarray]] = {}

    def optical(self, effects: dict) -> list[np.ndarray]:
        key = tuple(sorted((k, tuple(sorted(v.items()))) for k, v in effects.items() if k in OPTICAL_EFFECTS))
        if key not in self._optical:
            optical = {k: v for k, v in effects.items() if k in OPTICAL_EFFECTS}
            self._optical[key] = [optical_hologram(f, optical, wavelength_um=self.config.optics.wavelength_um, medium_index=self.config.optics.medium_index) for f in self.fields]
        return self._optical[key]

    def summaries(self, baseline: dict, effects: dict) -> np.ndarray:
        effects = {**self.known, **effects}
        sensor = {k: v for k, v in effects.items() if k not in OPTICAL_EFFECTS}
        images = [sensor_image(intensity, baseline, sensor, noise=noise) for intensity, noise in zip(self.optical(effects), self.noise, strict=True)]
        rows, cols = self.shape
        tiles = [images[f][r : r + rows, c : c + cols] for f, (r, c) in self.cuts]
        # the field a tile is measured against: its own image, or (no layout) the whole set
        if self.whole_fields:
            field_means = [float(image.mean()) for image in images]
            around = [field_surroundings(images[f], origin, self.shape) for f, origin in self.cuts]
        else:
            field_means = [float(np.mean([t.mean() for t in tiles]))] * len(images)
            around = [None] * len(tiles)
        return np.stack([
            tile_summaries(t, config=self.config, fringe_frequency=self.fringe_frequency, field_mean=field_means[f], surroundings=region)[0]
            for t, (f, _), region in zip(tiles, self.cuts, around, strict=True)
        ])


def _fit(model: _Model, real: np.ndarray, effect_ids: Sequence[str], *, start: dict, measured: dict, evaluations: int, spread: np.ndarray) -> tuple[dict, dict, float]:
    """Fit the baseline and the listed effects' parameters to ``real`` (in unit coordinates; returns baseline, effects, χ²).

    ``measured`` maps (effect, parameter) to a value read off the real tiles (e.g. the fringe
    period), held fixed; optical parameters are searched on a small grid (each point
    re-simulates the fields); new continuous parameters are searched globally, then polished.
    """
    bounds = [(("baseline", name), b) for name, b in BASELINE.bounds.items()]
    photon_transfer = "shot_noise" in effect_ids
    if photon_transfer:
        # Read and photon noise as a camera's photon-transfer curve: the total noise at the mean
        # level and the share of its variance that grows with the signal. In (sigma, photons) the
        # good fits lie along a curved valley of constant total noise; here it is a straight axis.
        bounds[[key for key, _ in bounds].index(("baseline", "sigma"))] = (("noise", "total"), BASELINE.bounds["sigma"])
        bounds.append((("noise", "photon_share"), (0.0, 1.0)))
        start = {**start, ("noise", "total"): start.get(("baseline", "sigma"), 0.05), ("noise", "photon_share"): 0.0}
    grid_params = {}
    for effect in effect_ids:
        for name, (low, high) in EFFECTS[effect].bounds.items():
            if (effect, name) in measured or (photon_transfer and effect == "shot_noise"):
                continue
            if effect in OPTICAL_EFFECTS:
                grid_params[(effect, name)] = (low, high)
            else:
                bounds.append(((effect, name), (low, high)))

    def unpack(unit, optical):
        params = {"baseline": {}, "noise": {}, **{e: dict(EFFECTS[e].neutral) for e in effect_ids}}
        for (key, (low, high)), u in zip(bounds, np.clip(unit, 0, 1), strict=True):
            params[key[0]][key[1]] = _from_unit(key, float(u), low, high)
        if photon_transfer:
            total, share = params["noise"]["total"], params["noise"]["photon_share"]
            params["baseline"]["sigma"] = float(total * np.sqrt(1.0 - share))
            # photon variance at the mean level is 1/N: N = 1 / (share · total²), "off" at most
            params["shot_noise"]["log10_photons"] = float(min(-np.log10(share * total**2 + 1e-300), EFFECTS["shot_noise"].neutral["log10_photons"]))
        for (effect, name), value in {**optical, **{k: v for k, v in measured.items() if k[0] in effect_ids}}.items():
            params[effect][name] = value
        return params["baseline"], {e: params[e] for e in effect_ids}

    def loss(unit, optical):
        baseline, effects = unpack(unit, optical)
        return gap_statistic(real, model.summaries(baseline, effects), spread=spread)[0]

    # the previous optimum, with each new parameter at its weakest in-bounds setting (nearest to off)
    x0 = np.array([_to_unit(key, start[key] if key in start else (EFFECTS[key[0]].neutral[key[1]] if key[0] in EFFECTS else (low + high) / 2), low, high) for key, (low, high) in bounds])
    is_new = np.array([key not in start for key, _ in bounds])
    grid_points = [{}]
    for key, (low, high) in grid_params.items():
        values = [low] if low == high else list(np.linspace(low, high, 4)[1:])
        grid_points = [{**point, key: v} for point in grid_points for v in values]
    nelder_mead = {"xatol": 1e-3, "fatol": 1e-3}
    if len(grid_points) == 1 and is_new.any():
        # New continuous parameters: precise summaries (noise level, bit depth) make narrow,
        # curved valleys in which a simplex from one start stalls, and an added effect often
        # needs the baseline's parameters to move too (blur matters only once there is noise to
        # blur). So: the previous optimum (with the new parameters at their weakest setting
        # and at 20/50/80 % of their range), the best of a space-filling design, and a global
        # search (DIRECT-L) compete, and the best of them is polished with a simplex.
        design = [x0, *[np.where(is_new, u, x0) for u in (0.2, 0.5, 0.8)], *stats.qmc.Sobol(len(x0), seed=0).random(_DESIGN_POINTS)]
        searched = optimize.direct(loss, [(0.0, 1.0)] * len(x0), args=({},), maxfun=max(evaluations // 2, 8), locally_biased=True)
        first = min([(loss(x, {}), x) for x in design] + [(searched.fun, searched.x)], key=lambda pair: pair[0])[1]
        result = optimize.minimize(loss, first, args=({},), method="Nelder-Mead", options={"maxfev": max(evaluations // 2, 8), "initial_simplex": _simplex(first, 0.1), **nelder_mead})
        best = (float(result.fun), result.x, {})
    else:
        # optical parameters: a short fit at each grid point from the previous optimum, then the
        # rest of the budget on the best point
        best = (np.inf, None, None)
        per_point = max(evaluations // (2 * len(grid_points)), 8) if len(grid_points) > 1 else evaluations
        for optical in grid_points:
            result = optimize.minimize(loss, x0, args=(optical,), method="Nelder-Mead", options={"maxfev": per_point, "initial_simplex": _simplex(x0), **nelder_mead})
            if result.fun < best[0]:
                best = (float(result.fun), result.x, optical)
        if len(grid_points) > 1:
            result = optimize.minimize(loss, best[1], args=(best[2],), method="Nelder-Mead", options={"maxfev": evaluations, "initial_simplex": _simplex(np.clip(best[1], 0, 1)), **nelder_mead})
            if result.fun < best[0]:
                best = (float(result.fun), result.x, best[2])
    baseline, effects = unpack(best[1], best[2])
    # Never end worse than the start on the fitting tiles: the start (the previous optimum, the
    # new effects switched off) is itself a model of this family.
    if all(("baseline", name) in start for name in BASELINE.bounds):
        start_baseline = {name: start[("baseline", name)] for name in BASELINE.bounds}
        start_effects = {e: {**EFFECTS[e].neutral, **{k: v for (owner, k), v in start.items() if owner == e}} for e in effect_ids}
        start_gap = gap_statistic(real, model.summaries(start_baseline, start_effects), spread=spread)[0]
        if start_gap <= best[0]:
            return start_baseline, start_effects, start_gap
    return baseline, effects, best[0]


# Fitted on a log scale: a noise level matters by its order of magnitude, and a linear scale
# would leave the small values a real camera has squeezed against the lower bound.
_LOG_SCALED = {("baseline", "sigma"), ("noise", "total")}


def _from_unit(key: tuple, unit: float, low: float, high: float) -> float:
    if key in _LOG_SCALED:
        return float(low * (high / low) ** unit)
    return low + (high - low) * unit


def _to_unit(key: tuple, value: float, low: float, high: float) -> float:
    if high <= low:
        return 0.5
    if key in _LOG_SCALED:
        return float(np.clip(np.log(max(value, low) / low) / np.log(high / low), 0.0, 1.0))
    return float(np.clip((value - low) / (high - low), 0.0, 1.0))


def _simplex(x0: np.ndarray, size: float = 0.25) -> np.ndarray:
    step = np.where(x0 > 0.5, -size, size)
    return np.vstack([x0] + [x0 + np.eye(len(x0))[i] * step[i] for i in range(len(x0))])


def _with_measured(effect_id: str, setting: dict, measured: dict) -> dict:
    """An effect setting with the parameters measured on the real tiles put in."""
    return {**setting, **{name: value for (effect, name), value in measured.items() if effect == effect_id}}


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


def measured_fringe(tiles: Sequence[np.ndarray]) -> tuple[float, float]:
    """Frequency (fy, fx) in cycles/px of a static fringe: the peak of the tiles' mean power spectrum.

    An etalon fringe has the same frequency in every tile, so it adds up in the mean spectrum
    while the particles' rings (random positions) average into a smooth background. Only
    frequencies within the `parasitic_fringes` period bounds are searched.
    """
    # geometric mean over tiles: a particle's speckle-like power fluctuates from tile to tile, a fringe's does not
    return _peak_frequency(np.exp(np.mean([np.log(_power_spectrum(np.asarray(t, np.float64) / np.mean(t)) + 1e-30) for t in tiles], axis=0)))


def _fringe_parameters(frequency: tuple[float, float]) -> dict:
    """The `parasitic_fringes` period (px) and angle (rad) of a frequency (fy, fx)."""
    fy, fx = frequency
    return {("parasitic_fringes", "period_px"): float(1.0 / np.hypot(fy, fx)), ("parasitic_fringes", "angle_rad"): float(np.arctan2(fy, fx) % np.pi)}


def resampled_gaps(real: np.ndarray, sims: dict, *, spread: np.ndarray, resamples: int, seed: int = 0) -> dict:
    """Each model's gap on bootstrap resamples of what the gap depends on.

    Parameters
    ----------
    real : (n_real, K) array
        Summaries of the real tiles the gap is measured on.
    sims : dict of (n_sim, K) arrays
        Each model's simulated summaries; row i of every model comes from the same simulated
        field and noise (common random numbers), so one draw of simulation seeds serves all.
    spread : (K,) array
        The per-summary unit (`real_spread`), held fixed.
    resamples : int
        Bootstrap draws: real tiles and simulation seeds, each drawn with replacement, paired
        across models (differences between models keep their correlation).

    Returns
    -------
    dict of (resamples,) arrays, one per model.
    """
    rng = np.random.default_rng([seed, 17])
    n_real, n_sim = len(real), len(next(iter(sims.values())))
    real_means = real[rng.integers(0, n_real, (resamples, n_real))].mean(axis=1)
    sim_draw = rng.integers(0, n_sim, (resamples, n_sim))
    scale = spread * np.sqrt(1.0 / n_real + 1.0 / n_sim)
    return {name: np.maximum(0.0, np.mean(np.minimum(((real_means - sim[sim_draw].mean(axis=1)) / scale) ** 2, 1e4), axis=1) - 1.0) for name, sim in sims.items()}


def _decision(entries: list, draws: dict, *, baseline_gap: float, held_out: int) -> dict:
    """The verdict from the confirmed effects' held-out gaps and their bootstrap draws (see `diagnose_tiles`).

    An effect is named only when (a) its reduction of the gap, against the baseline and against
    its own fit with the effect switched off, is at least ``_VERDICT_MIN_REDUCTION`` and
    ``_VERDICT_MIN_SHRINK`` of the baseline, and its lower confidence bound is above 0; and
    (b) its lead over the runner-up has a lower confidence bound above 0. Bounds are one-sided
    at 95 %, Bonferroni-corrected for the number of effects compared (the best of several is
    picked). ``tiles_to_decide``: held-out tiles at which the weaker of the two margins would
    reach its bound, if margin / bootstrap error grows as sqrt(tiles).
    """
    ranked = sorted(entries, key=lambda e: e["gap_after"])
    alpha = 0.05 / max(len(ranked), 1)
    z_needed = float(stats.norm.ppf(1.0 - alpha))
    verdict = {"id": None, "shrink": 0.0, "residual": float(baseline_gap), "interval": [0.0, 0.0], "runner_up": None, "confidence": 1.0 - alpha}
    if not ranked:
        return {**verdict, "reason": "no effect was refitted", "tiles_to_decide": None}
    best = ranked[0]
    against = np.minimum(draws["baseline"], draws[f"{best['id']} off"])
    reduction = against - draws[best["id"]]
    point_reduction = min(baseline_gap, best["gap_ablated"]) - best["gap_after"]
    margins = [(point_reduction, reduction)]
    runner = ranked[1] if len(ranked) > 1 else None
    if runner is not None:
        margins.append((runner["gap_after"] - best["gap_after"], draws[runner["id"]] - draws[best["id"]]))
    ratios = [point / max(float(np.std(samples)), 1e-12) for point, samples in margins]
    tiles = [int(np.ceil(held_out * (z_needed / ratio) ** 2)) if ratio > 0 else None for ratio in ratios]
    tiles_to_decide = None if None in tiles else max(tiles)
    verdict.update({"runner_up": runner["id"] if runner else None, "tiles_to_decide": tiles_to_decide})
    low_reduction = float(np.quantile(reduction, alpha))
    if point_reduction < _VERDICT_MIN_REDUCTION or best["shrink"] < _VERDICT_MIN_SHRINK or low_reduction <= 0:
        verdict["reason"] = f"gap within what {held_out} held-out tiles can resolve: " + (
            f"the best effect, {best['id']}, removes {point_reduction:.2f} of {baseline_gap:.2f} (lower bound {low_reduction:.2f})"
            if point_reduction > 0
            else f"no refitted effect lowers the gap of {baseline_gap:.2f}"
        )
        return verdict
    if runner is not None and float(np.quantile(margins[1][1], alpha)) <= 0:
        verdict["reason"] = f"two effects indistinguishable: {best['id']} ({best['gap_after']:.2f}) and {runner['id']} ({runner['gap_after']:.2f}) on {held_out} held-out tiles"
        return verdict
    verdict.update({"id": best["id"], "shrink": best["shrink"], "residual": best["gap_after"], "interval": best["shrink_interval"]})
    verdict["reason"] = f"{best['id']} removes {point_reduction:.2f} of {baseline_gap:.2f} (lower bound {low_reduction:.2f}) and leads {runner['id'] if runner else 'nothing'}"
    return verdict


def diagnose_tiles(
    real_tiles: Sequence[np.ndarray],
    config: ExperimentConfig,
    *,
    layout: TileLayout | None = None,
    known: dict | None = None,
    settings: DiagnosisSettings = DiagnosisSettings(),
    particles_per_tile: int | None = None,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> Diagnosis:
    """Diagnose the gap between real hologram tiles and the seed's simulator.

    Parameters
    ----------
    real_tiles : sequence of (rows, cols) arrays
        At least 4 tiles of the experiment (same shape, positive mean intensity).
    config : ExperimentConfig
        Optics, depths and particle sizes of the simulator.
    layout : TileLayout, optional
        Where the tiles were cut from one hologram: the simulation then makes whole fields and
        the tiles are split into fitting and held-out halves as a checkerboard. Without it,
        alternate tiles are fitted and held out, and each simulated tile is a field of its own.
    known : dict, optional
        ``{effect_id: params}``: effects the experiment states (e.g. the file's bit depth),
        put into every model with fixed parameters and not diagnosed.
    settings : DiagnosisSettings
    particles_per_tile : int, optional
        Particles per simulated tile; default ``per_tile`` scaled to the tile area.
    progress, should_stop
        One step per fit (baseline, screening, each confirmation, the waterfall); a stop
        raises `Stopped`.
    """
    start = time.perf_counter()
    tiles = [np.asarray(t, np.float32) for t in real_tiles]
    if len(tiles) < 4:
        raise InputError(f"real tiles: expected at least 4 tiles (half to fit, half to score), got {len(tiles)}")
    shape = tiles[0].shape
    if any(t.shape != shape for t in tiles):
        raise InputError("real tiles: expected tiles of one shape")
    means = np.array([t.mean() for t in tiles])
    if not np.all(np.isfinite(means)) or np.any(means <= 0):
        raise InputError("real tiles: expected finite intensities with a positive mean in every tile")
    known = check_effects(known or {})
    candidates = [e for e in EFFECTS if e not in known]
    count = particles_per_tile if particles_per_tile is not None else max(1, round(config.particles.per_tile * shape[0] * shape[1] / config.tile.size**2))
    fitting = layout.fitting(shape) if layout is not None else np.arange(len(tiles)) % 2 == 0
    fringe_frequency = measured_fringe([t for t, fit in zip(tiles, fitting, strict=True) if fit])  # from the fitting half only
    measured = _fringe_parameters(fringe_frequency)
    if layout is not None:
        # the field the tiles cover, reassembled: each tile's surroundings come from it
        field = np.full(layout.field_shape, np.nan)
        for t, (r, c) in zip(tiles, layout.origins, strict=True):
            field[r : r + shape[0], c : c + shape[1]] = t
        around = [field_surroundings(field, origin, shape) for origin in layout.origins]
        field_mean = layout.field_mean
    else:
        around, field_mean = [None] * len(tiles), float(means.mean())
    summaries = [tile_summaries(t, config=config, fringe_frequency=fringe_frequency, field_mean=field_mean, surroundings=region) for t, region in zip(tiles, around, strict=True)]
    names = summaries[0][1]
    real = np.stack([s[0] for s in summaries])
    fit_real, held_real = real[fitting], real[~fitting]
    spread = real_spread(real)  # the experiment's own tile-to-tile spread: the unit of every gap
    gap = lambda a, b: gap_statistic(a, b, spread=spread)  # noqa: E731
    model = _Model(config, shape=shape, count=count, settings=settings, fringe_frequency=fringe_frequency, layout=layout, known=known)
    confirmed = min(settings.confirm, len(candidates))
    steps = Steps(2 + confirmed + 1, progress=progress, should_stop=should_stop)

    steps.check()
    base_params, _, base_fit_gap = _fit(model, fit_real, [], start={}, measured=measured, evaluations=settings.evaluations, spread=spread)
    base_sim = model.summaries(base_params, {})
    baseline_gap = gap(held_real, base_sim)[0]
    held_sims = {"baseline": base_sim}  # every model's held-out simulation, for the resampling
    steps.advance()

    # screen: regress the standardised residual on each effect's signature (finite difference)
    steps.check()
    _, z_residual = gap(fit_real, base_sim)
    screening = {}
    for effect_id in candidates:
        signature_sim = model.summaries(base_params, {effect_id: _with_measured(effect_id, EFFECTS[effect_id].injections[1], measured)})
        _, signature = gap(signature_sim, base_sim)  # how far the effect moves the simulation, in z units
        norm = float(signature @ signature)
        coefficient = float(z_residual @ signature) / norm if norm > 0 else 0.0
        residual = z_residual - coefficient * signature
        dof = max(len(signature) - 1, 1)
        error = np.sqrt(float(residual @ residual) / dof / norm) if norm > 0 else np.inf
        screening[effect_id] = {"coefficient": coefficient, "t": coefficient / error if error > 0 else 0.0, "explained": 1.0 - float(residual @ residual) / max(float(z_residual @ z_residual), 1e-12)}
    steps.advance()

    # Confirm the effects whose fingerprint is most significant, whichever its sign: the
    # baseline's own parameters may already have over-compensated for the missing effect.
    refitted = sorted(candidates, key=lambda e: -abs(screening[e]["t"]))[:confirmed]
    effects_report = []
    fitted = {}
    for effect_id in candidates:
        entry = {"id": effect_id, "screening": screening[effect_id], "confirmed": effect_id in refitted}
        if effect_id in refitted:
            steps.check()
            start_params = {("baseline", k): v for k, v in base_params.items()}
            baseline_params, effect_params, fit_gap = _fit(model, fit_real, [effect_id], start=start_params, measured=measured, evaluations=settings.evaluations, spread=spread)
            entry["gap_fit"] = float(fit_gap)  # on the fitting tiles: never above the baseline's (`_fit` keeps its start)
            held_sims[effect_id] = model.summaries(baseline_params, effect_params)
            gap_after = gap(held_real, held_sims[effect_id])[0]
            # ablation at the optimum: the same fit with the effect switched off. A refit can
            # lower the gap by moving the baseline alone (out of an over-fitted optimum of
            # the fitting tiles); only what switching the effect on adds is the effect's.
            held_sims[f"{effect_id} off"] = model.summaries(baseline_params, {})
            entry["gap_ablated"] = float(gap(held_real, held_sims[f"{effect_id} off"])[0])
            fitted[effect_id] = (baseline_params, effect_params)
            entry["params"] = {**effect_params[effect_id], **{f"baseline.{k}": v for k, v in baseline_params.items()}}
            steps.advance()
        else:
            # not refitted: the best of a coarse scan (off, weak, strong) with the baseline's parameters
            scan = [(baseline_gap, dict(EFFECTS[effect_id].neutral))]
            settings_scanned = [_with_measured(effect_id, setting, measured) for setting in EFFECTS[effect_id].injections]
            scan += [(gap(held_real, model.summaries(base_params, {effect_id: setting}))[0], setting) for setting in settings_scanned]
            gap_after, entry["params"] = min(scan, key=lambda pair: pair[0])
        entry["gap_after"] = float(gap_after)
        entry["shrink"] = float(1.0 - gap_after / baseline_gap) if baseline_gap > 0 else 0.0
        effects_report.append(entry)

    # evidence with its uncertainty: resample the held-out real tiles and the simulation seeds
    draws = resampled_gaps(held_real, held_sims, spread=spread, resamples=settings.resamples, seed=settings.seed)
    for entry in effects_report:
        if entry["confirmed"]:
            reduction = draws["baseline"] - draws[entry["id"]]
            # shrink's interval: the reduction's 90 % interval over the measured baseline gap
            low, high = np.quantile(reduction, (0.05, 0.95)) / baseline_gap if baseline_gap > 0 else (0.0, 0.0)
            entry["shrink_interval"] = [float(low), float(high)]
    effects_report.sort(key=lambda e: (not e["confirmed"], e["gap_after"]))
    verdict = _decision([e for e in effects_report if e["confirmed"]], draws, baseline_gap=baseline_gap, held_out=len(held_real))

    # waterfall: baseline, + best, + best and the runner-up (greedy)
    waterfall = [{"model": "baseline", "gap": float(baseline_gap)}]
    confirmed_sorted = [e for e in effects_report if e["confirmed"]]
    if confirmed_sorted:
        waterfall.append({"model": f"+{confirmed_sorted[0]['id']}", "gap": confirmed_sorted[0]["gap_after"]})
    steps.check()
    if len(confirmed_sorted) > 1:
        pair = [confirmed_sorted[0]["id"], confirmed_sorted[1]["id"]]
        start_params = {("baseline", k): v for k, v in fitted[pair[0]][0].items()}
        start_params.update({(pair[0], k): v for k, v in fitted[pair[0]][1][pair[0]].items()})
        baseline_params, effect_params, _ = _fit(model, fit_real, pair, start=start_params, measured=measured, evaluations=settings.evaluations, spread=spread)
        waterfall.append({
            "model": f"+{pair[0]}+{pair[1]}",
            "gap": float(gap(held_real, model.summaries(baseline_params, effect_params))[0]),
            "params": {effect_id: dict(effect_params[effect_id]) for effect_id in pair},  # the joint fit, for `effects_from_report`
        })
    steps.advance()

    report = {
        "gap": {
            "metric": f"excess standardised chi-square over {len(names)} summaries, held-out real tiles vs simulation (0 = indistinguishable)",
            "baseline": float(baseline_gap),
            "baseline_fit": float(base_fit_gap),
            "baseline_interval": [float(v) for v in np.quantile(draws["baseline"], (0.05, 0.95))],
            "baseline_params": base_params,
            **where_gap(real, base_sim, names),
        },
        "known": known,
        "effects": effects_report,
        "verdict": verdict,
        "waterfall": waterfall,
        "tiles": {
            "real": len(tiles), "fit": len(fit_real), "held_out": len(held_real), "simulated": settings.sim_tiles, "shape": list(shape), "particles_per_tile": count,
            "split": "checkerboard over the hologram" if layout is not None else "alternate tiles",
        },
        "settings": {"sim_tiles": settings.sim_tiles, "evaluations": settings.evaluations, "confirm": settings.confirm, "resamples": settings.resamples, "seed": settings.seed},
    }
    seconds = time.perf_counter() - start
    report["seconds"] = round(seconds, 2)
    return Diagnosis(report, names, real, base_sim, seconds)


# A camera that clips piles its brightest pixels up at one value; a natural image reaches its
# maximum in a handful of pixels. This share of the pixels at the maximum marks saturation.
_PILE_UP = 1e-3


def known_sensor(image: np.ndarray) -> dict | None:
    """What an image of integer counts states about its camera: bit depth and saturation level.

    Parameters
    ----------
    image : 2-D array
        The hologram as recorded: an integer dtype, or floats holding integer counts (what
        `read_hologram` makes of an integer file: float32 holds integers exactly up to 2^24).

    Returns
    -------
    dict or None
        ``bits`` (uint8: 8; otherwise the fewest bits, at least 8, that hold the largest
        count), ``full_scale`` and ``saturation`` (counts: the largest value where at least
        0.1 % of the pixels pile up there, else the full scale), ``saturated_fraction`` and
        ``source``. None for an image that is not integer counts (a float simulation).
    """
    array = np.asarray(image)
    if array.ndim != 2 or array.dtype == bool or array.dtype.kind not in "uif" or array.size == 0:
        return None
    if array.dtype.kind in "ui":
        source = f"{array.dtype} image"
    elif np.all(np.isfinite(array)) and np.all(array == np.round(array)):
        source = "integer counts in a float image"
    else:
        return None
    low, high = float(array.min()), float(array.max())
    if low < 0 or high <= 0 or high > 2**16 - 1:
        return None
    bits = 8 if array.dtype == np.uint8 else int(max(8, np.ceil(np.log2(high + 1))))
    full_scale = float(2**bits - 1)
    saturated = float(np.mean(array == high))
    return {"bits": bits, "full_scale": full_scale, "saturation": high if saturated >= _PILE_UP else full_scale, "saturated_fraction": saturated, "source": source}


def adapted_tile_px(shape: tuple[int, int], largest: int, *, tiles: int = 16) -> int:
    """The largest tile edge (px; ``largest`` halved until it fits, not below `MIN_TILE_PX`) that cuts at least ``tiles`` tiles of ``shape``."""
    size = int(largest)
    while size // 2 >= MIN_TILE_PX and (shape[0] // size) * (shape[1] // size) < tiles:
        size //= 2
    return size


def diagnose_hologram(
    hologram: np.ndarray,
    config: ExperimentConfig,
    *,
    background: np.ndarray | None = None,
    tile_px: int | None = None,
    known: bool = True,
    settings: DiagnosisSettings = DiagnosisSettings(),
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> Diagnosis:
    """Diagnose one hologram: cut it into tiles and run `diagnose_tiles` with the field's layout.

    Parameters
    ----------
    hologram : 2-D array
        As recorded (integer counts keep what the file states about the camera).
    tile_px : int, optional
        Tile edge (px). Default: the largest edge up to ``tile.size`` that cuts at least 16
        tiles (512²: 128 px), so the held-out half has 8 tiles to resolve a gap with.
    known : bool
        Put what the file states into every model as known, not diagnosed: for integer
        counts (`known_sensor`), the bit depth and saturation as ``quantization``. Off, or
        with a ``background`` (the division makes the levels uneven), they are diagnosed.
    """
    image = as_hologram(hologram)
    # the array as given keeps its dtype; an RGB one is read from its channel of integer counts
    facts = (known_sensor(hologram) or known_sensor(image)) if known else None
    if background is not None:
        image = image / np.maximum(as_hologram(background, name="background"), 1e-6)
        facts = None
    rows, cols = image.shape
    size = int(tile_px or adapted_tile_px((rows, cols), config.tile.size))
    if size < MIN_TILE_PX:
        raise InputError(f"tile: expected at least {MIN_TILE_PX} pixels (the frequency bands need them), got {size}")
    if size > min(rows, cols):
        raise InputError(f"tile: a {size}-pixel tile is larger than the hologram ({rows}x{cols})")
    origins = tuple((r, c) for r in range(0, rows - size + 1, size) for c in range(0, cols - size + 1, size))
    if len(origins) < 4:
        raise InputError(f"tile: {size}-pixel tiles give {len(origins)} tiles of the {rows}x{cols} hologram; expected at least 4 (use a smaller tile)")
    tiles = [image[r : r + size, c : c + size] for r, c in origins]
    field_mean = float(np.mean([t.mean() for t in tiles]))
    # the sensor's levels in the simulation's unit (the tiles' mean intensity is 1 there)
    # sensor_image spreads 2^bits - 1 levels over [0, saturation]: one count a step only when that is the full scale
    # (a pile-up below full scale, e.g. clipping at 200 of 255, is in `facts` but not simulated)
    known_effects = {"quantization": {"bits": float(facts["bits"]), "saturation": facts["full_scale"] / field_mean}} if facts else {}
    covered = ((rows // size) * size, (cols // size) * size)  # the field the tiles cover
    diagnosis = diagnose_tiles(tiles, config, layout=TileLayout(covered, origins, field_mean), known=known_effects, settings=settings, progress=progress, should_stop=should_stop)
    diagnosis.report["known_sensor"] = facts if facts else {"source": "none: not integer counts, a background was divided out, or switched off"}
    return diagnosis


def write_report(diagnosis: Diagnosis, out_dir, *, provenance: dict | None = None) -> list:
    """Write ``report.json`` (CONTRACT.md), ``report.md`` and PNG figures into ``out_dir``; return the paths."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = {**diagnosis.report, "provenance": provenance or {}}
    gap = report["gap"]
    paths = [write_json(out / "report.json", report)]

    figure = Figure(figsize=(11, 3.4), tight_layout=True)
    axes = figure.subplots(1, 3)
    groups = list(gap["by_group"])
    axes[0].bar(groups, [gap["by_group"][g] for g in groups], color="tab:blue")
    axes[0].axhline(1.0, color="k", lw=0.8, ls="--")
    axes[0].set_ylabel("distance (1 = two real tiles)")
    axes[0].set_title("where: by kind of statistic")
    axes[0].tick_params(axis="x", rotation=45)
    axes[1].plot([b["distance"] for b in gap["by_band"]], "o-", label="spatial-frequency band (low → high)")
    axes[1].plot([d["distance"] for d in gap["by_depth"]], "s-", label="depth summaries (near → far)")
    axes[1].axhline(1.0, color="k", lw=0.8, ls="--")
    axes[1].legend(fontsize=7)
    axes[1].set_title("where: by band and by depth")
    tiles = np.asarray(gap["by_region"])
    side = int(round(np.sqrt(tiles.size)))
    if side * side == tiles.size:
        image = axes[2].imshow(tiles.reshape(side, side), cmap="magma")
        figure.colorbar(image, ax=axes[2])
    else:
        axes[2].bar(range(tiles.size), tiles)
    axes[2].set_title("where: by region (each real tile)")
    with atomic_path(out / "gap_where.png") as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    paths.append(out / "gap_where.png")

    figure = Figure(figsize=(11, 3.4), tight_layout=True)
    axes = figure.subplots(1, 2)
    effects = report["effects"]
    axes[0].barh([e["id"] + ("" if e["confirmed"] else " (screened)") for e in effects][::-1], [max(e["shrink"], -1.0) for e in effects][::-1], color=["tab:green" if e["confirmed"] else "tab:gray" for e in effects][::-1])
    axes[0].axvline(0.0, color="k", lw=0.8)
    axes[0].set_xlabel("shrink of the gap on held-out tiles")
    axes[0].set_title(f"effects ranked; verdict: {report['verdict']['id']}")
    steps = report["waterfall"]
    axes[1].bar([s["model"] for s in steps], [s["gap"] for s in steps], color="tab:purple")
    axes[1].set_ylabel("gap (excess χ²)")
    axes[1].set_title("waterfall: effects added greedily")
    axes[1].tick_params(axis="x", rotation=20)
    with atomic_path(out / "gap_effects.png") as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    paths.append(out / "gap_effects.png")

    verdict = report["verdict"]
    lines = [
        "# Sim-to-real gap diagnosis",
        "",
        f"- Gap between the experiment and the seed's simulator (baseline): **{gap['baseline']:.2f}** ({gap['metric']}).",
        f"- Verdict: **{verdict['id'] or 'none named (null)'}**; shrink {100 * verdict['shrink']:.0f} % "
        f"(90 % interval {100 * verdict['interval'][0]:.0f} to {100 * verdict['interval'][1]:.0f} %), residual gap {verdict['residual']:.2f}. Why: {verdict['reason']}.",
        f"- Data that would decide: {_tiles_to_decide_text(verdict, report['tiles'])}",
        f"- Known, not diagnosed (what the file states): {_known_text(report)}",
        f"- Time: {report['seconds']:.0f} s; tiles: {report['tiles']}.",
        "",
        "## Where the gap lies (1 = as different as two tiles of the experiment)",
        "",
        "| kind | distance |",
        "|---|---|",
        *[f"| {g} | {v:.2f} |" for g, v in gap["by_group"].items()],
        "",
        "Largest single differences:",
        "",
        *[f"- {s['name']} ({s['group']}): real {s['real']:.4g}, simulated {s['sim']:.4g}, distance {s['distance']:.1f}" for s in sorted(gap["summaries"], key=lambda s: -s["distance"])[:8]],
        "",
        "![where](gap_where.png)",
        "",
        "## Effects",
        "",
        "| effect | confirmed (refitted) | gap after | shrink (90 % interval) | gap with it switched off in its own fit | screening t |",
        "|---|---|---|---|---|---|",
        *[
            f"| {e['id']} | {'yes' if e['confirmed'] else 'no'} | {e['gap_after']:.2f} | {100 * e['shrink']:.0f} %"
            f"{' ({:.0f} to {:.0f} %)'.format(*(100 * v for v in e['shrink_interval'])) if 'shrink_interval' in e else ''} | "
            f"{format(e['gap_ablated'], '.2f') if 'gap_ablated' in e else '—'} | {e['screening']['t']:.1f} |"
            for e in effects
        ],
        "",
        "![effects](gap_effects.png)",
        "",
    ]
    paths.append(out / "report.md")
    atomic_write_bytes(out / "report.md", "\n".join(lines).encode("utf-8"))
    return paths


def _tiles_to_decide_text(verdict: dict, tiles: dict) -> str:
    needed = verdict.get("tiles_to_decide")
    if needed is None:
        return "no amount of data: the best effect does not improve on the baseline or on the runner-up."
    if needed <= tiles["held_out"]:
        return f"these {tiles['held_out']} held-out tiles suffice."
    return f"about {needed} held-out tiles of {tiles['shape'][0]}x{tiles['shape'][1]} px (now {tiles['held_out']}), i.e. about {2 * needed} tiles in all, if the margins stay as measured."


def _known_text(report: dict) -> str:
    known = report.get("known") or {}
    if not known:
        return "nothing."
    sensor = report.get("known_sensor", {})
    return "; ".join(f"{effect_id} {params}" for effect_id, params in known.items()) + (f" (from the {sensor['source']})" if "source" in sensor else "") + "."

