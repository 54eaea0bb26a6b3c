"""A blur that differs by direction: outside the catalog, whose blurs (a sensor's, a source's) are round.

The sample moving during the exposure streaks every particle's pattern along its motion; an
astigmatic or tilted optical path blurs one direction more than the other. The catalog's
round blur takes the mean of the two out, and leaves the difference. Near the fitted model
``M`` a Gaussian blur of covariance ``σ² I + Δ`` changes the frame by ``½ Σ Δ_ij ∂_i ∂_j M``
(the heat equation), so with the round part fitted, a blur that differs by direction adds

    a (∂_xx − ∂_yy) M + b ∂_xy M,

with ``Δ = [[2a, b], [b, −2a]]``: the two regressors of a score test (Rao, 1948), linear and
fitted in one step. ``a, b`` are fitted by least squares on one colour's tiles of the final
model's residual and judged on the other colour's tiles by the held-out likelihood
(`whittle_loglik`), as every effect is; the sign test's z counts the judged tiles that gain.
A particle the scene misfits leaves structure along its own directions, different in every
tile, which the other colour's tiles do not share; a blur by direction is the same in every
tile.

Reported: the held-out gain and its z, the covariance difference between the blur's long and
short axes ``2 √(4a² + b²)`` (px²; a streak of length L adds L²/12 along it) and the long
axis's angle from the frame's x axis, ``½ atan2(b, 2a)`` (rad), each the mean of the two
colours' fits.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.gap._heldout import TileSplit, tile_spectra, whittle_loglik
from napari_lbs._core.gap._nested import gain_and_z

__all__ = ["directional_blur_test"]


def _regressors(mean: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(∂_xx − ∂_yy) M`` and ``∂_xy M`` by central differences (px⁻²), edges repeated."""
    padded = np.pad(mean, 1, mode="edge")
    centre = padded[1:-1, 1:-1]
    d_xx = padded[1:-1, 2:] + padded[1:-1, :-2] - 2.0 * centre
    d_yy = padded[2:, 1:-1] + padded[:-2, 1:-1] - 2.0 * centre
    d_xy = 0.25 * (padded[2:, 2:] - padded[2:, :-2] - padded[:-2, 2:] + padded[:-2, :-2])
    return d_xx - d_yy, d_xy


def directional_blur_test(residuals: tuple[np.ndarray, np.ndarray], means: tuple[np.ndarray, np.ndarray], split: TileSplit,
                          baseline_loglik: np.ndarray) -> dict:
    """The held-out gain of a blur that differs by direction over the fitted model (module docstring).

    Parameters
    ----------
    residuals, means : two (rows, cols) arrays each
        The final model's residual and mean under its fit on the tiles of colour 0, then 1
        (`FrameFit`).
    split : TileSplit
    baseline_loglik : (tiles,) array
        The final model's held-out log-likelihood per tile (`FrameFit.loglik`).

    Returns
    -------
    dict
        ``gain_nats``, ``z`` (the sign test over the judged tiles, `gain_and_z`'s), and the fitted
        ``variance_difference_px2`` and ``angle_rad``.
    """
    spectra, differences, angles = [], [], []
    for colour, (residual, mean) in enumerate(zip(residuals, means, strict=True)):
        columns = _regressors(np.asarray(mean, np.float64))
        fitted = split.mask(colour)
        design = np.stack([c[fitted] for c in columns], axis=1)
        (a, b), *_ = np.linalg.lstsq(design, residual[fitted], rcond=None)
        spectra.append(tile_spectra(residual - a * columns[0] - b * columns[1], split))
        differences.append(2.0 * float(np.hypot(2.0 * a, b)))
        angles.append(0.5 * float(np.arctan2(b, 2.0 * a)))
    gain, z = gain_and_z(whittle_loglik(tuple(spectra), split), baseline_loglik)
    # the two colours' axes averaged as directions (an angle and the same angle + π are one axis)
    angle = 0.5 * float(np.angle(np.mean(np.exp(2j * np.asarray(angles)))))
    return {"gain_nats": gain, "z": z, "variance_difference_px2": float(np.mean(differences)), "angle_rad": angle % np.pi}
