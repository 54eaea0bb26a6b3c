"""The experiment's particles as the scene's fits measured them: how many, how large, how deep, and what is smaller.

The numbers a physicist reads off a characterised sample (Yevick et al. 2014; Altman & Grier
2020 gate their size-and-index scatter the same way): the count and density of the fitted
particles; the sizes, depths and index contrasts of those within the config's size range;
and the fits below that range, the small scatterers (debris, dust, bubbles) the frame holds
beside its sample, as counts per 256-pixel tile, the unit `generate --impurities` takes.

References
----------
Yevick, A., Hannel, M. & Grier, D. G. (2014). Machine-learning approach to holographic
particle characterization. Optics Express 22, 26884.
Altman, L. E. & Grier, D. G. (2020). CATCH: characterizing and tracking colloids
holographically using deep neural networks. J. Phys. Chem. B 124, 1602.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig

__all__ = ["scene_population"]

_TILE_PX = 256  # the training data's tile edge, in which `Distractors.impurities_per_tile` counts


def _quantiles(values: np.ndarray, levels: tuple[float, ...]) -> list[float] | None:
    return np.percentile(values, levels).round(4).tolist() if values.size else None


def scene_population(table, config: ExperimentConfig, shape: tuple[int, int]) -> dict:
    """The fitted particles' count, density, sizes, depths and index contrasts, and the small scatterers beside them.

    Parameters
    ----------
    table : pandas.DataFrame
        The scene's fitted particles (`refine_particles`: ``x_um, y_um, z_um, diameter_um,
        index_contrast``).
    config : ExperimentConfig
        Its particles' size range sets the sample apart from what is smaller or larger, its
        pitch the frame's area.
    shape : (int, int)
        The frame (pixels).

    Returns
    -------
    dict
        ``particles``; ``per_mm2`` (over the frame's area); ``in_size_range``,
        ``below_size_range``, ``above_size_range`` (counts against the config's diameters);
        for those in range ``diameter_um`` and ``index_contrast`` (5th, 25th, 50th, 75th and
        95th percentiles) and for all ``z_um`` (the same); ``small_scatterers``: ``count``,
        ``per_256px_tile`` and ``diameter_um`` (least and largest) of those below the range.
    """
    pixel_mm = config.optics.pixel_um * 1e-3
    area_mm2 = shape[0] * shape[1] * pixel_mm**2
    diameters = table["diameter_um"].to_numpy(np.float64) if len(table) else np.empty(0)
    low, high = config.particles.diameter_min_um, config.particles.diameter_max_um
    inside = (diameters >= low) & (diameters <= high)
    below = diameters < low
    levels = (5, 25, 50, 75, 95)
    index = table["index_contrast"].to_numpy(np.float64)[inside] if "index_contrast" in table and len(table) else np.empty(0)
    depths = table["z_um"].to_numpy(np.float64) if len(table) else np.empty(0)
    tiles = shape[0] * shape[1] / _TILE_PX**2
    return {
        "particles": int(diameters.size),
        "per_mm2": float(diameters.size / area_mm2),
        "in_size_range": int(inside.sum()),
        "below_size_range": int(below.sum()),
        "above_size_range": int((diameters > high).sum()),
        "percentiles": list(levels),
        "diameter_um": _quantiles(diameters[inside], levels),
        "index_contrast": _quantiles(index[np.isfinite(index)], levels),
        "z_um": _quantiles(depths, levels),
        "small_scatterers": {"count": int(below.sum()), "per_256px_tile": float(below.sum() / tiles),
                             "diameter_um": [float(diameters[below].min()), float(diameters[below].max())] if below.any() else None},
    }
