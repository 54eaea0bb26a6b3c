"""What a frame's model leaves: the unexplained share of its structure by tile, frequency band and particle depth, and fixed line patterns.

The scene diagnosis's step 4 (`_scene_diagnosis`): a pair fitted as one particle spoils a
few tiles, an effect the model lacks spoils them all, so the gap is the median over the
held-out tiles of the structured power the residual keeps over the frame's own.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.gap._heldout import TileSplit, tile_spectra
from napari_lbs._core.physics import gaussian_blur

__all__ = ["depth_groups", "line_pattern", "share_by_depth", "unexplained_share"]

_DEPTH_GROUPS = 6  # depth groups of the scene's particles for a depth-dependent effect
_FLOOR_CYCLES = 0.35  # cycles per pixel above which the residual's power is its white floor
_BANDS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.35, 0.5)  # cycles per pixel, the report's frequency bands


def unexplained_share(residuals: tuple[np.ndarray, np.ndarray], split: TileSplit, frame_spectra: np.ndarray) -> tuple[float, list, np.ndarray, float]:
    """The unexplained share of the frame's structure: its median over the tiles, per band, per tile; and the white floor's variance.

    ``frame_spectra`` are the frame's own tile spectra (`tile_spectra` of the frame less its
    mean). The floor is the residual's mean power per frequency above ``_FLOOR_CYCLES`` (a
    white residual's variance); a tile's structured power is what it holds beyond the floor
    times its frequencies, for the residual and for the frame alike. Sums, not bin by bin: a
    periodogram's bins scatter exponentially about their mean, and clipping each at a floor
    would call half of pure white noise structure. The bands split the residual's own
    structured power.
    """
    colours = split.colours()
    spectra = np.empty((len(colours), split.size, split.size))
    for fitted_on, residual in enumerate(residuals):
        judged = colours != fitted_on
        spectra[judged] = tile_spectra(residual, split)[judged]
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(split.size), np.fft.fftfreq(split.size), indexing="ij"))
    high = (f >= _FLOOR_CYCLES) & (f <= 0.5)
    floors = spectra[:, high].mean(axis=1)
    structured = spectra.sum(axis=(1, 2)) - floors * f.size
    frame = np.maximum(frame_spectra.sum(axis=(1, 2)) - floors * f.size, 1e-30)
    per_tile = np.clip(structured / frame, 0.0, None)
    grand = max(float(spectra.sum()), 1e-30)
    bands = []
    for low, high_f in zip(_BANDS[:-1], _BANDS[1:], strict=True):
        inside = (f >= low) & (f < high_f)
        power = float(spectra[:, inside].sum())
        bands.append({"cycles_per_px": [low, high_f], "share_of_power": power / grand,
                      "structured": max(power - float(floors.sum()) * int(inside.sum()), 0.0) / grand})
    return float(np.median(per_tile)), bands, per_tile.reshape(split.grid, split.grid), float(np.mean(floors))


def depth_groups(table) -> list[np.ndarray]:
    """The rows of each of the scene's depth groups: about equal counts, shallow to deep (none for fewer than two particles)."""
    return np.array_split(np.argsort(table["z_um"].to_numpy()), min(_DEPTH_GROUPS, len(table))) if len(table) >= 2 else []


def share_by_depth(before: tuple[np.ndarray, np.ndarray], after: tuple[np.ndarray, np.ndarray], data: np.ndarray, table, split: TileSplit,
              floor_variance: float, *, pixel_um: float, reach_px: int) -> list:
    """The unexplained share of the structure about the particles of each depth group, before and after the selected effects.

    Each held-out pixel within ``reach_px`` of a particle's centre belongs to its nearest
    particle, so to that particle's depth group (the scene's: equal counts, by depth). A
    group's share is the held-out residual's power there beyond the white floor over the
    frame's own beyond it, as the tiles' share (`_structure`) but summed over the group's
    pixels: a source's size leaves the deep groups' rings, a sensor's blur every group's.
    """
    from scipy.spatial import cKDTree

    if len(table) < 2:
        return []
    colour_of = np.append(split.colours(), -1)[split.labels()]  # -1: outside the tiles
    centres = np.stack([table["y_um"].to_numpy(), table["x_um"].to_numpy()], axis=1) / pixel_um
    rows, cols = np.nonzero(colour_of >= 0)
    distance, nearest = cKDTree(centres).query(np.stack([rows, cols], axis=1), distance_upper_bound=reach_px)
    near = np.isfinite(distance)
    rows, cols, nearest = rows[near], cols[near], nearest[near]
    group_of = np.empty(len(table), int)
    bins = depth_groups(table)
    for index, members in enumerate(bins):
        group_of[members] = index

    def held_out(residuals):  # each pixel from the fit on the other colour's tiles
        return np.where(colour_of[rows, cols] == 1, residuals[0][rows, cols], residuals[1][rows, cols])

    frame = (data[rows, cols] - 1.0) ** 2
    left_before, left_after = held_out(before) ** 2, held_out(after) ** 2
    out = []
    for index, members in enumerate(bins):
        inside = group_of[nearest] == index
        count = int(inside.sum())
        structure = max(float(frame[inside].sum()) - count * floor_variance, 1e-30)
        shares = [max(float(left[inside].sum()) - count * floor_variance, 0.0) / structure if count else None for left in (left_before, left_after)]
        out.append({"z_um": float(table["z_um"].to_numpy()[members].mean()), "particles": int(len(members)), "pixels": count,
                    "baseline": shares[0], "after": shares[1]})
    return out


def line_pattern(residuals: tuple[np.ndarray, np.ndarray]) -> dict:
    """Fixed column and row patterns: the variance of the high-passed residual's column and row means over what white noise gives.

    A camera's column amplifiers and row read-out add an offset per column or row, white
    along the other axis; particles, illumination and fringes at an angle average out in a
    column's mean, and the high pass (less a Gaussian blur of 1.5 px) keeps a smooth envelope
    out. White noise gives a ratio near 1.
    """
    ratios = {"columns": [], "rows": []}
    for residual in residuals:
        high = residual - gaussian_blur(residual, 1.5)
        white = float(high.var())
        for axis, name in ((0, "columns"), (1, "rows")):
            ratios[name].append(float(high.mean(axis=axis).var() / max(white / residual.shape[axis], 1e-30)))
    return {name: float(np.mean(values)) for name, values in ratios.items()}
