"""The gap statistic: excess standardised χ² between real and simulated summaries, and where it lies.

The gap between a set of real tiles ``R`` and simulated tiles ``S`` over the K summaries::

    z_k = (mean R_k - mean S_k) / (spread_k · sqrt(1/n_R + 1/n_S)),   gap = max(0, mean_k z_k² - 1)

with ``spread_k`` the experiment's own tile-to-tile spread (`real_spread`): 0 when the two
sets are as alike as sampling allows. "Where" tables give, per group, the rms of
``|Δ_k| / (sqrt 2 · spread_k)``: 1 means "as different as two tiles of the experiment".
(../shared/notes/calibration-and-gap.md: a standardised χ² separated models where a mean
absolute difference failed.)
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core._gap._summaries import SUMMARY_GROUPS

__all__ = ["real_spread", "gap_statistic", "where_gap"]


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
