"""The scene's particles rendered under each particle model the optics tests compare: opaque spheres and transparent ones.

Both views of the particles' optics (`_optics_power`, the fine rings' power spectrum;
`_through_focus`, the light on each sphere's axis) compare the frame with the same renders:
the fitted particles' places and sizes, each model's optics, every ring to 1 cycle per pixel
(the aliased rings a pixel records, where a transparent sphere's refracted light lies), through
the camera's blur the frame's effects hold.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, Steps
from napari_lbs._core.physics import gaussian_blur
from napari_lbs._core.refine import RefineSettings, particle_holograms

__all__ = ["OPAQUE", "OPAQUE_KAPPA", "optics_call", "particle_models"]

OPAQUE = "opaque"  # the simulator's particle model; every other model is named by its index contrast
OPAQUE_KAPPA = 1.0  # an absorption length λ/(4πκ) of 0.05 µm at 660 nm: opaque for a sphere of microns


def optics_call(z: float, *, level_z: float) -> str:
    """The particles' optics a sign test's z names: ``"transparent"`` from ``level_z``, ``"opaque"`` to ``-level_z``, else ``"undecided"``."""
    return "transparent" if z >= level_z else "opaque" if z <= -level_z else "undecided"


def particle_models(shape: tuple[int, int], table, config: ExperimentConfig, *, index_grid, blur_px: float = 0.0,
                    settings: RefineSettings | None = None, steps: Steps | None = None) -> dict[str, np.ndarray]:
    """``table``'s spheres rendered as opaque spheres and as transparent ones at each of ``index_grid``.

    Parameters
    ----------
    shape : (int, int)
        The frame (pixels).
    table : pandas.DataFrame
        The frame's fitted particles (``x_um, y_um, z_um, diameter_um``): their places and
        sizes; each model sets the optics.
    config : ExperimentConfig
    index_grid : sequence of float
        Index contrasts ``n_p - n_m`` of the transparent models.
    blur_px : float
        The camera's blur (σ, pixels) the frame's effects hold, applied to every model.
    settings : RefineSettings, optional
        The medium's index and the pixel integration of the renders.
    steps : Steps, optional
        Advanced by each particle rendered (under every model at once) and checked for a stop
        before each.

    Returns
    -------
    dict
        ``"opaque"`` and ``f"{contrast:g}"`` for each transparent model: its frame (unobstructed
        light 1), in that order.
    """
    models = {OPAQUE: {"index_contrast": 0.0, "absorption": OPAQUE_KAPPA}}
    models.update({f"{v:g}": {"index_contrast": float(v), "absorption": 0.0} for v in index_grid})
    check = (lambda: bool(steps.check())) if steps is not None else None
    heard = (lambda done, total: steps.advance()) if steps is not None else None
    renders = particle_holograms(tuple(shape), table, config, materials=list(models.values()), settings=settings or RefineSettings(),
                                 reach_cycles_per_px=1.0, progress=heard, should_stop=check)
    return {name: gaussian_blur(image, blur_px) if blur_px > 0 else image for name, image in zip(models, renders, strict=True)}
