"""Classifier two-sample test (C2ST): can a classifier tell the experiment's tiles from simulated ones?

A logistic regression on the standardised tile summaries, cross-validated: its held-out
balanced accuracy is 0.5 when the two samples are indistinguishable and approaches 1 when
they differ (Lopez-Paz & Oquab 2017). Each experiment tile's held-out probability of being
real says where the difference lies; the test restricted to one group of summaries (a
frequency band, a depth) says in which terms.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["c2st"]


def _wilson(successes: float, trials: int, z: float = 1.645) -> tuple[float, float]:
    """90 % Wilson interval of a proportion."""
    if trials <= 0:
        return (0.0, 1.0)
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    return (max(0.0, centre - half), min(1.0, centre + half))


def c2st(real: np.ndarray, simulated: np.ndarray, *, folds: int = 5, seed: int = 0) -> dict:
    """Two-sample test of ``real`` (n, features) against ``simulated`` (m, features).

    Returns
    -------
    dict
        ``accuracy`` (held-out balanced accuracy: 0.5 = indistinguishable, 1 = always told
        apart), ``interval`` (its 90 % Wilson interval over the n + m held-out decisions),
        ``real_probability`` (n,): each real tile's held-out probability of being real.
    """
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import StratifiedKFold

    real, simulated = np.asarray(real, np.float64), np.asarray(simulated, np.float64)
    x = np.vstack([real, simulated])
    y = np.r_[np.ones(len(real), int), np.zeros(len(simulated), int)]
    folds = max(2, min(folds, len(real), len(simulated)))
    probability = np.empty(len(x))
    for train, test in StratifiedKFold(folds, shuffle=True, random_state=seed).split(x, y):
        centre, scale = x[train].mean(axis=0), x[train].std(axis=0)
        scale[scale == 0] = 1.0
        model = LogisticRegression(C=0.1, class_weight="balanced", max_iter=500)
        model.fit((x[train] - centre) / scale, y[train])
        probability[test] = model.predict_proba((x[test] - centre) / scale)[:, 1]
    right = (probability >= 0.5) == (y == 1)
    accuracy = 0.5 * (right[y == 1].mean() + right[y == 0].mean())
    return {"accuracy": float(accuracy), "interval": [float(v) for v in _wilson(accuracy * len(x), len(x))], "real_probability": probability[: len(real)]}
