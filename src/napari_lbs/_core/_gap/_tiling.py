"""Where the tiles of one hologram lie: their size, positions, fitting/held-out split and surroundings."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from napari_lbs._core._gap._summaries import MIN_TILE_PX

__all__ = ["TileLayout", "field_surroundings", "adapted_tile_px"]


@dataclass(frozen=True)
class TileLayout:
    """Where the real tiles were cut from one hologram.

    Attributes
    ----------
    field_shape : (int, int)
        The hologram's (rows, cols) in pixels.
    origins : tuple of (int, int)
        Each tile's top-left (row, col) in pixels, in the order of the tiles.
    field_mean : float
        The hologram's mean intensity (the unit of the field-wide envelope summaries).
    """

    field_shape: tuple[int, int]
    origins: tuple[tuple[int, int], ...]
    field_mean: float

    def fitting(self, tile_shape: tuple[int, int]) -> np.ndarray:
        """Which tiles are fitted (True) and which held out: a checkerboard, so both halves span the field."""
        return np.array([(r // tile_shape[0] + c // tile_shape[1]) % 2 == 0 for r, c in self.origins])


def field_surroundings(field: np.ndarray, origin: tuple[int, int], tile_shape: tuple[int, int]) -> np.ndarray:
    """The field around a tile: twice the tile's size, centred on it, NaN outside the field (float64)."""
    rows, cols = tile_shape
    top, left = origin[0] - rows // 2, origin[1] - cols // 2
    region = np.full((2 * rows, 2 * cols), np.nan)
    r0, c0 = max(top, 0), max(left, 0)
    r1, c1 = min(top + 2 * rows, field.shape[0]), min(left + 2 * cols, field.shape[1])
    region[r0 - top : r1 - top, c0 - left : c1 - left] = field[r0:r1, c0:c1]
    return region


def adapted_tile_px(shape: tuple[int, int], largest: int, *, tiles: int = 16) -> int:
    """The largest tile edge (px; ``largest`` halved until it fits, not below `MIN_TILE_PX`) that cuts at least ``tiles`` tiles of ``shape``."""
    size = int(largest)
    while size // 2 >= MIN_TILE_PX and (shape[0] // size) * (shape[1] // size) < tiles:
        size //= 2
    return size
