"""The pitch a particle's fit sees: a microscope's sub-wavelength pixels binned to what the fringes need, and the depths a fit scans.

Shared by the ``refine`` command (`refine_hologram`) and ``predict --refine``, so that both
fit a hologram at the same scale.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, InputError

__all__ = ["binned_hologram", "default_depth_window_um", "fringe_binning"]


def fringe_binning(config: ExperimentConfig, *, medium_index: float) -> int:
    """Pixels binned per side for the fit: as many as keep the pitch within half the medium wavelength.

    The fringes of the scattered light with the beam hold no spatial frequency above ``n/λ``
    (only propagating light reaches the camera), so a pitch up to ``λ/(2n)`` samples them all: a microscope's pitch at the
    sample (0.0851 µm behind 85× in water, λ/(2n) = 0.248 µm) is binned by 2, which makes the
    same patch twice as wide for a quarter of the pixels. A lensless sensor's pitch is never
    binned (1).
    """
    return max(1, int(config.optics.wavelength_um / (2.0 * medium_index * config.optics.pixel_um) + 1e-9))


def default_depth_window_um(config: ExperimentConfig) -> float:
    """The depths a fit scans on each side of its guess by default (µm): a quarter of the config's depth range, at most `RefineSettings`' 400 µm.

    A lensless setup's range of millimetres keeps the 400 µm; a microscope's 5–65 µm scans
    ±15 µm, not a window 13 times the volume.
    """
    from napari_lbs._core.refine import RefineSettings

    return min(RefineSettings.depth_window_um, 0.25 * (config.volume.z_max_um - config.volume.z_min_um))


def binned_hologram(hologram: np.ndarray, config: ExperimentConfig, *, medium_index: float) -> tuple[np.ndarray, ExperimentConfig, float]:
    """The hologram as the fit sees it: binned by `fringe_binning`, the config of its pitch, and the shift (µm) of a binned pixel's centre beyond its block's first pixel.

    A position in the binned frame plus the shift is a position in the hologram's own
    coordinates (pixel ``(r, c)`` at ``(c, r) × pixel_um``); unbinned (a lensless pitch) the
    shift is 0 and the hologram is returned as it is.
    """
    factor = fringe_binning(config, medium_index=medium_index)
    image, fit_config = _binned(np.asarray(hologram, dtype=np.float64), config, factor)
    return image, fit_config, 0.5 * (factor - 1) * config.optics.pixel_um


def binned_valid(valid: np.ndarray | None, config: ExperimentConfig, *, medium_index: float) -> np.ndarray | None:
    """The fit's valid pixels (`refine_particles`) in `binned_hologram`'s frame: a binned pixel is valid where every pixel of its block is."""
    if valid is None:
        return None
    factor = fringe_binning(config, medium_index=medium_index)
    blocks, _ = _binned(np.asarray(valid, dtype=np.float64), config, factor)
    return blocks >= 1.0


def _binned(hologram: np.ndarray, config: ExperimentConfig, factor: int) -> tuple[np.ndarray, ExperimentConfig]:
    """The hologram's ``factor``² blocks averaged (the last rows and columns that fill no block dropped) and the config of their pitch."""
    from dataclasses import replace

    if factor == 1:
        return hologram, config
    rows, cols = (n // factor * factor for n in hologram.shape)
    if rows == 0 or cols == 0:
        raise InputError(f"hologram: expected at least {factor}x{factor} pixels, got shape {hologram.shape}")
    blocks = hologram[:rows, :cols].reshape(rows // factor, factor, cols // factor, factor).mean(axis=(1, 3))
    return blocks, replace(config, optics=replace(config.optics, pixel_um=config.optics.pixel_um * factor))
