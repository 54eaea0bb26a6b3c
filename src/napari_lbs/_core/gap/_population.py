"""The experiment's particles as the scene's fits measured them: how many, how large, how deep, and what is smaller.

The numbers a physicist reads off a characterised sample (the size-and-index scatter of
holographic characterisation: Yevick et al. 2014, Altman & Grier 2020, cited in
`refine/_material.py`): the count and density of the fitted particles; the sizes, depths and
index contrasts of those within the config's size range; and the small scatterers (debris,
dust, bubbles) the frame holds beside its sample, as counts per 256-pixel tile, the unit
`generate --impurities` takes.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig

__all__ = ["scene_population"]

_TILE_PX = 256  # the training data's tile edge, in which `Distractors.impurities_per_tile` counts
# a small scatterer is counted where its fit measured it: its size to within this fraction
# and its depth to within this fraction of itself. A fit on what a misfit neighbour leaves
# has neither (on development frames such fits had size errors of 0.5-70 times the size and
# depth errors of 9-230 %; the debris of a pseudo-real frame 0.01-0.37 and 0.1-1.5 %).
_SIZE_PRECISION = 0.5
_DEPTH_PRECISION = 0.05


def _measured(rows) -> np.ndarray:
    """(n,) bool: the rows whose fit measured size and depth (`_SIZE_PRECISION`, `_DEPTH_PRECISION`); all where no errors are given."""
    if rows is None or not len(rows):
        return np.zeros(0, bool)
    if "diameter_err_um" not in rows or "z_err_um" not in rows:
        return np.ones(len(rows), bool)
    size = rows["diameter_err_um"].to_numpy(np.float64) <= _SIZE_PRECISION * rows["diameter_um"].to_numpy(np.float64)
    depth = rows["z_err_um"].to_numpy(np.float64) <= _DEPTH_PRECISION * np.abs(rows["z_um"].to_numpy(np.float64))
    return size & depth


def _clearly_below(rows, least_um: float) -> np.ndarray:
    """(n,) bool: the rows sized below ``least_um`` by more than twice their size's uncertainty (a sample particle fitted a little small is not debris)."""
    if rows is None or not len(rows):
        return np.zeros(0, bool)
    error = rows["diameter_err_um"].to_numpy(np.float64) if "diameter_err_um" in rows else np.zeros(len(rows))
    return rows["diameter_um"].to_numpy(np.float64) + 2.0 * np.nan_to_num(error, nan=np.inf) < least_um


def _quantiles(values: np.ndarray, levels: tuple[float, ...]) -> list[float] | None:
    return np.percentile(values, levels).round(4).tolist() if values.size else None


def scene_population(table, config: ExperimentConfig, shape: tuple[int, int], *, small=None) -> dict:
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
    small : pandas.DataFrame, optional
        Small scatterers found apart from the scene (a search at smaller sizes): counted with
        the scene's own fits below the size range.

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
    extra = small["diameter_um"].to_numpy(np.float64)[_measured(small) & _clearly_below(small, low)] if small is not None and len(small) else np.empty(0)
    small_sizes = np.concatenate([diameters[_clearly_below(table, low) & _measured(table)] if len(table) else np.empty(0), extra])
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
        "small_scatterers": {"count": int(small_sizes.size), "per_256px_tile": float(small_sizes.size / tiles),
                             "diameter_um": [float(small_sizes.min()), float(small_sizes.max())] if small_sizes.size else None},
    }
