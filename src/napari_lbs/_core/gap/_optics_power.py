"""The particles' optics told by where their fine fringes lie: opaque spheres against transparent ones.

A transparent sphere is a ball lens: what it refracts leaves it in a wide cone, and at the
sensor interferes with the unscattered light in fine rings far out from its centre, up to
where the pixel's box transfer falls to zero (1 cycle per pixel, aliased). An opaque sphere
only diffracts, into a narrow lobe of coarse rings. On an independent Lorenz–Mie frame of
polystyrene spheres in water (512², 2.2 µm pixels) the project's spheres rendered to 1 cycle
per pixel reproduce the frame to 0.004 rms, opaque spheres at the same places to 0.038;
rendered to the Nyquist disc only (what a particle's fit patch models), 0.031 and 0.041: the
difference lies in the far rings, whose phase a depth error of a micrometre turns round but
whose power it does not change.

So the test compares power, not phase. The local fine-fringe power of the frame (its square
less its Gaussian blur of ``_HIGH_PASS_PX``, smoothed over ``_SMOOTH_PX``) is regressed on that
of the scene rendered under each particle model (opaque; transparent at each index contrast
of a grid), through the camera's blur where the frame's effects hold one, with the local
light beside it (photon noise's variance grows with the light): fitted on one colour of the
checkerboard of tiles, judged on the other by the squared error of each tile. The best
transparent model against the opaque one, tile by tile, gives a sign test's z, as the
catalog's effects get. A frame whose fine fringes its camera blurs away holds no such power,
and the test says so (z near 0) rather than naming either.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, Steps
from napari_lbs._core.gap._heldout import TileSplit
from napari_lbs._core.physics import gaussian_blur
from napari_lbs._core.refine import RefineSettings, particle_holograms

__all__ = ["OPAQUE_KAPPA", "fine_fringe_power", "optics_power_test"]

OPAQUE_KAPPA = 1.0  # an absorption length λ/(4πκ) of 0.05 µm at 660 nm: opaque for a sphere of microns
_HIGH_PASS_PX = 1.5  # the fine fringes: a frame less its Gaussian blur of this σ (above about 0.1 cycles per pixel)
_SMOOTH_PX = 6.0  # their power's local mean: a Gaussian of this σ


def fine_fringe_power(image: np.ndarray) -> np.ndarray:
    """The local power of ``image``'s fine fringes: ``blur((image - blur(image, 1.5 px))², 6 px)``."""
    high = image - gaussian_blur(image, _HIGH_PASS_PX)
    return gaussian_blur(high * high, _SMOOTH_PX)


def _models(index_grid) -> dict[str, dict]:
    models = {"opaque": {"index_contrast": 0.0, "absorption": OPAQUE_KAPPA}}
    models.update({f"{v:g}": {"index_contrast": float(v), "absorption": 0.0} for v in index_grid})
    return models


def optics_power_test(data: np.ndarray, table, config: ExperimentConfig, split: TileSplit, *, index_grid, blur_px: float = 0.0,
                      settings: RefineSettings | None = None, level_z: float = 3.0, steps: Steps | None = None) -> dict:
    """Opaque against transparent spheres by the fine-fringe power each puts where (module docstring).

    Parameters
    ----------
    data : (rows, cols) array
        The frame, unobstructed light 1.
    table : pandas.DataFrame
        The frame's fitted particles (``x_um, y_um, z_um, diameter_um``): only their places
        and sizes are used, each model sets the optics.
    config : ExperimentConfig
    split : TileSplit
        The held-out checkerboard.
    index_grid : sequence of float
        Index contrasts ``n_p - n_m`` of the transparent models.
    blur_px : float
        The camera's blur (σ, pixels) the frame's effects hold, applied to every model.
    settings : RefineSettings, optional
        The medium's index and the pixel integration of the renders.
    level_z : float
        The sign test's z from which transparent spheres are named.
    steps : Steps, optional
        Advanced by each particle rendered (under every model at once, `particle_holograms`)
        and checked for a stop before each.

    Returns
    -------
    dict
        ``model`` (``"transparent"`` from ``z >= level_z``, ``"opaque"`` to
        ``z <= -level_z``, else ``"undecided"``: the frame's fine fringes cannot tell), ``z``, ``transparent_better`` and
        ``transparent_worse`` (tiles), ``index_contrast`` (the best transparent model's),
        ``heldout_error`` and ``slope`` per model (the fitted scale of its power: near 1
        for the model the frame holds, through its camera), ``particles``;
        ``tile_differences``, each tile's held-out error of the opaque model less the best
        transparent one's, whose signs the sign test counts (`_confidence`).
    """
    settings = settings or RefineSettings()
    measured = fine_fringe_power(data)
    light = gaussian_blur(data, _SMOOTH_PX)
    windows, colours = split.windows(), split.colours()
    check = (lambda: bool(steps.check())) if steps is not None else None
    errors, slopes = {}, {}
    models = _models(index_grid)
    heard = (lambda done, total: steps.advance()) if steps is not None else None
    renders = particle_holograms(data.shape, table, config, materials=list(models.values()), settings=settings, reach_cycles_per_px=1.0,
                                 progress=heard, should_stop=check)
    for name, rendered in zip(models, renders, strict=True):
        if blur_px > 0:
            rendered = gaussian_blur(rendered, blur_px)
        predicted = fine_fringe_power(rendered)
        error = np.zeros(len(windows))
        fitted_slopes = []
        for fitted_on in (0, 1):
            chosen = [w for w, c in zip(windows, colours, strict=True) if c == fitted_on]
            design = np.concatenate([np.stack([np.ones(predicted[w].size), predicted[w].ravel(), light[w].ravel()], axis=1) for w in chosen])
            target = np.concatenate([measured[w].ravel() for w in chosen])
            coefficients, *_ = np.linalg.lstsq(design, target, rcond=None)
            fitted_slopes.append(float(coefficients[1]))
            for k, (w, c) in enumerate(zip(windows, colours, strict=True)):
                if c != fitted_on:
                    error[k] = float(np.mean((measured[w] - coefficients[0] - coefficients[1] * predicted[w] - coefficients[2] * light[w]) ** 2))
        errors[name], slopes[name] = error, float(np.mean(fitted_slopes))
    transparent = [name for name in errors if name != "opaque"]
    best = min(transparent, key=lambda name: float(errors[name].mean()))
    difference = errors["opaque"] - errors[best]  # > 0: the transparent model predicts the tile's fine-fringe power better
    better, worse = int(np.sum(difference > 0)), int(np.sum(difference < 0))
    z = float((better - worse) / np.sqrt(better + worse)) if better + worse else 0.0
    return {
        "method": "fine-fringe power",
        "particles": int(len(table)),
        "model": "transparent" if z >= level_z else "opaque" if z <= -level_z else "undecided",
        "z": z,
        "transparent_better": better,
        "transparent_worse": worse,
        "tile_differences": difference,
        "index_contrast": float(best),
        "heldout_error": {name: float(e.mean()) for name, e in errors.items()},
        "slope": slopes,
    }
