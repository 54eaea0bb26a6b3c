"""The particles' optics told through focus: is each sphere's axis bright or dark on the way to it?

A transparent sphere is a ball lens. The light it refracts crosses its axis in a focus behind
it (towards the sensor: for polystyrene in water about 1.5 diameters from its centre), so the
hologram propagated back through the sphere's depth keeps the centre of its image bright
over a range of depths set by its index contrast; an opaque sphere only diffracts, and
leaves its centre dark. This is the geometry of the light, not its power spectrum: photon
noise, whose white floor drowns the fine rings' spectrum, is spread over the whole crop by
back-propagation, where the rings' light adds up in phase on the axis.

Per sphere (its place, depth and size fitted by the scene), the frame is cropped about it
(mirrored at the frame's edges) and back-propagated to its depth plus `RELATIVE_DEPTHS` of
its diameter (−8 to +4: 200 µm towards the sensor to 100 µm past a sphere of 25 µm); the
mean amplitude of the centre's 3 × 3 pixels over the median of the 71² about it is the
sphere's **profile**. The same is done on the scene rendered under each particle model
(`particle_models`), and a model's distance from a sphere is the summed squared difference
of their profiles. Each sphere within the config's sizes votes (a fit outside them is more
often a pair fitted as one, or debris): for transparent where the transparent model nearest
the other colour's spheres of the checkerboard is nearer its own profile than the opaque
model, by its distances' difference over their sum (at most 1, so that a sphere the models
all misfit is one vote). The votes' signs give a sign test over the spheres, z =
(for − against) / √(for + against), and each vote keeps its tile for the verdict's
bootstrap (`_confidence`).

On independent Lorenz–Mie frames (pylorenzmie) of 20–30 µm spheres, read at their true
places with crops of 384 pixels, the profiles named polystyrene's contrast (0.26) and n 1.45's
(0.12), unblurred and through a 1.03 px blur; with the rendered depths off by σ 5 µm still
0.26.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, Steps
from napari_lbs._core.gap._confidence import sign_z
from napari_lbs._core.gap._heldout import TileSplit
from napari_lbs._core.gap._particle_models import OPAQUE, optics_call
from napari_lbs._core.physics import backpropagate

__all__ = ["RELATIVE_DEPTHS", "axis_profile", "through_focus_test"]

RELATIVE_DEPTHS = np.linspace(-8.0, 4.0, 16)  # in the sphere's diameters about its depth, negative towards the sensor (the ball lens's focus)
_HALF_PX = 128  # half the crop back-propagated about each sphere
_CENTRE_PX = 1  # the centre's half width: 3 × 3 pixels
_AROUND_PX = 35  # the half width of the surroundings whose median is the profile's unit


def axis_profile(padded: np.ndarray, row: int, col: int, depths_um: np.ndarray, config: ExperimentConfig, *, half_px: int = _HALF_PX) -> np.ndarray:
    """(depths,): the centre's amplitude over its surroundings' median, through focus.

    ``padded``: the frame padded by ``half_px`` on every side; the crop of ``2 * half_px``
    about the frame's pixel ``(row, col)`` is back-propagated to ``depths_um`` (the config's
    convention), and at each depth the mean amplitude of its centre's 3 × 3 pixels is divided
    by the median of the 71² about it.
    """
    crop = padded[row : row + 2 * half_px, col : col + 2 * half_px]
    stack = backpropagate(crop, depths_um, wavelength_um=config.optics.wavelength_um, pixel_um=config.optics.pixel_um,
                          medium_index=config.optics.medium_index)
    middle = slice(half_px - _CENTRE_PX, half_px + _CENTRE_PX + 1)
    around = slice(half_px - _AROUND_PX, half_px + _AROUND_PX + 1)
    return stack[:, middle, middle].mean((1, 2)) / np.maximum(np.median(stack[:, around, around].reshape(len(depths_um), -1), axis=1), 1e-12)


def through_focus_test(data: np.ndarray, models: dict[str, np.ndarray], table, config: ExperimentConfig, split: TileSplit, *,
                       level_z: float = 3.0, steps: Steps | None = None) -> dict:
    """Opaque against transparent spheres by the light on each sphere's axis through focus (module docstring).

    Parameters
    ----------
    data : (rows, cols) array
        The frame, unobstructed light 1.
    models : dict
        ``table`` rendered under each particle model (`particle_models`: ``"opaque"`` and one
        per transparent index contrast), through the camera's blur.
    table : pandas.DataFrame
        The rendered particles (``x_um, y_um, z_um, diameter_um``).
    config : ExperimentConfig
        Its optics propagate the crops; its diameters say which spheres vote.
    split : TileSplit
        The held-out checkerboard: a sphere's colour chooses the transparent model it is
        judged by (the one nearest the other colour's spheres, or all the spheres where the
        other colour holds none), its tile is its cluster in the verdict's bootstrap.
    level_z : float
        The sign test's z from which transparent spheres are named.
    steps : Steps, optional
        Advanced by each sphere read and checked for a stop before each.

    Returns
    -------
    dict
        ``model`` (``"transparent"`` from ``z >= level_z``, ``"opaque"`` to
        ``z <= -level_z``, else ``"undecided"``), ``z``, ``transparent_better`` and
        ``transparent_worse`` (spheres), ``index_contrast`` (the transparent model nearest
        all the voting spheres), ``profile_distance`` per model (the mean over the voting
        spheres of the summed squared difference of their profiles), ``spheres`` (how many
        voted), ``relative_depths`` (in diameters); ``sphere_differences`` (each vote) and
        ``sphere_tiles`` (each vote's tile), for the verdict's bootstrap.
    """
    pixel = config.optics.pixel_um
    rows = np.clip(np.round(table["y_um"].to_numpy(np.float64) / pixel).astype(int), 0, data.shape[0] - 1)
    cols = np.clip(np.round(table["x_um"].to_numpy(np.float64) / pixel).astype(int), 0, data.shape[1] - 1)
    diameters = table["diameter_um"].to_numpy(np.float64)
    tile = split.labels()[rows, cols]  # -1: outside every tile (a frame not a whole number of tiles)
    voting = np.flatnonzero((tile >= 0) & (diameters >= config.particles.diameter_min_um) & (diameters <= config.particles.diameter_max_um))
    padded = {name: np.pad(np.asarray(image, np.float32), _HALF_PX, mode="reflect") for name, image in {"data": data, **models}.items()}
    profiles = {name: np.empty((voting.size, RELATIVE_DEPTHS.size)) for name in padded}
    for k, sphere in enumerate(voting):  # sphere by sphere, so that a stop is heard between them
        if steps is not None:
            steps.check()
        # no closer to the sensor than one diameter (a microscope's spheres lie a few diameters from focus)
        depths = np.maximum(table["z_um"].iloc[sphere] + RELATIVE_DEPTHS * diameters[sphere], diameters[sphere])
        for name, image in padded.items():
            profiles[name][k] = axis_profile(image, rows[sphere], cols[sphere], depths, config)
        if steps is not None:
            steps.advance()
    measured = profiles.pop("data")
    distance = {name: ((measured - profile) ** 2).sum(1) for name, profile in profiles.items()}
    transparent = [name for name in models if name != OPAQUE]
    colour = split.colours()[tile[voting]]
    votes = np.zeros(voting.size)
    for own in (0, 1):
        others = colour == 1 - own
        others = others if others.any() else np.ones_like(others)  # no sphere on the other colour: chosen on them all
        chosen = min(transparent, key=lambda name: float(distance[name][others].sum()))
        mine = colour == own
        # bounded to ±1: a sphere every model misfits (a pair fitted as one) is one vote, not its tile's
        votes[mine] = (distance[OPAQUE][mine] - distance[chosen][mine]) / np.maximum(distance[OPAQUE][mine] + distance[chosen][mine], 1e-12)
    better, worse = int(np.sum(votes > 0)), int(np.sum(votes < 0))
    z = sign_z(votes)
    return {
        "model": optics_call(z, level_z=level_z),
        "z": z,
        "transparent_better": better,
        "transparent_worse": worse,
        "spheres": int(voting.size),
        "index_contrast": float(min(transparent, key=lambda name: float(distance[name].sum()))) if voting.size else None,
        "profile_distance": {name: float(d.mean()) if d.size else None for name, d in distance.items()},
        "relative_depths": RELATIVE_DEPTHS.tolist(),
        "sphere_differences": votes,
        "sphere_tiles": tile[voting],
    }
