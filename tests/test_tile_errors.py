"""Standard errors of fitted parameters with the tiles as clusters (`clustered_errors`)."""

import numpy as np
import pytest

from napari_lbs._core.gap._tile_errors import clustered_errors


def _clustered_line(rng: np.random.Generator, *, clusters: int = 8, per_cluster: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``y = 1 + 2 x + e``: within each cluster the regressor and the noise share a common part, as a tile's misfit does."""
    labels = np.repeat(np.arange(clusters), per_cluster)
    x = rng.normal(size=clusters)[labels] + 0.3 * rng.normal(size=labels.size)
    y = 1.0 + 2.0 * x + rng.normal(size=clusters)[labels] + 0.3 * rng.normal(size=labels.size)
    return np.stack([np.ones_like(x), x], axis=1), y, labels


def test_the_errors_are_the_spread_of_the_fit_over_draws_where_the_pixels_errors_are_not():
    """Over 400 draws of a line with clustered noise the slope scatters by what the tiles' errors say, several times the formal error."""
    rng = np.random.default_rng(0)
    slopes, clustered, formal = [], [], []
    for _ in range(400):
        design, y, labels = _clustered_line(rng)
        coefficients, *_ = np.linalg.lstsq(design, y, rcond=None)
        residuals = y - design @ coefficients
        slopes.append(coefficients[1])
        clustered.append(clustered_errors(-design, residuals, labels)[1])  # the residuals' Jacobian is -design
        formal.append(np.sqrt(residuals.var() * np.linalg.inv(design.T @ design)[1, 1]))
    spread = np.std(slopes)
    assert np.sqrt(np.mean(np.square(clustered))) == pytest.approx(spread, rel=0.3)
    assert np.mean(formal) < 0.5 * spread


def test_a_parameter_on_a_bound_has_no_error_and_a_direction_nothing_constrains_none_either():
    rng = np.random.default_rng(1)
    design, y, labels = _clustered_line(rng)
    errors = clustered_errors(-design, y - design @ np.array([1.0, 2.0]), labels, fixed=np.array([False, True]))
    assert np.isfinite(errors[0]) and np.isnan(errors[1])
    flat = np.concatenate([design, np.zeros((design.shape[0], 1))], axis=1)
    assert np.isnan(clustered_errors(-flat, y, labels)[2])
    assert np.all(np.isnan(clustered_errors(-design, y, np.zeros_like(labels))))  # one tile cannot tell its own spread
