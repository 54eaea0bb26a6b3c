"""The amortized diagnoser: simulations from the prior, a forest that answers "which model, which effects?", cached per setup.

Trained once per setup (config, the sensor's shape and tiles, what is known) from
``settings.simulations`` scenarios (`draw_scenario`, `simulate_tiles`, `set_features`), it
is kept on disk under a name made of the setup's hash and reused by every later diagnosis of
the same setup. The cache file holds plain arrays and JSON text, read with
``allow_pickle=False``; a file that is not one is refused with one line, never executed.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from napari_lbs import __version__
from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import InputError
from napari_lbs._core.gap._features import feature_names, set_features, set_summaries
from napari_lbs._core.gap._forest import ForestArrays, train_forest
from napari_lbs._core.gap._scenarios import ScenarioPrior, TileGrid, draw_scenario, simulate_tiles
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback
from napari_lbs._core.foundation import available_threads, run_in_workers

__all__ = ["DiagnosisSettings", "Diagnoser", "amortized_diagnoser", "default_cache_dir", "forest_posterior", "load_diagnoser"]

CACHE_FORMAT = "napari-lbs diagnoser 3"


@dataclass(frozen=True)
class DiagnosisSettings:
    """How a diagnosis learns and decides.

    Attributes
    ----------
    simulations : int
        Scenarios simulated to train the diagnoser (once per setup; cached).
    trees : int
        Trees of the forest.
    level : float
        An effect is named when its probability of being present reaches this; else the
        verdict is nothing missing (where that model reaches it) or undecided. Chosen on the
        development suite (`benchmarks/withheld_suite.py`), never on the frozen one: 0.35 keeps
        a margin of 0.1 over the largest probability any effect got in its controls (0.23)
        and names 5 of its 11 effects (0.5: 4; 0.25: 8, with a margin of 0.02).
    neighbours : int
        Simulations of each model closest to the experiment (in every feature) that the
        two-sample tests compare it with.
    seed : int
        The two-sample tests' folds. The diagnoser itself is trained with ``training_seed``,
        so the same hologram gets the same posterior whatever ``seed``.
    training_seed : int
    jobs : int or None
        Processes that simulate, one thread each (default and most: `available_threads`, the
        cores this process may use or ``NAPARI_LBS_THREADS``). More than 1 spawns processes
        (`run_in_workers`), so a script must start its work under ``if __name__ == "__main__":``.
    cache_dir : str or None
        Where diagnosers are kept (default `default_cache_dir`).
    """

    simulations: int = 2000
    trees: int = 300
    level: float = 0.35
    neighbours: int = 6
    seed: int = 0
    training_seed: int = 0
    jobs: int | None = None
    cache_dir: str | None = None

    def __post_init__(self) -> None:
        for name, low in (("simulations", 20), ("trees", 10), ("neighbours", 1), ("seed", 0), ("training_seed", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InputError(f"{name}: expected an integer of at least {low}, got {value!r}")
        if not 0.0 < float(self.level) <= 1.0:
            raise InputError(f"level: expected a probability in (0, 1], got {self.level!r}")
        if self.jobs is not None and (isinstance(self.jobs, bool) or not isinstance(self.jobs, int) or self.jobs < 1):
            raise InputError(f"jobs: expected a positive integer, got {self.jobs!r}")


@dataclass(frozen=True)
class Diagnoser:
    """A trained diagnoser and the simulations it was trained on.

    ``features`` (simulations, F) the set features, ``summaries`` (simulations, tiles, S) each
    simulated tile's summaries, ``present`` (simulations, candidates) which effects each
    scenario had, ``params`` ``{"effect.param": (simulations,)}`` (NaN where absent).
    """

    key: str
    candidates: tuple
    summary_names: list
    features: np.ndarray
    summaries: np.ndarray
    present: np.ndarray
    params: dict
    forest: ForestArrays
    meta: dict

    @property
    def feature_names(self) -> list[str]:
        return feature_names(self.summary_names)


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/napari-lbs/diagnosers`` (``~/.cache/...`` where unset)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "napari-lbs" / "diagnosers"


# the modules whose code makes a diagnoser's simulations and features: any change to them makes another diagnoser
_SIMULATION_CODE = ("physics._optics", "physics._synthesis", "physics._effects", "gap._scenarios", "gap._summaries", "gap._features", "gap._forest")


def _code_hash() -> str:
    digest = hashlib.sha256()
    for name in _SIMULATION_CODE:
        spec = importlib.util.find_spec(f"napari_lbs._core.{name}")
        digest.update(Path(spec.origin).read_bytes())
    return digest.hexdigest()[:16]


def _setup(config: ExperimentConfig, grid: TileGrid, prior: ScenarioPrior, settings: DiagnosisSettings) -> dict:
    return {
        "format": CACHE_FORMAT, "napari_lbs": __version__, "code": _code_hash(), "config": config.to_dict(), "grid": {"frame_shape": list(grid.frame_shape), "tile_px": grid.tile_px, "per_side": grid.per_side},
        "prior": {"candidates": list(prior.candidates), "none": prior.none, "one": prior.one, "known": prior.known, "bits": prior.bits, "density": list(prior.density), "strength": list(prior.strength)},
        "simulations": settings.simulations, "trees": settings.trees, "training_seed": settings.training_seed,
    }


def _simulate(task: tuple) -> tuple[int, np.ndarray, np.ndarray, tuple, dict]:
    """One training simulation: (index, set features, tile summaries, effects present, their parameters)."""
    index, config, grid, prior, seed = task
    rng = np.random.default_rng([seed, index])
    scenario = draw_scenario(prior, rng)
    tiles = simulate_tiles(scenario, config, grid, rng)
    summaries, _ = set_summaries(tiles, config=config)
    features = set_features(tiles, summaries, grid.centres())
    params = {f"{e}.{k}": float(v) for e in scenario.present for k, v in scenario.effects[e].items()}
    return index, features, summaries, scenario.present, params


def _simulations(tasks: list, *, jobs: int, steps: Steps) -> list:
    """Every task's `_simulate`, in task order, on ``jobs`` processes (`run_in_workers`); one progress step each; a stop raises `Stopped`."""
    return run_in_workers(_simulate, tasks, workers=jobs, steps=steps)


def amortized_diagnoser(
    config: ExperimentConfig,
    grid: TileGrid,
    prior: ScenarioPrior,
    *,
    settings: DiagnosisSettings = DiagnosisSettings(),
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> Diagnoser:
    """The diagnoser of this setup: read from the cache, or trained (one progress step per simulation) and cached.

    A stop (``should_stop``) raises `Stopped` and caches nothing.
    """
    setup = _setup(config, grid, prior, settings)
    key = hashlib.sha256(json.dumps(setup, sort_keys=True).encode()).hexdigest()[:16]
    folder = Path(settings.cache_dir) if settings.cache_dir else default_cache_dir()
    path = folder / f"diagnoser-{key}.npz"
    if path.exists() or path.is_symlink():
        diagnoser = load_diagnoser(path)
        if diagnoser.key == key:
            return diagnoser
    start = time.perf_counter()
    steps = Steps(settings.simulations + 1, progress=progress, should_stop=should_stop)
    tasks = [(i, config, grid, prior, settings.training_seed) for i in range(settings.simulations)]
    results = _simulations(tasks, jobs=settings.jobs or available_threads(), steps=steps)
    steps.check()
    candidates = tuple(prior.candidates)
    features = np.stack([r[1] for r in results])
    summaries = np.stack([r[2] for r in results]).astype(np.float32)
    present = np.array([[c in r[3] for c in candidates] for r in results], bool)
    param_names = sorted({name for r in results for name in r[4]})
    params = {name: np.array([r[4].get(name, np.nan) for r in results], np.float64) for name in param_names}
    forest = train_forest(features, forest_answers(present), trees=settings.trees, seed=settings.training_seed, jobs=min(settings.jobs or available_threads(), 4))
    steps.advance()
    _, names = set_summaries([np.random.default_rng(0).uniform(0.5, 1.5, (grid.tile_px, grid.tile_px)).astype(np.float32)], config=config)  # the names only
    meta = {**setup, "key": key, "summary_names": [list(n) for n in names], "candidates": list(candidates), "train_seconds": round(time.perf_counter() - start, 1)}
    diagnoser = Diagnoser(key, candidates, [tuple(n) for n in names], features, summaries, present, params, forest, meta)
    _save(diagnoser, path)
    return diagnoser


def forest_answers(present: np.ndarray) -> np.ndarray:
    """(simulations, 2 C + 2) yes/no answers the forest learns: each of the C effects present, then the model as one-hot (nothing, each effect alone, two effects).

    One forest learns both: its splits serve the model (is anything missing, which one, or two)
    and each effect's presence, which tells the two effects of a pair apart.
    """
    count = present.sum(axis=1)
    alone = present & (count == 1)[:, None]
    return np.concatenate([present, (count == 0)[:, None], alone, (count >= 2)[:, None]], axis=1)


def forest_posterior(diagnoser: Diagnoser, x: np.ndarray) -> tuple[dict, dict]:
    """(each candidate's probability of being present, each model's probability) for one feature vector ``x``.

    Models: ``"null"``, each effect alone, and each pair ``"a+b"`` (catalog order): the
    forest's probability of two effects, shared among the pairs in proportion to the product
    of their effects' probabilities of being present.
    """
    answers = diagnoser.forest.predict(np.asarray(x, np.float32)[None, :])[0].astype(np.float64)
    c = len(diagnoser.candidates)
    presence = dict(zip(diagnoser.candidates, answers[:c], strict=True))
    model = {"null": answers[c], **dict(zip(diagnoser.candidates, answers[c + 1 : 2 * c + 1], strict=True))}
    two = answers[2 * c + 1]
    pairs = {f"{a}+{b}": presence[a] * presence[b] for i, a in enumerate(diagnoser.candidates) for b in diagnoser.candidates[i + 1 :]}
    total = sum(pairs.values())
    for name, weight in pairs.items():
        model[name] = two * (weight / total if total > 0 else 1.0 / len(pairs))
    norm = sum(model.values())
    return presence, {k: v / norm for k, v in model.items()}


def _save(diagnoser: Diagnoser, path: Path) -> None:
    """Write the cache file atomically (a temporary name, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {
        "meta": np.array(json.dumps(diagnoser.meta)), "features": diagnoser.features, "summaries": diagnoser.summaries, "present": diagnoser.present,
        "param_names": np.array(list(diagnoser.params), dtype=str), **diagnoser.forest.arrays(),
    }
    for i, values in enumerate(diagnoser.params.values()):
        arrays[f"param_{i}"] = values
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(temporary, "wb") as file:
        np.savez(file, **arrays)
    os.replace(temporary, path)


def load_diagnoser(path) -> Diagnoser:
    """A cached diagnoser (`amortized_diagnoser`); anything else raises `InputError` naming the file."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except (OSError, RuntimeError) as error:
        raise InputError(f"{path}: cannot be read as a diagnoser cache ({type(error).__name__})") from None
    if not stat.S_ISREG(mode):  # a FIFO would block the read forever, a device never end
        raise InputError(f"{path}: not a regular file (a FIFO, device or socket); remove it to train the diagnoser again")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if meta.get("format") != CACHE_FORMAT:
                raise ValueError(f"format {meta.get('format')!r}, expected {CACHE_FORMAT!r}")
            names = [str(n) for n in data["param_names"]]
            diagnoser = Diagnoser(
                str(meta["key"]), tuple(meta["candidates"]), [tuple(n) for n in meta["summary_names"]], np.asarray(data["features"], np.float32),
                np.asarray(data["summaries"], np.float32), np.asarray(data["present"], bool), {n: np.asarray(data[f"param_{i}"], np.float64) for i, n in enumerate(names)},
                ForestArrays.from_arrays(data), meta,
            )
    except Exception as error:  # a truncated zip, a JSON of the wrong shape, a missing array: never the file's code
        raise InputError(f"{path}: not a napari-lbs diagnoser cache ({type(error).__name__}: {error})") from None
    problem = _cache_problem(diagnoser)
    if problem:
        raise InputError(f"{path}: not a napari-lbs diagnoser cache ({problem}); remove it to train the diagnoser again")
    return diagnoser


def _cache_problem(diagnoser: Diagnoser) -> str | None:
    """What is wrong with a loaded cache's arrays (shapes, lengths, finiteness), or None."""
    if diagnoser.features.ndim != 2 or diagnoser.summaries.ndim != 3 or diagnoser.present.ndim != 2:
        return "features, summaries and present: expected 2-D, 3-D and 2-D arrays"
    n = diagnoser.features.shape[0]
    forest = diagnoser.forest
    if not (diagnoser.present.shape == (n, len(diagnoser.candidates)) and forest.value.shape[1] == 2 * len(diagnoser.candidates) + 2 and diagnoser.summaries.shape[0] == n
            and forest.feature.max(initial=-1) < diagnoser.features.shape[1]):
        return "arrays of inconsistent shapes"
    if len(diagnoser.summary_names) != diagnoser.summaries.shape[2] or not all(isinstance(c, str) for c in diagnoser.candidates):
        return "summary names or candidates that do not match the arrays"
    if np.isinf(diagnoser.features).any() or np.isinf(diagnoser.summaries).any():
        return "infinite features or summaries"
    for name, values in diagnoser.params.items():
        if values.shape != (n,) or np.isinf(values).any():  # NaN marks an absent effect
            return f"param {name}: expected {n} finite values or NaN"
    return None
