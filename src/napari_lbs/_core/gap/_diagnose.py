"""Diagnosis as inference: which catalog effects the experiment's holograms hold, where the gap lies, how far it shrinks.

1. The holograms are read on a `TileGrid` (one tile per cell of the sensor, every shift that
   fits), each set of tiles summarised (`set_features`), the sets' features averaged: more
   frames, less noise.
2. The setup's amortized diagnoser (`amortized_diagnoser`: simulations from a broad prior,
   a random forest, cached) gives each candidate effect's probability of being present; the
   posterior over models — nothing missing, one effect, or two — is the same forest's
   (`forest_posterior`). The verdict names the effects present with at least
   ``settings.level`` probability (two at most); with none, nothing is missing where that is
   the most probable model and clears the level, else the two most probable models are
   named undecided.
3. Where and how much: for every model, the simulations of that model closest to the
   experiment in every feature (ABC rejection) are compared with the experiment's tiles: the
   gap is their squared maximum mean discrepancy (`mmd`), and a classifier two-sample test
   (`c2st`) says whether they can be told apart at all, per frequency band, per depth and per
   tile (the map of where the experiment is most unlike the simulation).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.physics import check_effects
from napari_lbs._core.gap._amortized import Diagnoser, DiagnosisSettings, amortized_diagnoser, forest_posterior
from napari_lbs._core.gap._features import set_features, set_summaries
from napari_lbs._core.gap._known import known_sensor
from napari_lbs._core.gap._scenarios import EFFECT_BRANCHES, ScenarioPrior, TileGrid, catalog_candidates
from napari_lbs._core.gap._summaries import MIN_TILE_PX
from napari_lbs._core.gap._twosample import c2st, mmd
from napari_lbs._core.foundation import InputError, as_hologram
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback

__all__ = ["Diagnosis", "diagnose_hologram", "decide"]

_TILE_PX = 128  # tile edge (px) where the sensor's cells hold it
# The gap (squared MMD) whose lower bound, with the best model, says the catalog does not explain the
# data: twice the largest such bound of the development suite's cases (0.095), where every answer was
# a catalog effect or nothing
_UNEXPLAINED = 0.2
_NO_GAP = 1e-3  # squared MMD below which two samples of tile summaries are as alike as one simulator's (test_diagnosis)
_MOST_TILES = 512  # experiment tiles the two-sample tests take at most (evenly spaced): their cost grows with the square


@dataclass(frozen=True)
class Diagnosis:
    """The report (docs/formats.md ``report.json``) plus what the figures need: ``tile_map`` (rows, cols), each tile's held-out probability of being the experiment's against the baseline's closest simulations (near 1: told apart; NaN where no tile was read)."""

    report: dict
    tile_map: np.ndarray = field(repr=False)
    seconds: float = 0.0


def decide(marginals: dict, posterior: dict, *, level: float) -> tuple:
    """The verdict of a posterior: ``(id, effects named, probability, undecided, reason)``.

    The effects present with at least ``level`` probability (the two most probable where more
    clear it) are named; with none, nothing is missing where that is the most probable model
    and clears the level; else the two most probable models are undecided.
    """
    ranked = sorted(posterior.items(), key=lambda item: -item[1])
    candidates = list(marginals)
    present = sorted((e for e in candidates if marginals[e] >= level), key=lambda e: -marginals[e])[:2]
    named = tuple(e for e in candidates if e in present)
    if named:
        reason = " and ".join(f"{e} present with probability {marginals[e]:.2f}" for e in named) + f" (level {level:.2f})"
        return "+".join(named), named, min(marginals[e] for e in named), [], reason
    likeliest = max(candidates, key=lambda e: marginals[e])
    if ranked[0][0] == "null" and ranked[0][1] >= level:
        return None, (), ranked[0][1], [], f"nothing missing: posterior probability {ranked[0][1]:.2f} (level {level:.2f}); most probable effect {likeliest} ({marginals[likeliest]:.2f})"
    reason = f"undecided between {ranked[0][0]} ({ranked[0][1]:.2f}) and {ranked[1][0]} ({ranked[1][1]:.2f}): no effect is present with probability {level:.2f}"
    return None, (), ranked[0][1], [ranked[0][0], ranked[1][0]], reason


def _frames(holograms) -> list[np.ndarray]:
    """The 2-D frames of one hologram, a (frames, rows, cols) stack or a sequence of either."""
    if isinstance(holograms, np.ndarray) or not isinstance(holograms, Sequence):
        holograms = [holograms]
    frames = []
    for item in holograms:
        array = np.asarray(item)
        if array.ndim == 3 and array.shape[-1] not in (3, 4):
            frames.extend(array)
        else:
            frames.append(array)
    if not frames:
        raise InputError("holograms: expected at least one hologram")
    shape = as_hologram(frames[0]).shape
    for i, frame in enumerate(frames):
        if as_hologram(frame).shape != shape:
            raise InputError(f"holograms: frame {i} is {as_hologram(frame).shape[0]}x{as_hologram(frame).shape[1]}, expected {shape[0]}x{shape[1]} like the first")
    return frames


def _grid(shape: tuple[int, int], tile_px: int | None) -> TileGrid:
    cell = min(shape) // 4
    size = int(tile_px) if tile_px else min(_TILE_PX, cell)
    if size < MIN_TILE_PX:
        raise InputError(f"tile: expected at least {MIN_TILE_PX} pixels (a {shape[0]}x{shape[1]} hologram holds 4x4 tiles of {cell} px; the frequency bands need {MIN_TILE_PX})")
    if size > cell:
        raise InputError(f"tile: a {size}-pixel tile does not fit the 4x4 cells ({cell} px) of the {shape[0]}x{shape[1]} hologram")
    return TileGrid((int(shape[0]), int(shape[1])), size)


def _nearest(diagnoser: Diagnoser, distance: np.ndarray, model: tuple, count: int) -> np.ndarray:
    """Indices of the ``count`` simulations of exactly ``model`` (effects present) closest to the experiment (smallest ``distance``)."""
    wanted = np.array([c in model for c in diagnoser.candidates])
    members = np.flatnonzero((diagnoser.present == wanted).all(axis=1))
    if members.size == 0:
        return members
    return members[np.argsort(distance[members], kind="stable")[:count]]


def _separation(real: np.ndarray, simulated: np.ndarray, *, seed: int) -> float:
    """How often a classifier tells the two samples apart: 2 (C2ST accuracy − 0.5), 0 … 1."""
    return max(0.0, 2 * (c2st(real, simulated, seed=seed)["accuracy"] - 0.5))


def _shrink(baseline: float, after: float) -> float:
    """1 − after / baseline, 0 where the baseline gap is within sampling noise of nothing (or unknown)."""
    return float(1.0 - after / baseline) if np.isfinite(baseline) and np.isfinite(after) and baseline > _NO_GAP else 0.0


def _gap(real: np.ndarray, simulated: np.ndarray, *, seed: int) -> dict:
    """The gap (squared MMD, with its interval) and the C2ST (accuracy, interval, each real tile's held-out probability)."""
    test, distance = c2st(real, simulated, seed=seed), mmd(real, simulated, seed=seed)
    return {"gap": max(distance["value"], 0.0), "interval": [max(v, 0.0) for v in distance["interval"]], "accuracy": test["accuracy"], "accuracy_interval": test["interval"], "real_probability": test["real_probability"]}


def _params(diagnoser: Diagnoser, distance: np.ndarray, effect_id: str) -> dict:
    """The effect's parameters by ABC rejection: median and 90 % interval over the simulations with it closest to the experiment in every feature.

    The closest tenth of the simulations that have the effect (at least 20) are kept.
    """
    column = diagnoser.candidates.index(effect_id)
    members = np.flatnonzero(diagnoser.present[:, column])
    kept = members[np.argsort(distance[members], kind="stable")[: max(20, members.size // 10)]]
    if effect_id in EFFECT_BRANCHES:  # an effect of two kinds: the kind most of the closest have, alone (no mix of the two)
        strength = diagnoser.params.get(f"{effect_id}.{EFFECT_BRANCHES[effect_id][0]}")
        if strength is not None and kept.size:
            first_kind = np.nan_to_num(strength[kept]) > 0
            kept = kept[first_kind] if first_kind.mean() >= 0.5 else kept[~first_kind]
    out, intervals = {}, {}
    for name, values in diagnoser.params.items():
        effect, _, param = name.partition(".")
        v = values[kept]
        v = v[np.isfinite(v)]
        if effect != effect_id or v.size == 0:
            continue
        low, median, high = np.quantile(v, (0.05, 0.5, 0.95))
        out[param], intervals[param] = float(median), [float(low), float(high)]
    return {"params": check_effects({effect_id: out})[effect_id] if out else {}, "intervals": intervals}


def diagnose_hologram(
    holograms,
    config: ExperimentConfig,
    *,
    background: np.ndarray | None = None,
    tile_px: int | None = None,
    known: bool = True,
    stated: dict | None = None,
    settings: DiagnosisSettings = DiagnosisSettings(),
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> Diagnosis:
    """Diagnose the gap between the experiment's holograms and the seed's simulator.

    Parameters
    ----------
    holograms : 2-D array, (frames, rows, cols) array, or a sequence of them
        As recorded (integer counts keep what the file states about the camera). Several
        frames of one setup are pooled: their features are averaged.
    config : ExperimentConfig
        Optics, depths and particle sizes: the setup the diagnoser simulates.
    background : 2-D array, optional
        Divided out of every frame first.
    tile_px : int, optional
        Tile edge (px); default 128, or the sensor's cell (a quarter of its shorter side) where smaller.
    known : bool
        Put what the file states (bit depth, `known_sensor`) into every simulation, not diagnosed.
    stated : dict, optional
        ``{effect_id: params}`` the user knows of the experiment (e.g. transparent beads:
        ``{"particle_phase": {"index_contrast": 0.26, "transmission": 1.0}}``): in every
        simulation, not diagnosed.
    settings : DiagnosisSettings
    progress, should_stop
        One step per training simulation (when the setup's diagnoser is not cached yet) and
        one per model tested; a stop raises `Stopped`.
    """
    start = time.perf_counter()
    frames = _frames(holograms)
    images = [as_hologram(f) for f in frames]
    facts = (known_sensor(frames[0]) or known_sensor(images[0])) if known else None
    if background is not None:
        divisor = np.maximum(as_hologram(background, name="background"), 1e-6)
        if divisor.shape != images[0].shape:
            raise InputError(f"background: expected {images[0].shape[0]}x{images[0].shape[1]} like the hologram, got {divisor.shape[0]}x{divisor.shape[1]}")
        images = [i / divisor for i in images]
        facts = None
    for i, image in enumerate(images):
        if not np.all(np.isfinite(image)) or float(image.mean()) <= 0:
            raise InputError(f"hologram {i}: expected finite intensities with a positive mean")
    grid = _grid(images[0].shape, tile_px)
    # the file's bit depth is known; where the camera saturates, relative to the mean, varies with the
    # scene and is drawn in every simulation (so one diagnoser serves every hologram of the setup)
    bits = float(facts["bits"]) if facts and not facts["coarse"] else None
    stated = check_effects(stated or {})
    known_effects = ({"quantization": {"bits": bits}} if bits else {}) | stated
    candidates = catalog_candidates(known_effects)
    if not candidates:
        raise InputError("stated: every catalog effect is known or stated; nothing is left to diagnose")
    prior = ScenarioPrior(candidates=candidates, known=stated, bits=bits)
    trained = []  # the training's steps, where the setup's diagnoser is not cached yet: one progress bar for both

    def training(done, total):
        trained[:] = [total]
        if progress is not None:
            progress(done, total + len(candidates) + 3)

    diagnoser = amortized_diagnoser(config, grid, prior, settings=settings, progress=training, should_stop=should_stop)
    offset = trained[0] if trained else 0
    steps = Steps(len(candidates) + 3, progress=(lambda d, t: progress(offset + d, offset + t)) if progress else None, should_stop=should_stop)

    # the experiment: every frame, every shift of the grid
    steps.check()
    features, real_tiles, places = [], [], []
    for image in images:
        for shift in grid.shifts():
            origins = grid.origins(shift)
            tiles = [image[r : r + grid.tile_px, c : c + grid.tile_px] for r, c in origins]
            summaries, _ = set_summaries(tiles, config=config)
            features.append(set_features(tiles, summaries, grid.centres(shift)))
            real_tiles.append(summaries)
            places.extend(origins)
    x = np.mean(features, axis=0)[None, :]
    real = np.vstack(real_tiles)
    tested = np.unique(np.linspace(0, len(real) - 1, min(len(real), _MOST_TILES)).round().astype(int))
    real, places = real[tested], [places[i] for i in tested]
    marginals, posterior = forest_posterior(diagnoser, x[0])
    marginals = {k: float(v) for k, v in marginals.items()}
    # the simulations most like the experiment in every feature, nuisances included (ABC rejection):
    # what the two-sample tests compare it with
    scale = diagnoser.features.std(axis=0)
    scale[scale == 0] = 1.0
    distance = np.sqrt((((diagnoser.features - x) / scale) ** 2).sum(axis=1))
    steps.advance()

    # how far each model's closest simulations are from the experiment
    def gap_of(model: tuple) -> dict:
        chosen = _nearest(diagnoser, distance, model, settings.neighbours)
        if chosen.size == 0:
            return {"gap": float("nan"), "interval": [float("nan")] * 2, "accuracy": float("nan"), "accuracy_interval": [float("nan")] * 2, "real_probability": np.full(len(real), np.nan), "simulations": 0}
        return {**_gap(real, diagnoser.summaries[chosen].reshape(-1, real.shape[1]), seed=settings.seed), "simulations": int(chosen.size)}

    steps.check()
    baseline = gap_of(())
    neighbours_null = _nearest(diagnoser, distance, (), settings.neighbours)
    null_sim = diagnoser.summaries[neighbours_null].reshape(-1, real.shape[1]) if neighbours_null.size else None
    steps.advance()
    effects, gaps = [], {}
    for effect_id in candidates:
        steps.check()
        after = gaps[effect_id] = gap_of((effect_id,))
        shrink = _shrink(baseline["gap"], after["gap"])
        effects.append({
            "id": effect_id, "probability": marginals[effect_id], "gap_after": after["gap"], "gap_after_interval": after["interval"], "shrink": float(shrink), "c2st_accuracy": after["accuracy"],
            **_params(diagnoser, distance, effect_id),
        })
        steps.advance()
    effects.sort(key=lambda e: -e["probability"])

    verdict_id, named_effects, probability, undecided, reason = decide(marginals, posterior, level=settings.level)
    named_gap = (gaps[named_effects[0]] if len(named_effects) == 1 else gap_of(named_effects)) if named_effects else baseline
    explained = named_gap if verdict_id else min([baseline, gaps[effects[0]["id"]]], key=lambda g: g["gap"])
    catalog_explains = not (np.isfinite(explained["interval"][0]) and explained["interval"][0] >= _UNEXPLAINED)
    verdict = {
        "id": verdict_id, "effects": list(named_effects), "probability": float(probability),
        "shrink": _shrink(baseline["gap"], named_gap["gap"]) if verdict_id else 0.0,
        "residual": float(named_gap["gap"]), "residual_interval": [float(v) for v in named_gap["interval"]], "undecided": undecided, "catalog_explains": bool(catalog_explains), "reason": reason,
        "runner_up": next((k for k, _ in sorted(posterior.items(), key=lambda item: -item[1]) if k != (verdict_id or (undecided[0] if undecided else "null"))), None),
    }
    if not catalog_explains:
        verdict["reason"] += (f"; the catalog does not explain this gap: with the best model the experiment's tiles are still far from its closest simulations "
                              f"(gap {explained['gap']:.3f}, lower bound {explained['interval'][0]:.3f}; C2ST accuracy {explained['accuracy']:.2f})")

    # where the baseline's gap lies: per frequency band, per depth, per tile
    steps.check()
    names = diagnoser.summary_names
    separation = (lambda columns: _separation(real[:, columns], null_sim[:, columns], seed=settings.seed)) if null_sim is not None else (lambda columns: None)
    by_band = [{"band": n, "told_apart": separation([i])} for i, (n, g) in enumerate(names) if g == "band" and n.startswith("log power ") and "cyc/px" in n]
    depths = sorted({n.split(" at ")[1] for n, g in names if g == "depth" and " at " in n}, key=lambda s: float(s.split()[0]))
    at_depth = {d: [i for i, (n, _) in enumerate(names) if n.endswith(f" at {d}")] for d in depths}
    by_depth = [{"depth_um": float(d.split()[0]), "told_apart": separation(at_depth[d])} for d in depths]
    tile_map = _tile_map(grid, places, baseline["real_probability"])
    steps.advance()

    report = {
        "posterior": {k: float(v) for k, v in sorted(posterior.items(), key=lambda item: -item[1])},
        "marginals": marginals,
        "gap": {
            "metric": "squared maximum mean discrepancy (Gaussian kernel, standardised tile summaries) between the experiment's tiles and the closest simulations' (0 = one distribution)",
            "baseline": float(baseline["gap"]), "baseline_interval": baseline["interval"], "baseline_c2st_accuracy": baseline["accuracy"],
            "told_apart": "by_band, by_depth: 2 (C2ST held-out accuracy - 0.5) on one band's or one depth's summaries, against the baseline's closest simulations: 0 = indistinguishable, 1 = always told apart",
            "by_band": by_band, "by_depth": by_depth,
            "tiles": {"shape": list(tile_map.shape), "most_unlike": _most_unlike(tile_map, grid)},
        },
        "known": known_effects,
        "effects": effects,
        "verdict": verdict,
        "tiles": {"frames": len(images), "per_frame": len(places) // len(images), "tile_px": grid.tile_px, "grid": [grid.per_side, grid.per_side]},
        "diagnoser": {"key": diagnoser.key, "simulations": int(diagnoser.features.shape[0]), "trees": int(diagnoser.forest.roots.size), "candidates": list(candidates), "train_seconds": diagnoser.meta.get("train_seconds")},
        "known_sensor": facts if facts else {"source": "none: not integer counts, a background was divided out, or switched off"},
        "stated": stated,
        "settings": {"level": settings.level, "neighbours": settings.neighbours, "seed": settings.seed, "simulations": settings.simulations, "trees": settings.trees, "training_seed": settings.training_seed},
    }
    seconds = time.perf_counter() - start
    report["seconds"] = round(seconds, 2)
    return Diagnosis(report, tile_map, seconds)


def _tile_map(grid: TileGrid, places: list, probability: np.ndarray) -> np.ndarray:
    """(rows, cols) mean held-out probability of being real of the tiles at each tile-sized cell of the sensor (NaN: none read there)."""
    rows, cols = grid.frame_shape[0] // grid.tile_px, grid.frame_shape[1] // grid.tile_px
    total, count = np.zeros((rows, cols)), np.zeros((rows, cols))
    for (r, c), p in zip(places, probability, strict=True):
        i, j = min((r + grid.tile_px // 2) // grid.tile_px, rows - 1), min((c + grid.tile_px // 2) // grid.tile_px, cols - 1)
        if np.isfinite(p):
            total[i, j] += p
            count[i, j] += 1
    with np.errstate(invalid="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _most_unlike(tile_map: np.ndarray, grid: TileGrid) -> list:
    """The three tiles most often told apart: their top-left pixel (x, y) and probability of being real."""
    order = np.argsort(-np.nan_to_num(tile_map, nan=-1).ravel())[:3]
    return [{"x_px": int(k % tile_map.shape[1]) * grid.tile_px, "y_px": int(k // tile_map.shape[1]) * grid.tile_px, "probability": float(tile_map.ravel()[k])} for k in order if np.isfinite(tile_map.ravel()[k])]

