"""Training targets of the ``focus`` formulation: particle-centre heatmaps, depth offsets, diameters.

A back-propagated 25 µm particle looks nearly the same over a depth of focus of about
d²/λ ≈ 1 mm, so one plane cannot say where the focus is. The ``focus`` formulation gives the
network the planes around a depth as channels (`FocusSpec.context`, in planes of the stack
grid) and asks three things of the centre plane, as in keypoint detectors (CenterNet, Zhou et
al. 2019; Spotiflow, Dominguez Mantes et al. 2024; DECODE, Speiser et al. 2021):

*heat*
    1 at the pixel nearest a particle's centre on the plane nearest its depth, a Gaussian of
    ``sigma_px`` laterally and ``sigma_planes`` in depth around it (the planes next to the
    focus are *near* negatives, penalised less by the focal loss than far ones);
*offset*
    at those peak pixels, the depth of the particle relative to the plane, in planes
    (−0.5 … 0.5);
*diameter*
    at the peak pixels, the diameter divided by ``diameter_scale_um``.

Detection (the heat) is thus separate from measurement (offset, diameter), which are only
regressed where a particle is. Positions follow docs/formats.md (pixel centres at integer
indices, ``x_um = col * pixel_um``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from napari_lbs._core.foundation import InputError

__all__ = ["FocusSpec", "FocusTargets", "FocusMarks", "focus_marks", "focus_targets", "context_indices"]

_TRUNCATE = 3.0  # Gaussians are drawn out to 3 sigma


@dataclass(frozen=True)
class FocusSpec:
    """What the ``focus`` network sees and is asked.

    Attributes
    ----------
    context : tuple of int
        Plane offsets (in stack planes) fed as channels, including 0; the default reaches
        ±8 planes (±400 µm at 50 µm steps), about half the depth of focus of a 25 µm sphere.
    sigma_px : float
        Lateral width of a heat peak (pixels).
    sigma_planes : float
        Depth width of a heat peak (planes).
    """

    context: tuple[int, ...] = (-8, -4, -2, -1, 0, 1, 2, 4, 8)
    sigma_px: float = 1.0
    sigma_planes: float = 1.0

    def __post_init__(self) -> None:
        if 0 not in self.context or len(set(self.context)) != len(self.context):
            raise InputError(f"context: expected distinct plane offsets including 0, got {self.context}")
        if self.sigma_px <= 0 or self.sigma_planes <= 0:
            raise InputError(f"sigma_px / sigma_planes: expected positive widths, got {self.sigma_px} / {self.sigma_planes}")

    @property
    def reach(self) -> int:
        """Planes needed on each side of a centre plane."""
        return max(abs(int(o)) for o in self.context)


@dataclass
class FocusTargets:
    """Targets of one plane (or crop): ``heat``, ``offset``, ``diameter`` float32 and ``positive`` bool, all ``(rows, cols)``."""

    heat: np.ndarray
    offset: np.ndarray
    diameter: np.ndarray
    positive: np.ndarray


@dataclass
class FocusMarks:
    """The targets of one window as sparse entries (flat pixel indices into ``rows * cols``).

    ``heat_index``/``heat_value``: each particle's Gaussian, the largest value at a pixel
    wins; ``peak_index`` with ``offset`` and ``diameter``: the peak pixels, where the heat is 1
    (a later particle's peak overwrites an earlier one's at the same pixel).
    """

    heat_index: np.ndarray
    heat_value: np.ndarray
    peak_index: np.ndarray
    offset: np.ndarray
    diameter: np.ndarray


def focus_marks(
    particles: dict[str, np.ndarray],
    *,
    plane_um: float,
    step_um: float,
    pixel_um: float,
    shape: tuple[int, int],
    origin_px: tuple[int, int] = (0, 0),
    diameter_scale_um: float,
    spec: FocusSpec = FocusSpec(),
) -> FocusMarks:
    """The sparse targets of the plane at ``plane_um`` for a window of ``shape`` starting at pixel ``origin_px``.

    Parameters
    ----------
    particles : dict
        Particle table (``x_um``, ``y_um``, ``z_um``, ``diameter_um``) of the whole group.
    plane_um, step_um : float
        Depth of the plane and spacing of the stack's planes (µm).
    pixel_um : float
        Pixel pitch (µm).
    shape, origin_px : (int, int)
        The window (rows, cols) and its top-left pixel (row, col) in the group.
    diameter_scale_um : float
        Diameters are regressed divided by this (the largest trained diameter).
    spec : FocusSpec
    """
    rows, cols = shape
    dz = (np.asarray(particles["z_um"], np.float64) - plane_um) / step_um
    near = np.abs(dz) <= _TRUNCATE * spec.sigma_planes
    depth = dz[near]
    row = np.rint(np.asarray(particles["y_um"], np.float64)[near] / pixel_um).astype(np.int64) - origin_px[0]
    col = np.rint(np.asarray(particles["x_um"], np.float64)[near] / pixel_um).astype(np.int64) - origin_px[1]
    radius = int(np.ceil(_TRUNCATE * spec.sigma_px))
    lateral = np.arange(-radius, radius + 1)
    window = np.exp(-(lateral[:, None] ** 2 + lateral[None, :] ** 2) / (2 * spec.sigma_px**2)).astype(np.float32)
    weight = np.exp(-(depth**2) / (2 * spec.sigma_planes**2)).astype(np.float32)
    box_rows = row[:, None, None] + lateral[None, :, None]
    box_cols = col[:, None, None] + lateral[None, None, :]
    inside = (box_rows >= 0) & (box_rows < rows) & (box_cols >= 0) & (box_cols < cols)
    values = weight[:, None, None] * window[None]
    # the plane nearest the particle (half-open, so a particle between two planes has one) holds its peak
    peak = (depth >= -0.5) & (depth < 0.5) & (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    return FocusMarks(
        heat_index=(box_rows * cols + box_cols)[inside],
        heat_value=values[inside],
        peak_index=(row * cols + col)[peak],
        offset=depth[peak].astype(np.float32),
        diameter=(np.asarray(particles["diameter_um"], np.float64)[near][peak] / diameter_scale_um).astype(np.float32),
    )


def focus_targets(particles: dict[str, np.ndarray], **window) -> FocusTargets:
    """The dense targets of a window: `focus_marks` (its keyword arguments) drawn on ``window["shape"]``."""
    shape = window["shape"]
    marks = focus_marks(particles, **window)
    heat = np.zeros(shape[0] * shape[1], np.float32)
    np.maximum.at(heat, marks.heat_index, marks.heat_value)
    offset, diameter, positive = np.zeros_like(heat), np.zeros_like(heat), np.zeros(heat.shape, bool)
    heat[marks.peak_index] = 1.0
    positive[marks.peak_index] = True
    offset[marks.peak_index] = marks.offset
    diameter[marks.peak_index] = marks.diameter
    return FocusTargets(*(a.reshape(shape) for a in (heat, offset, diameter, positive)))


def context_indices(centres: Sequence[int], context: Sequence[int], n_planes: int) -> np.ndarray:
    """Stack indices of each centre plane's context, ``(len(centres), len(context))``; raises if one leaves the stack."""
    index = np.asarray(centres, np.int64)[:, None] + np.asarray(context, np.int64)[None, :]
    if index.size and (index.min() < 0 or index.max() >= n_planes):
        raise InputError(f"context: planes {index.min()}..{index.max()} needed, the stack has 0..{n_planes - 1}")
    return index
