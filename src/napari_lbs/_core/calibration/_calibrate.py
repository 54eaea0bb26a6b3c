"""Holo-processing and its calibration to one experimental tile (OCE, seed paper Sec. 2.2).

Holo-processing turns a simulated hologram ``h`` into a reference synthetic image ``I_s``:
add Gaussian noise N(N_R·R, (N_σ·σ)²) (``R = max - min``, ``σ = std`` of ``h``),
back-propagate to the reference planes, take ``|·|``, normalise each plane, apply the gamma
map ``s = r^γ`` and average over planes. An experimental tile becomes ``I_e`` through the same
planes → normalise → average path, inverted so that particles are bright (the seed inverts
its experimental planes, 255 - I). A genetic algorithm (pygad) minimises ``1 - SSIM(I_e, I_s)``.

Two modes:

``seed``
    The seed code's conventions: per-plane min–max stretch to 0–255 uint8, one fixed
    simulated hologram, fresh noise on every evaluation, parameters on a 0.01 grid.
``robust`` (default)
    Fixes the seed mode's weaknesses: float throughout,
    common random numbers (one noise draw per generation shared by all candidates), several
    simulated fields, and the best candidates re-scored on fresh noise before one is returned.

Speed: back-propagation is linear and maps a constant to itself, so the noisy planes are
``B(h) + N_R·R + N_σ·σ·B(n)`` with ``B(h)`` and ``B(n)`` (standard-normal noise) computed once;
an evaluation is then elementwise work plus one SSIM.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import InputError
from napari_lbs._core.physics import backpropagate, propagate
from napari_lbs._core.foundation import ProgressCallback, ReportCallback, Steps, StopCallback, Stopped
from napari_lbs._core.physics import random_particle_field, simulate_hologram
from napari_lbs._core.foundation import thread_pool
from napari_lbs._core.foundation import check_holo_params, check_memory

__all__ = [
    "HoloParams",
    "CalibrationSettings",
    "CalibrationResult",
    "PARAM_BOUNDS",
    "holo_processing",
    "experimental_reference",
    "experimental_planes",
    "choose_reference_tile",
    "reference_planes",
    "calibrate",
    "calibrate_hologram",
    "score_params",
]

PARAM_BOUNDS = {"N_R": (-1.0, 0.0), "N_sigma": (0.2, 0.6), "gamma": (0.6, 1.4)}  # the seed's code
_NOISE_POOL = 16  # independent noise realisations per simulated field
_RESCORE_DRAWS = 8  # fresh noise draws per field when re-scoring the finalists
_FINALISTS = 5
_UNSCORED = -1e9  # the fitness of a candidate left unscored once a stop is requested (a loss is at most 2)


@dataclass(frozen=True)
class HoloParams:
    """Holo-processing parameters: noise mean and width as multiples of R and σ, and the gamma."""

    N_R: float = 0.0
    N_sigma: float = 0.0
    gamma: float = 1.0

    def __post_init__(self) -> None:
        check_holo_params(self.as_dict(), name="params")

    def as_dict(self) -> dict[str, float]:
        return {"N_R": float(self.N_R), "N_sigma": float(self.N_sigma), "gamma": float(self.gamma)}


@dataclass(frozen=True)
class CalibrationSettings:
    """How to fit; the defaults run 100 generations in well under a minute on 2 cores.

    Attributes
    ----------
    mode : {"robust", "seed"}
        See the module docstring.
    generations, population, parents : int
        pygad's ``num_generations``, ``sol_per_pop`` and ``num_parents_mating``.
    runs : int
        Independent GA runs (different seeds); the best is kept.
    fields : int
        Simulated particle fields (``robust`` mode; ``seed`` mode always uses one).
    seed : int
        Seeds the simulated fields, the noise and the GA.
    """

    mode: str = "robust"
    generations: int = 100
    population: int = 12
    parents: int = 4
    runs: int = 1
    fields: int = 3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mode not in ("robust", "seed"):
            raise InputError(f"mode: expected 'robust' or 'seed', got {self.mode!r}")
        for name in ("generations", "population", "runs", "fields"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name}: expected a positive integer, got {getattr(self, name)!r}")
        if self.parents < 2:
            raise InputError(f"parents: expected at least 2, got {self.parents}")
        if self.population < self.parents:
            raise InputError(f"population: expected at least {self.parents} (the parents mating each generation), got {self.population}")


@dataclass(frozen=True)
class CalibrationResult:
    """The fitted parameters with the SSIM they reach and how they were found."""

    params: HoloParams
    ssim: float
    history: list[dict] = field(default_factory=list)
    evaluations: int = 0
    seconds: float = 0.0
    stopped: bool = False
    settings: CalibrationSettings = field(default_factory=CalibrationSettings)
    roi: tuple[int, int, int] | None = None
    roi_choice: str = ""
    reference_experimental: np.ndarray | None = None
    reference_synthetic: np.ndarray | None = None

    def to_json(self) -> dict:
        """The calibration JSON of docs/formats.md (plus provenance keys)."""
        return {
            "params": self.params.as_dict(),
            "ssim": float(self.ssim),
            "roi": list(self.roi) if self.roi else None,
            "roi_choice": self.roi_choice,
            "seconds": round(float(self.seconds), 3),
            "evaluations": int(self.evaluations),
            "stopped": bool(self.stopped),
            "settings": asdict(self.settings),
            "history": self.history,
        }


def _normalise_planes(planes: np.ndarray, *, mode: str) -> np.ndarray:
    """Per-plane min–max stretch: to [0, 1] float (robust) or to 0–255 uint8 values (seed)."""
    low = planes.min(axis=(-2, -1), keepdims=True)
    span = planes.max(axis=(-2, -1), keepdims=True) - low
    unit = (planes - low) / np.where(span > 0, span, 1)
    if mode == "seed":
        return np.floor(unit * 255.0).astype(np.uint8).astype(np.float32) / 255.0
    return unit


def _processed_planes(magnitudes: np.ndarray, *, gamma: float, invert: bool, mode: str) -> np.ndarray:
    """Planes ``|·|`` → per-plane normalisation → (inversion) → gamma, in [0, 1]."""
    unit = _normalise_planes(magnitudes, mode=mode)
    if invert:
        unit = 1.0 - unit
    if gamma != 1.0:
        unit = unit**gamma
        if mode == "seed":
            unit = np.floor(unit * 255.0) / 255.0
    return unit


def _reference_image(magnitudes: np.ndarray, *, gamma: float, invert: bool, mode: str) -> np.ndarray:
    """Depth average of `_processed_planes`: a reference image ``I_e`` or ``I_s``."""
    return _processed_planes(magnitudes, gamma=gamma, invert=invert, mode=mode).mean(axis=0)


class _SSIM:
    """SSIM against a fixed reference (Wang et al. 2004; MATLAB's ``ssim``).

    Gaussian window σ = 1.5 truncated at 3.5σ (11x11), population covariances, data range 1,
    as `skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1)`; the reference's local statistics are
    computed once, so an evaluation filters three images instead of five.
    """

    _C1, _C2 = (0.01 * 1.0) ** 2, (0.03 * 1.0) ** 2

    def __init__(self, reference: np.ndarray) -> None:
        self.reference = np.asarray(reference, dtype=np.float64)
        self.mu_x = self._filter(self.reference)
        self.var_x = self._filter(self.reference**2) - self.mu_x**2

    @staticmethod
    def _filter(image: np.ndarray) -> np.ndarray:
        from scipy.ndimage import gaussian_filter

        return gaussian_filter(image, sigma=1.5, truncate=3.5, mode="reflect")

    def __call__(self, image: np.ndarray) -> float:
        image = np.asarray(image, dtype=np.float64)
        mu_y = self._filter(image)
        var_y = self._filter(image**2) - mu_y**2
        cov = self._filter(self.reference * image) - self.mu_x * mu_y
        numerator = (2 * self.mu_x * mu_y + self._C1) * (2 * cov + self._C2)
        denominator = (self.mu_x**2 + mu_y**2 + self._C1) * (self.var_x + var_y + self._C2)
        # skimage crops (win_size - 1) / 2 = 5 pixels at each edge before averaging
        return float((numerator / denominator)[5:-5, 5:-5].mean())


def holo_processing(
    hologram: np.ndarray,
    params: HoloParams,
    *,
    planes_um: Sequence[float],
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
    seed: int | np.random.Generator | None = None,
    mode: str = "robust",
    average: bool = True,
) -> np.ndarray:
    """Holo-processing of one simulated hologram (seed paper Sec. 2.2.1).

    Returns the reference synthetic image ``I_s`` ((rows, cols) in [0, 1]) or, with
    ``average=False``, the processed planes ((len(planes_um), rows, cols)) used as training input.
    """
    hologram = np.asarray(hologram)
    rng = np.random.default_rng(seed)
    noisy = hologram + rng.normal(params.N_R * np.ptp(hologram), params.N_sigma * hologram.std(), hologram.shape).astype(hologram.dtype)
    magnitudes = np.abs(propagate(noisy, -np.asarray(planes_um, float), wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index))
    planes = _processed_planes(magnitudes, gamma=params.gamma, invert=False, mode=mode)
    return planes.mean(axis=0) if average else planes.astype(np.float32)


def experimental_reference(stack: np.ndarray, *, mode: str = "robust") -> np.ndarray:
    """Reference experimental image ``I_e`` from a tile's raw reconstruction planes (particles bright)."""
    return _reference_image(np.asarray(stack), gamma=1.0, invert=True, mode=mode)


def experimental_planes(stack: np.ndarray, *, invert: bool, mode: str = "robust") -> np.ndarray:
    """A tile's raw reconstruction planes as the network sees them, float32 in [0, 1].

    Each plane is min–max normalised and, with ``invert``, inverted (the seed's ``255 - I``),
    exactly the planes that `experimental_reference` averages into ``I_e``.
    """
    return _processed_planes(np.asarray(stack), gamma=1.0, invert=invert, mode=mode).astype(np.float32)


class _Fitness:
    """``1 - SSIM(I_e, I_s(θ))`` on precomputed back-propagations (see the module docstring)."""

    def __init__(self, reference, holograms, *, planes_um, optics, mode, seed, steps: Steps | None = None):
        """``steps``, when given, counts one step per back-propagation made here and is checked after each (`Stopped`)."""
        self.ssim = _SSIM(reference)
        self.mode = mode
        self.rng = np.random.default_rng([seed, 1])
        z = -np.asarray(planes_um, float)
        self.signal = []  # B(h) per field
        self.noise = []  # B(n) per field and draw: (draws, planes, rows, cols)
        self.ranges = []
        for index, hologram in enumerate(holograms):
            self.signal.append(self._counted(propagate(hologram, z, **optics), steps))
            noise_rng = np.random.default_rng([seed, 2, index])
            draws = [self._counted(propagate(noise_rng.standard_normal(hologram.shape).astype(np.float32), z, **optics), steps)
                     for _ in range(_NOISE_POOL + _RESCORE_DRAWS)]
            self.noise.append(np.stack(draws))
            self.ranges.append((float(np.ptp(hologram)), float(hologram.std())))
        self.evaluations = 0

    @staticmethod
    def _counted(planes: np.ndarray, steps: Steps | None) -> np.ndarray:
        if steps is not None:
            steps.advance()
            steps.check()
        return planes

    @staticmethod
    def setup_steps(fields: int) -> int:
        """The back-propagations `_Fitness` makes for ``fields`` simulated fields: each field's, and its noise draws'."""
        return fields * (1 + _NOISE_POOL + _RESCORE_DRAWS)

    def image(self, params: HoloParams, field_index: int, draw: int) -> np.ndarray:
        value_range, sigma = self.ranges[field_index]
        planes = np.multiply(self.noise[field_index][draw], np.float32(params.N_sigma * sigma))
        planes += self.signal[field_index]
        planes += np.float32(params.N_R * value_range)
        return _reference_image(np.abs(planes), gamma=params.gamma, invert=False, mode=self.mode)

    def fresh_loss(self, params: HoloParams) -> float:
        """Mean loss over the noise draws kept out of the fit."""
        fresh = range(_NOISE_POOL, _NOISE_POOL + _RESCORE_DRAWS)
        return float(np.mean([self.loss(params, [d] * len(self.signal)) for d in fresh]))

    def loss(self, params: HoloParams, draws: Sequence[int]) -> float:
        """Mean ``1 - SSIM`` over the simulated fields, each with its noise draw (fields in parallel)."""
        self.evaluations += 1
        scores = thread_pool("fitness").map(lambda pair: 1.0 - self.ssim(self.image(params, *pair)), zip(range(len(self.signal)), draws, strict=False))
        return float(np.mean(list(scores)))


def score_params(
    reference: np.ndarray,
    holograms: Sequence[np.ndarray],
    candidates: Sequence[HoloParams],
    *,
    planes_um: Sequence[float],
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
    mode: str = "robust",
    seed: int = 0,
) -> np.ndarray:
    """SSIM each candidate reaches, scored exactly as `calibrate` scores its result (same seed → same noise)."""
    optics = {"wavelength_um": wavelength_um, "pixel_um": pixel_um, "medium_index": medium_index}
    fitness = _Fitness(np.asarray(reference, np.float64), [np.asarray(h, np.float32) for h in holograms], planes_um=planes_um, optics=optics, mode=mode, seed=seed)
    return np.array([1.0 - fitness.fresh_loss(params) for params in candidates])


def _gene_space(mode: str) -> list[dict]:
    space = []
    for low, high in PARAM_BOUNDS.values():
        space.append({"low": low, "high": high, "step": 0.01} if mode == "seed" else {"low": low, "high": high})
    return space


def calibrate(
    reference: np.ndarray,
    holograms: Sequence[np.ndarray],
    *,
    planes_um: Sequence[float],
    wavelength_um: float,
    pixel_um: float,
    medium_index: float = 1.0,
    settings: CalibrationSettings = CalibrationSettings(),
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
    report: ReportCallback | None = None,
) -> CalibrationResult:
    """Fit (N_R, N_σ, γ) so that Holo-processing of ``holograms`` matches ``reference`` by SSIM.

    Parameters
    ----------
    reference : (rows, cols) array in [0, 1]
        ``I_e`` (`experimental_reference`).
    holograms : sequence of (rows, cols) arrays
        Simulated holograms of random fields (unobstructed light = 1); ``seed`` mode uses the first.
    planes_um : sequence of float
        Reference depths (µm).
    settings : CalibrationSettings
    progress, should_stop
        One step per back-propagation of the set-up (``fields * 25``), per candidate scored
        (``(generations + 1) * population`` a run: the first population is scored too) and
        per noise draw re-scoring the finalists (``5 * 8``; ``seed`` mode ``1 * 8``). On a stop
        request the candidates not yet scored are left unscored, the GA ends with the current
        generation, and the best candidate so far, re-scored alone, is returned with
        ``stopped=True``; a stop before any candidate was scored raises `Stopped`.
    report : callable, optional
        Called with each generation's history record (``run``, ``generation``,
        ``best_fitness``) as it is made, for a live fitness curve.
    """
    import pygad

    reference = np.asarray(reference, dtype=np.float64)
    holograms = [np.asarray(h, dtype=np.float32) for h in holograms[: 1 if settings.mode == "seed" else settings.fields]]
    if not holograms:
        raise InputError("holograms: expected at least one simulated hologram")
    if any(h.shape != reference.shape for h in holograms):
        raise InputError(f"holograms: expected the reference's shape {reference.shape}, got {[h.shape for h in holograms]}")
    start = time.perf_counter()
    optics = {"wavelength_um": wavelength_um, "pixel_um": pixel_um, "medium_index": medium_index}
    setup = _Fitness.setup_steps(len(holograms))
    per_run = (settings.generations + 1) * settings.population
    finalists_wanted = 1 if settings.mode == "seed" else _FINALISTS
    steps = Steps(setup + settings.runs * per_run + finalists_wanted * _RESCORE_DRAWS, progress=progress, should_stop=should_stop)
    fitness = _Fitness(reference, holograms, planes_um=planes_um, optics=optics, mode=settings.mode, seed=settings.seed, steps=steps)
    history: list[dict] = []
    candidates: dict[tuple, float] = {}

    def draws_for(ga) -> list[int]:
        if settings.mode == "seed":  # fresh noise on every call, as the seed's code
            return [int(fitness.rng.integers(_NOISE_POOL))]
        # common random numbers: every candidate of a generation sees the same noise
        return [(ga.generations_completed + f) % _NOISE_POOL for f in range(len(holograms))]

    def fitness_func(ga, solution, _index):
        if steps.stop_requested():  # heard between candidates: the rest of the generation is left unscored
            return _UNSCORED
        params = HoloParams(*map(float, solution))
        loss = fitness.loss(params, draws_for(ga))
        key = tuple(np.round(solution, 6))
        candidates[key] = min(candidates.get(key, math.inf), loss)
        steps.advance()
        return -loss

    stopped = False
    for run in range(settings.runs):
        def on_generation(ga, run=run):
            if steps.stop_requested():  # a generation cut short is no point of the curve
                return "stop"
            # pygad reuses the scores of the candidates it keeps: the count is made up at each generation's end
            steps.advance(setup + run * per_run + (ga.generations_completed + 1) * settings.population - steps.done)
            best = -float(np.max(ga.last_generation_fitness))
            history.append({"run": run, "generation": ga.generations_completed, "best_fitness": best})
            if report is not None:
                report(history[-1])
            return None

        ga = pygad.GA(
            num_generations=settings.generations,
            num_parents_mating=settings.parents,
            sol_per_pop=settings.population,
            num_genes=3,
            gene_space=_gene_space(settings.mode),
            fitness_func=fitness_func,
            parent_selection_type="tournament",
            keep_elitism=1,
            crossover_type="uniform",
            mutation_type="random",
            mutation_probability=0.3,
            mutation_by_replacement=False,
            random_mutation_min_val=-0.1,
            random_mutation_max_val=0.1,
            random_seed=settings.seed + 1000 * run,
            on_generation=on_generation,
            suppress_warnings=True,
        )
        ga.run()
        if steps.stop_requested():
            stopped = True
            break

    if not candidates:
        raise Stopped("calibration stopped before any candidate was scored")
    # Re-score the finalists on noise the fit never saw; the winner's SSIM is that fresh score.
    # A stopped fit re-scores its best alone, so that Stop is answered within a second or so.
    finalists = sorted(candidates, key=candidates.get)[: 1 if stopped else finalists_wanted]
    steps.advance(setup + settings.runs * per_run - steps.done)
    scores = {}
    for key in finalists:
        scores[key] = fitness.fresh_loss(HoloParams(*key))
        steps.advance(_RESCORE_DRAWS)
    best_key = min(scores, key=scores.get)
    params = HoloParams(*map(float, best_key))
    return CalibrationResult(
        params=params,
        ssim=1.0 - float(scores[best_key]),
        history=history,
        evaluations=fitness.evaluations,
        seconds=time.perf_counter() - start,
        stopped=stopped,
        settings=settings,
        reference_experimental=reference,
        reference_synthetic=fitness.image(params, 0, _NOISE_POOL),
    )


def _tile_origins(shape: tuple[int, int], size: int) -> list[tuple[int, int]]:
    return [(x, y) for y in range(0, shape[0] - size + 1, size) for x in range(0, shape[1] - size + 1, size)]


def choose_reference_tile(stack: np.ndarray, *, size: int) -> tuple[tuple[int, int], str]:
    """Pick the most representative ``size`` tile of a raw reconstruction stack.

    Candidates are the non-overlapping tiles. Each is described by the mean, contrast
    (std) and high-frequency energy of its ``I_e`` and by the mean and std of its planes;
    after standardising each feature across tiles, the tile with the smallest summed distance
    to all others (the medoid) is chosen: the one least unlike the rest of the hologram.

    Returns
    -------
    ((x, y), reason)
    """
    origins = _tile_origins(stack.shape[-2:], size)
    if not origins:
        raise InputError(f"tile.size: a {size}x{size} tile is larger than the image {stack.shape[-2:]}")
    features = []
    for x, y in origins:
        planes = stack[:, y : y + size, x : x + size]
        image = experimental_reference(planes)
        high = np.abs(np.diff(image, axis=0)).mean() + np.abs(np.diff(image, axis=1)).mean()
        features.append([image.mean(), image.std(), high, planes.mean(), planes.std()])
    features = np.asarray(features)
    features = (features - features.mean(axis=0)) / np.where(features.std(axis=0) > 0, features.std(axis=0), 1)
    distance = np.sqrt(((features[:, None] - features[None]) ** 2).sum(-1)).sum(1)
    index = int(np.argmin(distance))
    return origins[index], f"medoid of {len(origins)} non-overlapping {size}² tiles by mean, contrast and texture of I_e and plane statistics"


def reference_planes(hologram: np.ndarray, config: ExperimentConfig, *, background: np.ndarray | None = None) -> np.ndarray:
    """The whole hologram back-propagated to the reference planes, as calibration sees it.

    The planes are ``config.layer_depths_um()`` (``z_min_um`` … ``z_max_um`` every
    ``particles.layer_step_um``); a tile's ``experimental_reference(planes[:, y:y+size, x:x+size])``
    is the ``I_e`` that `calibrate_hologram` compares against.

    Returns
    -------
    (len(config.layer_depths_um()), rows, cols) float32 array
    """
    rows, cols = np.shape(hologram)
    planes_um = config.layer_depths_um()
    check_memory(len(planes_um) * rows * cols * np.dtype(np.float32).itemsize, what=f"{len(planes_um)} reference planes of {rows}x{cols} pixels",
                 remedy="raise particles.layer_step_um or crop the hologram")
    return backpropagate(hologram, planes_um, background=background, wavelength_um=config.optics.wavelength_um,
                         pixel_um=config.optics.pixel_um, medium_index=config.optics.medium_index)


def calibrate_hologram(
    hologram: np.ndarray,
    config: ExperimentConfig,
    *,
    roi: tuple[int, int] | None = None,
    background: np.ndarray | None = None,
    settings: CalibrationSettings = CalibrationSettings(),
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
    report: ReportCallback | None = None,
) -> CalibrationResult:
    """Calibrate Holo-processing to a real hologram: the `napari-lbs calibrate` step.

    The whole hologram is back-propagated to the reference planes (`reference_planes`) so
    the tile keeps its true surroundings;
    ``roi = (x, y)`` is the tile's top-left pixel, or None to let `choose_reference_tile` pick.
    The simulated fields have ``particles.per_tile`` particles on the same layers.
    """
    size = config.tile.size
    rows, cols = np.shape(hologram)
    if size > rows or size > cols:
        raise InputError(f"tile.size: a {size}x{size} tile is larger than the hologram ({rows}x{cols})")
    if roi is not None:
        x, y = (int(v) for v in roi)
        if x < 0 or y < 0 or x + size > cols or y + size > rows:
            raise InputError(f"roi: a {size}² tile at x={x}, y={y} crosses the edge of the {cols}x{rows} (x by y) hologram")
    planes_um = config.layer_depths_um()
    optics = {"wavelength_um": config.optics.wavelength_um, "pixel_um": config.optics.pixel_um, "medium_index": config.optics.medium_index}
    stack = reference_planes(hologram, config, background=background)
    if roi is None:
        (x, y), reason = choose_reference_tile(stack, size=size)
    else:
        reason = "given"
    reference = experimental_reference(stack[:, y : y + size, x : x + size], mode=settings.mode)
    rng = np.random.default_rng([settings.seed, 3])
    holograms = []
    for _ in range(1 if settings.mode == "seed" else settings.fields):
        particles = random_particle_field(
            (size, size),
            count=config.particles.per_tile,
            diameter_min_um=config.particles.diameter_min_um,
            diameter_max_um=config.particles.diameter_max_um,
            layers_um=planes_um,
            pixel_um=config.optics.pixel_um,
            seed=rng,
        )
        holograms.append(simulate_hologram(particles, wavelength_um=config.optics.wavelength_um, medium_index=config.optics.medium_index))
    result = calibrate(reference, holograms, planes_um=planes_um, settings=settings, progress=progress, should_stop=should_stop, report=report, **optics)
    return replace(result, roi=(x, y, size), roi_choice=reason)
