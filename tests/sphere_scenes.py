"""Lorenz–Mie scenes of polystyrene spheres in water and starting tables, for the refinement tests."""

from __future__ import annotations

import numpy as np
import torch

from napari_lbs._core.physics._lorenz_mie import sphere_holograms

WAVELENGTH_UM = 0.66
WATER = 1.33
PIXEL_UM = 2.2
# small patches keep each test within seconds; the benchmark uses the defaults
FAST = {"patch_px": 48, "depth_window_um": 120.0, "iterations": 8, "depth_candidates": 2}


def default_config():
    from napari_lbs._core import ExperimentConfig

    return ExperimentConfig.from_dict({})


def sphere_scene(particles, shape=(72, 72), *, noise=0.01, seed=0, contrast=0.26):
    """A Lorenz–Mie hologram (water, pixel-integrated) of ``(x_um, y_um, z_um, d_um[, index contrast])`` particles, z air-equivalent as the config's."""
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]] * PIXEL_UM
    hologram = np.ones(shape)
    for x, y, z, d, *own in particles:
        h = sphere_holograms(torch.tensor(cols.ravel() - x)[None], torch.tensor(rows.ravel() - y)[None], torch.tensor([z * WATER]), torch.tensor([d]),
                             torch.tensor([own[0] if own else contrast]), torch.tensor([0.0]), wavelength_um=WAVELENGTH_UM, medium_index=WATER, pixel_um=PIXEL_UM)
        hologram += h[0].numpy().reshape(shape) - 1.0
    return hologram + np.random.default_rng(seed).normal(0.0, noise, shape)


def guess_table(rows):
    import pandas as pd

    return pd.DataFrame(rows, columns=["x_um", "y_um", "z_um", "diameter_um"])
