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


def test_two_readings_of_a_phase_either_side_of_its_wrap_average_to_the_wrap_not_to_zero():
    """A fringe's phase near π reads 3.10 on one colour and −3.12 on the other: the mean is π − 0.01 and its error half their 0.06 apart, not 0 ± 3.1."""
    from napari_lbs._core.gap._tile_errors import mean_of_halves

    mean, error = mean_of_halves([3.10, -3.12], [0.01, 0.01], period=2 * np.pi)
    assert mean == pytest.approx(np.pi - 0.01, abs=1e-9) and error == pytest.approx(0.5 * (2 * np.pi - 6.22), abs=1e-9)
    # away from the wrap a period changes nothing
    assert mean_of_halves([1.0, 1.2], [0.1, 0.1], period=2 * np.pi) == pytest.approx(mean_of_halves([1.0, 1.2], [0.1, 0.1]))
