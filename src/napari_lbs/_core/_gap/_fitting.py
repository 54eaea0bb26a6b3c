"""Simulated tiles with common random numbers (`_Model`) and the refits of the baseline and added effects (`_fit`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import optimize, stats

from napari_lbs._core._config import ExperimentConfig
from napari_lbs._core._effects import BASELINE, EFFECTS, OPTICAL_EFFECTS, optical_hologram, sensor_image
from napari_lbs._core._gap._statistic import gap_statistic
from napari_lbs._core._gap._summaries import _tiles_summaries
from napari_lbs._core._gap._tiling import TileLayout, field_surroundings
from napari_lbs._core._io import InputError
from napari_lbs._core._synthesis import random_particle_field

__all__ = ["DiagnosisSettings"]

_DESIGN_POINTS = 16  # Sobol points tried by a fit that adds parameters
_MIN_EVALUATIONS = 8  # each fit stage runs at least this many evaluations (see `_fit`)


@dataclass(frozen=True)
class DiagnosisSettings:
    """How hard to look.

    ``sim_tiles`` simulated tiles per model; ``evaluations`` per fit; ``confirm`` how many
    effects, in order of screening significance, are refitted (default all: the linear
    screening misses effects the baseline over-compensates, e.g. shot noise absorbed by read
    noise); the others get the best of a coarse off/weak/strong scan; ``resamples`` bootstrap
    draws for the intervals and the verdict's confidence; ``cross_fit_below_px``: cross-fit
    (fit on each half, score on the other: every tile held out once) when one half of the real
    tiles holds fewer pixels than this (0: never). The default, 2^20 px, cross-fits up to a
    1024² hologram (its halves hold 2^19): 8 held-out tiles (a 512² hologram's 8 tiles of 128²
    hold about 12 spheres, a 1024² one's of 256² about 50) are what limits the verdicts; a
    larger hologram has data enough in one split. ``scoring_replicates``: simulated tiles per
    held-out tile when the models are scored (the fits use ``sim_tiles``): a model's held-out
    score compares the real tiles' mean with the mean of this many times as many simulated
    tiles, from fields drawn apart from the fits' (`_Model`), so the simulation's own sampling
    noise, which weighed as much as the real tiles' in every z, weighs a quarter of it by
    default (z² 1.6× as large for the same difference). It costs a few summaries per model,
    not per fit evaluation.
    """

    sim_tiles: int = 8
    evaluations: int = 40
    confirm: int = len(EFFECTS)
    resamples: int = 2000
    seed: int = 0
    cross_fit_below_px: int = 2**20
    scoring_replicates: int = 4

    def __post_init__(self) -> None:
        for name, low in (("sim_tiles", 2), ("evaluations", _MIN_EVALUATIONS), ("confirm", 0), ("resamples", 100), ("seed", 0), ("cross_fit_below_px", 0), ("scoring_replicates", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InputError(f"{name}: expected an integer of at least {low}, got {value!r}")


class _Model:
    """Simulated tiles of one effect set, with fixed fields and noise (common random numbers).

    With a `TileLayout` the simulation makes whole fields of the hologram's shape (so a
    field-wide envelope spans them as it spans the experiment) and cuts ``sim_tiles`` tiles for
    each half of the real tiles at that half's own positions (``half="fit"`` or ``"held"``): a
    tile's field-wide summaries depend on where it lies (a vignetting's tilt is largest at the
    edge), so real and simulated tiles are compared position by position, and with as many
    simulated tiles as real ones row i of both lies at one place (``paired``). Without a
    layout, each simulated tile is a field of its own, the "field" is the set of simulated
    tiles and both halves see the same tiles. ``known`` effects (with fixed parameters: what
    the file states) are part of every model. ``light``: a cache of simulated light (`light`)
    to share with the other half's model of a cross-fit, whose fields are the same (both are
    drawn from ``settings.seed``): each optical setting is then simulated once.

    Scoring (``summaries(..., scored=True)``) adds ``settings.scoring_replicates - 1`` more sets
    of fields, drawn from their own stream (the fits' fields and noise stay those of one set):
    replicate r's tiles follow the first set's, cut at the same places (row ``r·n + i`` lies
    where row i does).
    """

    def __init__(self, config: ExperimentConfig, *, shape, count: int, settings: DiagnosisSettings, fringe_frequency: tuple[float, float], layout: TileLayout | None, known: dict, light: dict | None = None) -> None:
        self.config = config
        self.fringe_frequency = fringe_frequency
        self.known = known
        self.shape = tuple(shape)
        field_shape = tuple(layout.field_shape) if layout is not None else self.shape
        if layout is not None:
            fitting = layout.fitting(self.shape)
            halves = {"fit": [o for o, f in zip(layout.origins, fitting, strict=True) if f], "held": [o for o, f in zip(layout.origins, fitting, strict=True) if not f]}
        else:
            halves = {"fit": [(0, 0)], "held": [(0, 0)]}
        self.cuts, fields = {}, 1
        for half, origins in halves.items():
            picked = np.round(np.linspace(0, len(origins) - 1, min(settings.sim_tiles, len(origins)))).astype(int)
            places = [origins[i] for i in picked]
            fields = max(fields, -(-settings.sim_tiles // len(places)))
            self.cuts[half] = [(index // len(places), places[index % len(places)]) for index in range(settings.sim_tiles)]
        replicates = settings.scoring_replicates
        self.scored_cuts = {half: [(f + r * fields, place) for r in range(replicates) for f, place in cuts] for half, cuts in self.cuts.items()}
        self.fields_per_set = fields
        self.paired = layout is not None and all(len(origins) == settings.sim_tiles for origins in halves.values())
        self.whole_fields = layout is not None
        field_count = max(1, round(count * field_shape[0] * field_shape[1] / (self.shape[0] * self.shape[1])))
        self.fields, self.noise = [], []
        for stream, sets in ((11, 1), (12, replicates - 1)):  # the fits' set, then the scoring's other sets
            rng = np.random.default_rng([settings.seed, stream])
            self.fields += [
                random_particle_field(field_shape, count=field_count, diameter_min_um=config.particles.diameter_min_um, diameter_max_um=config.particles.diameter_max_um, layers_um=config.layer_depths_um(), pixel_um=config.optics.pixel_um, seed=rng)
                for _ in range(sets * fields)
            ]
            self.noise += [rng.standard_normal(field_shape).astype(np.float32) for _ in range(sets * fields)]
        self._light: dict[tuple, np.ndarray] = {} if light is None else light

    def light(self, effects: dict, field: int) -> np.ndarray:
        """The simulated light (intensity, unobstructed 1) of field ``field`` with the optical effects of ``effects``, cached."""
        # field i is the same draw in every model of one diagnosis (the fields come first in
        # their stream): (field, setting) names it across the halves of a cross-fit
        key = (field, *sorted((k, tuple(sorted(v.items()))) for k, v in effects.items() if k in OPTICAL_EFFECTS))
        if key not in self._light:
            optical = {k: v for k, v in effects.items() if k in OPTICAL_EFFECTS}
            self._light[key] = optical_hologram(self.fields[field], optical, wavelength_um=self.config.optics.wavelength_um, medium_index=self.config.optics.medium_index)
        return self._light[key]

    def forget_light(self) -> None:
        """Drop the simulated light of every setting tried (`light`): once scored, only the summaries are needed."""
        self._light.clear()

    def summaries(self, baseline: dict, effects: dict, *, half: str = "fit", scored: bool = False) -> np.ndarray:
        """Summaries of the tiles cut for ``half`` ("fit" or "held") of the real tiles: (sim_tiles, K), or with ``scored`` (sim_tiles · scoring_replicates, K)."""
        effects = {**self.known, **effects}
        sensor = {k: v for k, v in effects.items() if k not in OPTICAL_EFFECTS}
        cuts = self.scored_cuts[half] if scored else self.cuts[half]
        images = {f: sensor_image(self.light(effects, f), baseline, sensor, noise=self.noise[f]) for f in sorted({f for f, _ in cuts})}
        rows, cols = self.shape
        tiles = [images[f][r : r + rows, c : c + cols] for f, (r, c) in cuts]
        # the field a tile is measured against: its own image, or (no layout) its set of tiles
        if self.whole_fields:
            field_means = {f: float(image.mean()) for f, image in images.items()}
            around = [field_surroundings(images[f], origin, self.shape) for f, origin in cuts]
        else:
            sets = [f // self.fields_per_set for f, _ in cuts]
            set_means = {s: float(np.mean([t.mean() for t, t_set in zip(tiles, sets, strict=True) if t_set == s])) for s in set(sets)}
            field_means = {f: set_means[f // self.fields_per_set] for f in images}
            around = [None] * len(tiles)
        return _tiles_summaries(tiles, config=self.config, fringe_frequency=self.fringe_frequency, field_means=[field_means[f] for f, _ in cuts], surroundings=around)[0]


def _fit(model: _Model, real: np.ndarray, effect_ids: Sequence[str], *, start: dict, measured: dict, evaluations: int, spread: np.ndarray, half: str = "fit") -> tuple[dict, dict, float]:
    """Fit the baseline and the listed effects' parameters to the fitting tiles ``real`` (in unit coordinates; returns baseline, effects, gap).

    The loss is `_chi_square`; the gap returned is its excess, ``max(0, χ² - 1)``. ``half``:
    the half of the layout ``real`` comes from (`_Model.summaries`; ``"held"`` when the halves
    swap roles in a cross-fit).

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
        return _chi_square(real, model.summaries(baseline, effects, half=half), spread=spread)

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
        start_chi_square = _chi_square(real, model.summaries(start_baseline, start_effects, half=half), spread=spread)
        if start_chi_square <= best[0]:
            return start_baseline, start_effects, max(0.0, start_chi_square - 1.0)
    return baseline, effects, max(0.0, best[0] - 1.0)


def _chi_square(real: np.ndarray, sim: np.ndarray, *, spread: np.ndarray) -> float:
    """The fits' loss: mean standardised χ² (`gap_statistic` before its excess is clipped at 0).

    The gap ``max(0, χ² - 1)`` is flat wherever χ² ≤ 1, and with 55 summaries one summary
    5 spreads off adds only 25/55 to χ²: a fit of the gap stopped anywhere in that flat region
    (measured on a Lorenz–Mie field with photon noise: fitting gap 0, held-out z = 5.1 on the
    highest band). χ² itself keeps falling until every summary is matched as well as it can be.
    """
    z = gap_statistic(real, sim, spread=spread)[1]
    return float(np.mean(np.minimum(z**2, 1e4)))


# Fitted on a log scale: a noise level matters by its order of magnitude, and a linear scale
# would leave the small values a real camera has squeezed against the lower bound.
_LOG_SCALED = {("baseline", "sigma"), ("noise", "total")}
# Fitted on a square-root scale: an index contrast spans weak cells in water (0.01-0.05) to
# polystyrene in air (0.59), and 0 (off) must stay reachable, which a log scale cannot.
_SQUARE_SCALED = {("particle_phase", "index_contrast")}


def _from_unit(key: tuple, unit: float, low: float, high: float) -> float:
    if key in _LOG_SCALED:
        return float(low * (high / low) ** unit)
    if key in _SQUARE_SCALED:
        return low + (high - low) * unit**2
    return low + (high - low) * unit


def _to_unit(key: tuple, value: float, low: float, high: float) -> float:
    if high <= low:
        return 0.5
    if key in _LOG_SCALED:
        return float(np.clip(np.log(max(value, low) / low) / np.log(high / low), 0.0, 1.0))
    if key in _SQUARE_SCALED:
        return float(np.sqrt(np.clip((value - low) / (high - low), 0.0, 1.0)))
    return float(np.clip((value - low) / (high - low), 0.0, 1.0))


def _simplex(x0: np.ndarray, size: float = 0.25) -> np.ndarray:
    step = np.where(x0 > 0.5, -size, size)
    return np.vstack([x0] + [x0 + np.eye(len(x0))[i] * step[i] for i in range(len(x0))])


def _with_measured(effect_id: str, setting: dict, measured: dict) -> dict:
    """An effect setting with the parameters measured on the real tiles put in."""
    return {**setting, **{name: value for (effect, name), value in measured.items() if effect == effect_id}}
