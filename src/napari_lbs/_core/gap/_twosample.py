"""Two-sample tests of the experiment's tiles against simulated ones: how far apart, and where.

`c2st`: a classifier two-sample test — a logistic regression on the standardised tile
summaries, cross-validated: its held-out balanced accuracy is 0.5 when the two samples are
indistinguishable and approaches 1 when they differ (Lopez-Paz & Oquab 2017). Each
experiment tile's held-out probability of being real says where the difference lies; the
test restricted to one group of summaries (a frequency band, a depth) says in which terms.
Its accuracy saturates at 1 once any summary separates the samples, so how *much* they
differ is measured by `mmd` (maximum mean discrepancy with a Gaussian kernel; Gretton et al.,
JMLR 13, 723, 2012), which keeps growing with the difference.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["c2st", "mmd"]


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


def mmd(real: np.ndarray, simulated: np.ndarray, *, resamples: int = 200, seed: int = 0) -> dict:
    """Squared maximum mean discrepancy between ``real`` (n, features) and ``simulated`` (m, features).

    The features are standardised by the pooled samples' spread; the Gaussian kernel's width
    is the median distance between the pooled samples (the median heuristic), fixed for the
    resamples. Returns ``value`` (the unbiased estimate; 0 for one distribution) and
    ``interval`` (90 % bootstrap interval, tiles resampled within each sample).
    """
    real, simulated = np.asarray(real, np.float64), np.asarray(simulated, np.float64)
    pooled = np.vstack([real, simulated])
    scale = pooled.std(axis=0)
    scale[scale == 0] = 1.0
    z = (pooled - pooled.mean(axis=0)) / scale
    squared = np.maximum((z * z).sum(axis=1)[:, None] + (z * z).sum(axis=1)[None, :] - 2 * z @ z.T, 0.0)
    width = np.median(squared[np.triu_indices(len(z), 1)]) or 1.0
    kernel = np.exp(-squared / (2 * width))
    n = len(real)

    def estimate(a: np.ndarray, b: np.ndarray) -> float:
        # within each sample, pairs of distinct tiles only (a resample repeats tiles: a tile with itself is no pair)
        within_a = kernel[np.ix_(a, a)][a[:, None] != a[None, :]].mean()
        within_b = kernel[np.ix_(b, b)][b[:, None] != b[None, :]].mean()
        return float(within_a + within_b - 2 * kernel[np.ix_(a, b)].mean())

    first, second = np.arange(n), np.arange(n, len(z))
    rng = np.random.default_rng(seed)
    draws = [estimate(rng.choice(first, n), rng.choice(second, len(second))) for _ in range(resamples)]
    return {"value": estimate(first, second), "interval": [float(v) for v in np.quantile(draws, (0.05, 0.95))]}
