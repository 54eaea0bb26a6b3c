"""Standard errors of parameters fitted over a frame's tiles, the residuals correlated within each tile.

A fit of the frame's model leaves residuals that are anything but independent from pixel to
pixel: a misfit particle's rings fill its tile, and the camera's blur couples neighbours.
The formal least-squares covariance ``σ² (JᵀJ)⁻¹`` counts every pixel as a fresh draw and
makes the error bars far too small. Tiles, on the other hand, are nearly independent (the
held-out test already rests on that, `napari_lbs._core.gap._heldout`). So the errors are the
cluster-robust ("sandwich") ones, with each tile a cluster (Liang & Zeger, *Biometrika* 73,
13, 1986)::

    Cov = (JᵀJ)⁻¹ (G / (G - 1) Σ_t (s_t - s̄)(s_t - s̄)ᵀ) (JᵀJ)⁻¹,   s_t = J_tᵀ r_t,

``J_t`` and ``r_t`` the Jacobian's rows and the residuals of tile ``t``'s pixels, ``G`` the
tiles. Each tile's score ``s_t`` is how hard its pixels pull the parameters; their spread
from tile to tile is how far the fit would move with other tiles. The scores are centred: a
fit stopped before its optimum leaves a common pull, which is the optimiser's, not the
data's. With the 8 tiles of one colour of a 4 × 4 checkerboard the errors are themselves
uncertain by about a quarter (a variance of 7 degrees of freedom).
"""

from __future__ import annotations

import numpy as np

__all__ = ["clustered_errors", "mean_of_halves"]


def clustered_errors(jacobian: np.ndarray, residuals: np.ndarray, clusters: np.ndarray, *, fixed: np.ndarray | None = None) -> np.ndarray:
    """Cluster-robust standard errors of least-squares parameters (module docstring).

    Parameters
    ----------
    jacobian : (pixels, parameters) array
        The residuals' derivatives at the fit, in the parameters' own units.
    residuals : (pixels,) array
        The fit's residuals.
    clusters : (pixels,) int array
        Each pixel's tile.
    fixed : (parameters,) bool array, optional
        Parameters held on a bound of the fit: no error (NaN), and the others' errors are
        those of the fit with them fixed.

    Returns
    -------
    (parameters,) array of standard errors, in the parameters' units; NaN where a parameter
    is fixed or the tiles cannot tell it (fewer than two tiles, or no curvature along it).
    """
    jacobian = np.asarray(jacobian, dtype=np.float64)
    residuals = np.asarray(residuals, dtype=np.float64)
    clusters = np.asarray(clusters)
    count = jacobian.shape[1]
    errors = np.full(count, np.nan)
    free = np.ones(count, bool) if fixed is None else ~np.asarray(fixed, bool)
    labels = np.unique(clusters)
    if labels.size < 2 or not free.any():
        return errors
    # each column scaled to unit norm: parameters of very different units (a gain, a period in pixels) stay comparable
    norms = np.linalg.norm(jacobian, axis=0)
    free &= np.isfinite(norms) & (norms > 0)
    if not free.any():
        return errors
    columns = jacobian[:, free] / norms[free]
    scores = np.stack([columns[clusters == label].T @ residuals[clusters == label] for label in labels])
    centred = scores - scores.mean(axis=0)
    meat = centred.T @ centred * (labels.size / (labels.size - 1))
    curvature = columns.T @ columns
    if np.linalg.cond(curvature) > 1e12:
        return errors  # a direction no pixel constrains
    bread = np.linalg.inv(curvature)
    variance = np.diag(bread @ meat @ bread)
    errors[free] = np.sqrt(np.clip(variance, 0.0, None)) / norms[free]
    return errors


def mean_of_halves(values, errors, *, period: float | None = None) -> tuple[float, float]:
    """The mean of two independent measurements (the two colours' fits) and its standard error.

    Half their errors' quadrature sum, scaled up where the two disagree by more than that
    (the Particle Data Group's scale factor ``S = √(χ² / (N - 1))`` for N = 2): never below
    half their difference. NaN where either has no error. ``period``: the measurements are
    angles of that period (a fringe's phase, 2π): the second is taken within half a period of
    the first, and the mean wrapped into ``(-period/2, period/2]``, so that two readings
    either side of the wrap (3.1 and −3.1 rad) average to π, not to 0.
    """
    first, second = (float(v) for v in values)
    turned = period is not None and np.isfinite(first) and np.isfinite(second)
    if turned:
        second = first + (second - first + 0.5 * period) % period - 0.5 * period
    mean = 0.5 * (first + second)
    if turned:
        mean = 0.5 * period - (0.5 * period - mean) % period
    return float(mean), float(0.5 * max(np.hypot(*errors), abs(first - second)))
