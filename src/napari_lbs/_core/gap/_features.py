"""What a diagnosis measures on a set of tiles: each tile's summaries and the set's features.

Each tile is summarised by `tile_summaries` (frequency bands, depth planes, intensity,
noise, particle appearance). A set of tiles — one hologram read on a `TileGrid` — becomes one
feature vector: every summary's mean and spread over the tiles, and the field-wide envelope
(a quadratic surface fitted to the tiles' log mean brightness over their places on the
sensor: a vignetting or a beam spans tiles, where a tile's own brightness is mostly its particles).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.gap._summaries import _tiles_summaries

__all__ = ["set_summaries", "set_features", "feature_names"]

_ENVELOPE_TERMS = ("tilt y", "tilt x", "curvature y", "curvature x", "saddle", "residual")


def set_summaries(tiles: Sequence[np.ndarray], *, config: ExperimentConfig) -> tuple[np.ndarray, list]:
    """(tiles, summaries) float32 matrix of one set of tiles, and each summary's (name, group).

    Every tile gets the set's mean brightness as its field mean, and its own strongest
    spectral peak as the fringe frequency: the same code path for real and simulated tiles.
    """
    means = [float(np.mean(t, dtype=np.float64)) for t in tiles]
    field_mean = float(np.mean(means))
    values, names = _tiles_summaries(list(tiles), config=config, fringe_frequency=None, field_means=[field_mean] * len(tiles), surroundings=[None] * len(tiles))
    return np.nan_to_num(np.asarray(values, np.float32), nan=0.0, posinf=0.0, neginf=0.0), names


def _envelope(tiles: Sequence[np.ndarray], centres: np.ndarray) -> np.ndarray:
    """Quadratic surface of the tiles' log mean brightness over their centres (fractions of the frame) and its residual spread."""
    level = np.log(np.maximum([float(np.mean(t, dtype=np.float64)) for t in tiles], 1e-9))
    y, x = centres[:, 0], centres[:, 1]
    design = np.stack([np.ones_like(y), y, x, y * y, x * x, x * y], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, level - level.mean(), rcond=None)
    residual = level - level.mean() - design @ coefficients
    return np.concatenate([coefficients[1:], [residual.std()]])


def set_features(tiles: Sequence[np.ndarray], summaries: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """One feature vector (float32) of a set of tiles: the summaries' mean and spread over the tiles, and the field envelope (`feature_names`)."""
    return np.concatenate([summaries.mean(axis=0), summaries.std(axis=0), _envelope(tiles, centres)]).astype(np.float32)


def feature_names(names: list) -> list[str]:
    """The name of each entry of `set_features`, from the summaries' (name, group)."""
    return [f"mean {n}" for n, _ in names] + [f"spread {n}" for n, _ in names] + [f"field envelope {t}" for t in _ENVELOPE_TERMS]
