"""Scoring reconstructed particles against a reference: one-to-one matching, ER and JI.

ER = 1 - FN / n_truth and JI = TP / (TP + FP + FN) (seed paper, Eqs. 4–5). A prediction
matches a reference particle when its lateral distance is <= ``lateral_tol_um`` and its axial
distance <= ``axial_tol_um``; each reference is matched at most once, and the assignment
maximises the number of matches, then minimises the summed normalised distance (Hungarian
algorithm, `scipy.optimize.linear_sum_assignment`).

`seed_scores` reproduces the seed's scoring for comparison: every prediction within tolerance
of some reference counts as a true positive, so one particle seen on several planes counts
several times. Those figures are optimistic; show them only next to the one-to-one ones.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.optimize import linear_sum_assignment

from napari_lbs._core.foundation import InputError

__all__ = ["match_particles", "score_particles", "depth_errors_um", "diameter_errors_um", "seed_scores", "LATERAL_TOL_UM", "AXIAL_TOL_UM"]

LATERAL_TOL_UM = 22.0
AXIAL_TOL_UM = 150.0


def _positions(table: Mapping[str, np.ndarray], name: str) -> np.ndarray:
    try:
        columns = [np.asarray(table[c], dtype=np.float64) for c in ("x_um", "y_um", "z_um")]
    except KeyError as missing:
        raise InputError(f"{name}: missing column {missing.args[0]}") from None
    positions = np.stack(columns, axis=1) if columns[0].size else np.zeros((0, 3))
    if not np.all(np.isfinite(positions)):
        raise InputError(f"{name}: contains NaN or infinite positions")
    return positions


def _feasible_distances(pred, truth, lateral_tol_um, axial_tol_um):
    if not (0 < lateral_tol_um < np.inf and 0 < axial_tol_um < np.inf):  # NaN fails every comparison: refused too
        raise InputError(f"tolerances: expected positive finite values, got lateral {lateral_tol_um}, axial {axial_tol_um}")
    lateral = np.hypot(pred[:, None, 0] - truth[None, :, 0], pred[:, None, 1] - truth[None, :, 1])
    axial = np.abs(pred[:, None, 2] - truth[None, :, 2])
    # A hair of slack so a distance equal to the tolerance matches despite float round-off.
    feasible = (lateral <= lateral_tol_um * (1 + 1e-9)) & (axial <= axial_tol_um * (1 + 1e-9))
    return feasible, np.hypot(lateral / lateral_tol_um, axial / axial_tol_um)


def match_particles(pred: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], *, lateral_tol_um: float = LATERAL_TOL_UM, axial_tol_um: float = AXIAL_TOL_UM) -> list[tuple[int, int]]:
    """One-to-one matches ``(pred_index, truth_index)`` of the largest possible size."""
    p, t = _positions(pred, "prediction"), _positions(truth, "truth")
    if not p.size or not t.size:
        return []
    feasible, distance = _feasible_distances(p, t, lateral_tol_um, axial_tol_um)
    # An infeasible pair costs more than any set of feasible ones: the optimum has the most matches.
    penalty = 2.0 * np.sqrt(2.0) * min(feasible.shape) + 1.0
    rows, cols = linear_sum_assignment(np.where(feasible, distance, penalty))
    return [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if feasible[r, c]]


def _metrics(tp: int, fp: int, fn: int, n_truth: int, n_pred: int) -> dict:
    # With nothing to find nothing was missed (ER 1); with nothing on either side the match is perfect (JI 1).
    er = 1.0 - fn / n_truth if n_truth else 1.0
    ji = tp / (tp + fp + fn) if tp + fp + fn else 1.0
    return {"tp": tp, "fp": fp, "fn": fn, "n_truth": n_truth, "n_pred": n_pred, "er": float(er), "ji": float(ji)}


def score_particles(pred: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], *, lateral_tol_um: float = LATERAL_TOL_UM, axial_tol_um: float = AXIAL_TOL_UM) -> dict:
    """One-to-one metrics: the metrics JSON of docs/formats.md as a dict."""
    n_pred, n_truth = len(_positions(pred, "prediction")), len(_positions(truth, "truth"))
    tp = len(match_particles(pred, truth, lateral_tol_um=lateral_tol_um, axial_tol_um=axial_tol_um))
    return _metrics(tp, n_pred - tp, n_truth - tp, n_truth, n_pred)


def depth_errors_um(pred: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], *, lateral_tol_um: float = LATERAL_TOL_UM, axial_tol_um: float = AXIAL_TOL_UM) -> np.ndarray:
    """Signed depth errors ``z_pred - z_truth`` (µm) of the one-to-one matches (negative: nearer the sensor)."""
    return _matched_differences(pred, truth, "z_um", lateral_tol_um=lateral_tol_um, axial_tol_um=axial_tol_um)


def diameter_errors_um(pred: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], *, lateral_tol_um: float = LATERAL_TOL_UM, axial_tol_um: float = AXIAL_TOL_UM) -> np.ndarray:
    """Signed diameter errors ``d_pred - d_truth`` (µm) of the one-to-one matches."""
    return _matched_differences(pred, truth, "diameter_um", lateral_tol_um=lateral_tol_um, axial_tol_um=axial_tol_um)


def _matched_differences(pred, truth, column: str, *, lateral_tol_um: float, axial_tol_um: float) -> np.ndarray:
    matches = match_particles(pred, truth, lateral_tol_um=lateral_tol_um, axial_tol_um=axial_tol_um)
    return np.array([float(pred[column][i]) - float(truth[column][j]) for i, j in matches])


def seed_scores(pred: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], *, lateral_tol_um: float = LATERAL_TOL_UM, axial_tol_um: float = AXIAL_TOL_UM) -> dict:
    """The seed's (optimistic) scoring: every prediction near any reference is a TP."""
    p, t = _positions(pred, "prediction"), _positions(truth, "truth")
    if not p.size or not t.size:
        return _metrics(0, len(p), len(t), len(t), len(p))
    feasible, _ = _feasible_distances(p, t, lateral_tol_um, axial_tol_um)
    tp = int(feasible.any(axis=1).sum())
    fn = int((~feasible.any(axis=0)).sum())
    return _metrics(tp, len(p) - tp, fn, len(t), len(p))
