"""The particles' optics told by the power spectrum of their fringes: opaque spheres against transparent ones.

A transparent sphere is a ball lens: what it refracts leaves it in a wide cone, and at the
sensor interferes with the unscattered light in fine rings far out from its centre, up to
where the pixel's box transfer falls to zero (1 cycle per pixel, aliased). An opaque sphere
only diffracts, into a narrow lobe of coarse rings. On an independent Lorenz–Mie frame of
polystyrene spheres in water (512², 2.2 µm pixels) the project's spheres rendered to 1 cycle
per pixel reproduce the frame to 0.004 rms, opaque spheres at the same places to 0.038;
rendered to the Nyquist disc only (what a particle's fit patch models), 0.031 and 0.041: the
difference lies in the far rings, whose phase a depth error of a micrometre turns round but
whose power it does not change.

So the test compares power, not phase, and compares it by spatial frequency: the rings'
frequency at the sensor is the angle the light left the sphere at, so the refracted cone's
power lies in a band of frequencies whose extent follows the index contrast, where an
opaque sphere's diffraction has fallen away. Each tile's radial power spectrum from
``_BAND_CYCLES_PER_PX[0]`` to ``[1]`` cycles per pixel (below it the coarse rings both models
share, and an envelope) is modelled as a scale times the power spectrum of the scene
rendered under one particle model (opaque; transparent at each index contrast of a grid),
through the camera's blur where the frame's effects hold one, plus the noise: a white floor
and photon noise growing with the tile's light, each also through that blur (a colour
sensor's interpolation blurs its noise). The nonnegative coefficients are fitted on one
colour of the checkerboard of tiles by relative least squares and judged on the other by
each tile's mean squared log ratio over the bins. The best transparent model against the
opaque one, tile by tile, gives a sign test's z, as the catalog's effects get.

A map of the fine rings' local power (a high pass's square smoothed over a few pixels)
cannot tell spheres of index contrast 0.14–0.18 (z 0–1 on frozen frames): their refracted
cones overlap across the frame and raise that power nearly everywhere alike, which the map's
free offset takes as noise. Their spectra keep the cone's shape.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from napari_lbs._core.gap._confidence import sign_z
from napari_lbs._core.gap._heldout import TileSplit, tile_spectra
from napari_lbs._core.gap._particle_models import OPAQUE, optics_call

__all__ = ["optics_power_test"]

_BAND_CYCLES_PER_PX = (0.08, 0.70)  # the fine rings' band: above the coarse rings and an envelope, to the pixel grid's corner
_BINS = 24


def _band_edges() -> np.ndarray:
    return np.linspace(*_BAND_CYCLES_PER_PX, _BINS + 1)


def _ring_powers(image: np.ndarray, split: TileSplit, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each tile's power spectrum (`tile_spectra`, each tile's mean removed) averaged over rings of radial frequency.

    Returns ``(tiles, bins)`` mean powers and the ``(bins,)`` number of frequencies in each
    ring (``edges``: the rings' edges, cycles per pixel).
    """
    centred = np.array(image, dtype=np.float64)
    for window in split.windows():
        centred[window] -= centred[window].mean()
    frequency = np.hypot(*np.meshgrid(np.fft.fftfreq(split.size), np.fft.fftfreq(split.size), indexing="ij"))
    ring = np.digitize(frequency.ravel(), edges) - 1
    inside = (ring >= 0) & (ring < len(edges) - 1)
    counts = np.bincount(ring[inside], minlength=len(edges) - 1).astype(np.float64)
    spectra = tile_spectra(centred, split).reshape(len(split.windows()), -1)[:, inside]
    sums = np.stack([np.bincount(ring[inside], tile, len(edges) - 1) for tile in spectra])
    return sums / np.maximum(counts, 1.0), counts


def _design(model_power: np.ndarray, light: float, blur_transfer: np.ndarray | None) -> np.ndarray:
    """(bins, terms): the model's power, the white floor, photon noise; blurred noise where the camera blurs."""
    columns = [model_power, np.ones_like(model_power), np.full_like(model_power, light)]
    if blur_transfer is not None:
        columns += [blur_transfer, light * blur_transfer]
    return np.stack(columns, axis=1)


def optics_power_test(data: np.ndarray, models: dict[str, np.ndarray], split: TileSplit, *, blur_px: float = 0.0, level_z: float = 3.0) -> dict:
    """Opaque against transparent spheres by the power spectrum each puts into the fine rings' band (module docstring).

    Parameters
    ----------
    data : (rows, cols) array
        The frame, unobstructed light 1.
    models : dict
        The scene under each particle model (`particle_models`: ``"opaque"`` and one per
        transparent index contrast), through the camera's blur.
    split : TileSplit
        The held-out checkerboard.
    blur_px : float
        The camera's blur (σ, pixels) the models went through: the noise's terms go through
        it too.
    level_z : float
        The sign test's z from which transparent spheres are named.

    Returns
    -------
    dict
        ``model`` (``"transparent"`` from ``z >= level_z``, ``"opaque"`` to
        ``z <= -level_z``, else ``"undecided"``: the frame's fine rings cannot tell), ``z``,
        ``transparent_better`` and ``transparent_worse`` (tiles), ``index_contrast`` (the
        best transparent model's), ``heldout_error`` (the mean squared log ratio of the
        tiles' spectra) and ``slope`` per model (the fitted scale of its power: near 1 for
        the model the frame holds, through its camera), ``band_cycles_per_px``;
        ``tile_differences``, each tile's held-out error of the opaque model less the best
        transparent one's, whose signs the sign test counts (`_confidence`).
    """
    edges = _band_edges()
    centres = 0.5 * (edges[1:] + edges[:-1])
    windows, colours = split.windows(), split.colours()
    measured, counts = _ring_powers(data, split, edges)
    measured = np.maximum(measured, 1e-30)
    weights = counts / counts.sum()
    light = np.array([float(data[w].mean()) for w in windows])
    # a Gaussian blur of σ passes power as exp(-(2πfσ)²)
    blur_transfer = np.exp(-((2 * np.pi * centres * blur_px) ** 2)) if blur_px > 0 else None
    errors, slopes = {}, {}
    for name, rendered in models.items():
        predicted = _ring_powers(rendered, split, edges)[0]
        error = np.zeros(len(windows))
        fitted_slopes = []
        for fitted_on in (0, 1):
            chosen = np.flatnonzero(colours == fitted_on)
            # relative least squares: each bin's residual over its measured power (a periodogram's spread grows with its mean)
            design = np.concatenate([_design(predicted[k], light[k], blur_transfer) / measured[k][:, None] for k in chosen])
            coefficients, _ = nnls(design, np.ones(design.shape[0]))
            fitted_slopes.append(float(coefficients[0]))
            for k in np.flatnonzero(colours != fitted_on):
                model_power = np.maximum(_design(predicted[k], light[k], blur_transfer) @ coefficients, 1e-30)
                error[k] = float(np.sum(weights * np.log(measured[k] / model_power) ** 2))
        errors[name], slopes[name] = error, float(np.mean(fitted_slopes))
    transparent = [name for name in errors if name != OPAQUE]
    best = min(transparent, key=lambda name: float(errors[name].mean()))
    difference = errors[OPAQUE] - errors[best]  # > 0: the transparent model predicts the tile's spectrum better
    better, worse = int(np.sum(difference > 0)), int(np.sum(difference < 0))
    z = sign_z(difference)
    return {
        "band_cycles_per_px": list(_BAND_CYCLES_PER_PX),
        "model": optics_call(z, level_z=level_z),
        "z": z,
        "transparent_better": better,
        "transparent_worse": worse,
        "tile_differences": difference,
        "index_contrast": float(best),
        "heldout_error": {name: float(e.mean()) for name, e in errors.items()},
        "slope": slopes,
    }
