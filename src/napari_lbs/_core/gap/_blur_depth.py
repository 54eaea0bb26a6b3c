"""Where a frame's blur comes from, read from how it grows with the particles' depth.

A sensor's blur (pixel crosstalk, a defocused relay) softens every particle's fringes alike;
a source of angular size θ softens a particle's fringes by σ = θ·z, so deep particles lose
more than shallow ones (`Scene.coherent_blur`). Both models are nested in one with a free
blur per depth group of the scene's particles: ``σ_g² = σ_sensor² + (θ·z_g / pixel)²``.
The held-out comparison of the two single-parameter models (`select_effects`) cannot tell
them apart once both gain on every tile (its sign test saturates), and when the real kernel
has another shape than the catalog's Gaussian (a uniform disc source, a binomial crosstalk)
the pair of them fits better than either, so both are named. The depth profile asks the
physical question directly: each group's blur is fitted on each colour of the checkerboard,
and the two colours' mean ``σ_g²`` is regressed on ``z_g²``; the intercept is the sensor's
share, the slope the source's. The group, not the colour, is the replicate: what the
particles' fits leave about a group (a depth slightly off, a neighbour missed) is blurred
away alike on both colours, so a frame with no blur at all shows group blurs of 0.1–1.3 px
whose two colours agree to a few hundredths. Each share's t statistic, on the groups less
two degrees of freedom, is read as the normal deviate of the same one-sided probability; a
share whose deviate reaches ``level_z`` is named, the other is not. Neither reaching it
leaves the origin undecided.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import optimize, stats

from napari_lbs._core.gap._heldout import TileSplit, model_probabilities
from napari_lbs._core.gap._nested import EVERY_OTHER, MEAN_EFFECTS, Selection, both_colours, fit_frame, gain_and_z, last_two, shot_noise_test
from napari_lbs._core.gap._scene_image import Scene
from napari_lbs._core.physics import EFFECTS, gaussian_blur, sensor_image

__all__ = ["BLUR_EFFECTS", "blur_by_depth", "attribute_blur", "spectrum_width_test"]

BLUR_EFFECTS = ("coherence", "sensor_blur")
_MIN_GROUPS = 4  # the line's two coefficients leave two degrees of freedom to four groups' scatter
_STEPS = 20  # least-squares steps of the per-group fit (each also costs one evaluation per parameter)
_MAX_SIGMA_PX = 6.0


def _fit_groups(data: np.ndarray, scene: Scene, mask: np.ndarray, camera: dict, start: dict, check) -> np.ndarray:
    """Each depth group's blur σ (px) and the baseline's gain, contrast and gamma, fitted on ``mask``'s pixels."""
    sample = mask[EVERY_OTHER]
    target = data[EVERY_OTHER][sample]
    zeros = np.zeros(data.shape, np.float32)
    groups = len(scene.depths_um)
    image32 = scene.image.astype(np.float32)
    # each group's blur is redone for its own σ's moves only
    changes = [last_two(lambda sigma, group=group: gaussian_blur(group, sigma) - group) for group in scene.groups]

    def residual(x: np.ndarray) -> np.ndarray:
        if check is not None:
            check()
        image = image32.copy()
        for change, sigma in zip(changes, x[3:], strict=True):
            image += change(float(sigma))
        baseline = {"contrast": x[1], "sigma": 0.0, "gamma": x[2]}
        return x[0] * sensor_image(image, baseline, camera, noise=zeros, keep=EVERY_OTHER).astype(np.float64)[sample] - target

    x0 = np.array([start["gain"], start["contrast"], start["gamma"]] + [0.5] * groups)
    low = np.array([0.2, 0.0, 0.3] + [0.0] * groups)
    high = np.array([5.0, 3.0, 3.0] + [_MAX_SIGMA_PX] * groups)
    result = optimize.least_squares(residual, np.clip(x0, low, high), bounds=(low, high), x_scale="jac", max_nfev=_STEPS, diff_step=1e-3, ftol=1e-5, xtol=1e-5)
    return result.x[3:]


def blur_by_depth(data: np.ndarray, scene: Scene, split: TileSplit, params: tuple[dict, dict], effects: tuple[str, ...], *,
                  level_z: float = 3.0, check=None) -> dict:
    """Each depth group's blur, and the sensor's and the source's shares of it (module docstring).

    Parameters
    ----------
    data : (rows, cols) array
        The frame, unobstructed light 1.
    scene : Scene
        The frame's particles, with at least three depth groups.
    split : TileSplit
        The checkerboard: each group's blur is fitted on each colour's tiles.
    params, effects
        The selected model's parameters fitted on each colour and its effects: the camera's
        effects other than a blur are held at those values.
    level_z : float
        The normal deviate a share's t statistic must reach, read at the same one-sided
        probability, to be named.
    check : callable, optional
        Called before each evaluation of the model (`Steps.check`: raises `Stopped`).

    Returns
    -------
    dict
        ``depths_um`` (each group's mean depth), ``sigma_px`` (the two colours' fits per
        group), ``sensor_sigma_px`` and ``theta_mrad`` (the line's intercept and slope as a
        sensor's σ and a source's angular size), ``t_sensor`` and ``t_source`` (their t
        statistics on ``dof`` degrees of freedom), ``z_sensor`` and ``z_source`` (the normal
        deviates of the same one-sided probabilities) and ``origin`` (the blur effects named,
        sorted; empty when neither deviate reaches ``level_z``).
    """
    if scene.groups is None or len(scene.depths_um) < _MIN_GROUPS:
        raise ValueError(f"scene: expected at least {_MIN_GROUPS} depth groups, got {0 if scene.groups is None else len(scene.depths_um)}")
    camera_effects = [e for e in effects if e not in BLUR_EFFECTS]

    def on_colour(colour: int, heard) -> np.ndarray:
        fitted = params[colour]
        camera = {e: {**EFFECTS[e].neutral, **{p: fitted[f"{e}.{p}"] for p in MEAN_EFFECTS[e]}} for e in camera_effects}
        return _fit_groups(data, scene, split.mask(colour), camera, fitted, heard)

    sigmas = np.array(both_colours(on_colour, check))
    depths = np.asarray(scene.depths_um, np.float64)
    # the line through the groups' points: sigma² = a + b z², z in mm to keep the columns alike in scale
    z2 = (depths / 1000.0) ** 2
    y = np.mean(sigmas**2, axis=0)
    design = np.stack([np.ones_like(z2), z2], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, y, rcond=None)
    dof = y.size - 2
    scatter = float(np.sum((y - design @ coefficients) ** 2)) / dof
    errors = np.sqrt(np.maximum(np.diag(np.linalg.pinv(design.T @ design)) * scatter, 1e-30))
    t_sensor, t_source = (float(c / e) for c, e in zip(coefficients, errors, strict=True))
    z_sensor, z_source = (float(stats.norm.isf(stats.t.sf(t, dof))) for t in (t_sensor, t_source))
    origin = tuple(sorted(name for name, z in (("sensor_blur", z_sensor), ("coherence", z_source)) if z >= level_z))
    intercept, slope = (float(c) for c in coefficients)
    return {
        "depths_um": [float(d) for d in depths],
        "sigma_px": [[float(s) for s in row] for row in sigmas],
        "sensor_sigma_px": float(np.sqrt(max(intercept, 0.0))),
        # slope in px² per mm²: sigma = theta z / pixel, theta in mrad with z in mm is sqrt(slope) * pixel (µm)
        "theta_mrad": float(np.sqrt(max(slope, 0.0)) * scene.pixel_um),
        "t_sensor": t_sensor,
        "t_source": t_source,
        "z_sensor": z_sensor,
        "z_source": z_source,
        "dof": dof,
        "origin": list(origin),
    }


def attribute_blur(data: np.ndarray, scene: Scene, split: TileSplit, selection: Selection, *, level_z: float = 3.0, check=None) -> tuple[Selection, dict | None]:
    """The selection with its blur named by the depth profile (`blur_by_depth`), and the profile.

    Applies where the selection named a blur (``coherence`` or ``sensor_blur``) or was
    undecided between them, and the scene has at least three depth groups; otherwise the
    selection is returned as it is, with no profile. The selected blur effects are replaced by
    the profile's ``origin`` (the model refitted where it was not fitted yet); the pair's
    undecided records are dropped once the profile names an origin, and kept when it names
    none.
    """
    blur_chosen = [e for e in selection.chosen if e in BLUR_EFFECTS]
    pair_undecided = [u for u in selection.undecided if {u["selected"], u["rival"]} <= set(BLUR_EFFECTS)]
    if not (blur_chosen or pair_undecided) or scene.groups is None or len(scene.depths_um) < _MIN_GROUPS:
        return selection, None
    final = selection.fits["+".join(selection.chosen) or "baseline"]
    profile = blur_by_depth(data, scene, split, final.params, selection.chosen, level_z=level_z, check=check)
    if not profile["origin"]:
        return selection, profile
    chosen = tuple(sorted((*(e for e in selection.chosen if e not in BLUR_EFFECTS), *profile["origin"])))
    fits = dict(selection.fits)
    key = "+".join(chosen)
    if key not in fits:
        fits[key] = fit_frame(data, scene, split, chosen, starts=final.params, check=check)
    undecided = tuple(u for u in selection.undecided if u not in pair_undecided)
    probabilities = model_probabilities({name: fit.loglik for name, fit in fits.items()})
    return replace(selection, chosen=chosen, fits=fits, undecided=undecided, probabilities=probabilities), profile


def spectrum_width_test(data: np.ndarray, scene: Scene, split: TileSplit, selection: Selection, *, level_z: float = 3.0,
                        check=None) -> tuple[Selection, dict | None]:
    """The named blur against a spectrum's width in its place (`Scene.spectral_blur`): the selection with the better, and the test.

    A spectrum's width (an LED, a laser diode) washes a fringe out with its order (f⁴) and
    with depth; a sensor's blur takes f² from every depth and a source's size a Gaussian
    growing with depth. Where the selection names a blur (``sensor_blur``, ``coherence`` or
    both), the model with coherence as a spectrum's width in their place is fitted on each
    colour and judged on the other against the selection's final model; it replaces them
    where it gains on the held-out tiles at ``level_z`` with a positive sum. The depth
    profile's reading (`attribute_blur`) assumes Gaussian blurs, so the swap is judged after
    it, on the model it left.

    Returns
    -------
    (Selection, dict or None)
        The selection (``coherence``, fitted as ``coherence.bandwidth_nm``, in the blurs'
        place where the spectrum's width wins, and photon noise's test on that model) and the test: ``replaces`` (the blurs),
        ``gain_nats``, ``z``, ``bandwidth_nm`` and its error, ``named``, ``tile_gains`` (for the
        verdict's bootstrap); None where no blur is named or the scene has too few depth groups.
    """
    blurs = [e for e in selection.chosen if e in BLUR_EFFECTS]
    if not blurs or scene.groups is None or len(scene.depths_um) < _MIN_GROUPS:
        return selection, None
    final = selection.fits["+".join(selection.chosen)]
    model = tuple(sorted((*(e for e in selection.chosen if e not in BLUR_EFFECTS), "coherence")))
    fit = fit_frame(data, scene, split, model, starts=final.params, check=check, parameters={"coherence": ("bandwidth_nm",)})
    gain, z = gain_and_z(fit.loglik, final.loglik)
    width, width_err = fit.estimate("coherence.bandwidth_nm")
    record = {"replaces": blurs, "gain_nats": gain, "z": z, "bandwidth_nm": width, "bandwidth_nm_err": width_err if np.isfinite(width_err) else None,
              "named": bool(z >= level_z and gain > 0), "tile_gains": fit.loglik - final.loglik}
    if not record["named"]:
        return selection, record
    fits = dict(selection.fits)
    fits["+".join(model)] = fit  # the coherence of the verdict is now the spectrum's width
    undecided = tuple(u for u in selection.undecided if not {u["selected"], u["rival"]} <= set(BLUR_EFFECTS))
    probabilities = model_probabilities({name: f.loglik for name, f in fits.items()})
    # photon noise is judged on the final model again: a spectrum's width blurs the light, not
    # the camera's noise, so noise blurred by the replaced sensor blur is no longer a hypothesis
    return replace(selection, chosen=model, fits=fits, undecided=undecided, probabilities=probabilities, shot_noise=shot_noise_test(fit, split)), record
