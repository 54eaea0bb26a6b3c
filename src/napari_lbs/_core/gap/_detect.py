"""The experiment's particles found without a trained model: focus in the back-propagated volume.

A particle at depth ``z`` is where the back-propagated field departs most from the
unobstructed light: an opaque disc is dark there, a transparent sphere a bright focal spot in
a dark ring. Both make the local energy of ``|B_z(h)| - 1`` (smoothed over about a particle's
area) peak at ``(x, y, z)``. The peaks of its maximum over the depths, a particle's diameter
apart and above the map's own spread, are the guesses, each at the depth of its maximum; the
Lorenz–Mie fits (`refine_particles`) correct depth and size from there.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig, InputError, Steps
from napari_lbs._core.physics import backpropagated_blocks, gaussian_blur

__all__ = ["find_particles"]

_PEAK_SPREADS = 8.0  # a peak stands this many robust spreads (1.4826 MAD) above the map's median


def find_particles(hologram: np.ndarray, config: ExperimentConfig, *, max_particles: int = 64, z_step_um: float | None = None,
                   steps: Steps | None = None) -> dict[str, np.ndarray]:
    """Guesses ``x_um, y_um, z_um, diameter_um`` (and ``focus``, the peak's height in spreads) of the particles of ``hologram``.

    Parameters
    ----------
    hologram : (rows, cols) array
        Intensity; divided by its mean before back-propagation.
    config : ExperimentConfig
        Optics, the depth range searched (``volume``) and the expected diameters
        (``particles``: their mean is each guess's diameter and sets the smoothing and the
        peaks' least distance).
    max_particles : int
        The strongest peaks kept.
    z_step_um : float, optional
        Spacing of the depths searched (µm); default twice the volume's step (the fit's depth
        scan covers the rest).
    steps : Steps, optional
        Advanced by each depth; a stop raises `Stopped`.

    Returns
    -------
    dict of arrays, strongest first.
    """
    image = np.asarray(hologram, dtype=np.float32)
    if image.ndim != 2:
        raise InputError(f"hologram: expected a 2-D image, got shape {image.shape}")
    if not (isinstance(max_particles, int) and max_particles >= 1):
        raise InputError(f"max_particles: expected a positive integer, got {max_particles!r}")
    optics, volume, particles = config.optics, config.volume, config.particles
    step = float(z_step_um) if z_step_um is not None else 2.0 * volume.z_step_um
    depths = np.arange(volume.z_min_um, volume.z_max_um + 0.5 * step, step)
    diameter_um = 0.5 * (particles.diameter_min_um + particles.diameter_max_um)
    radius_px = 0.5 * diameter_um / optics.pixel_um
    best = np.zeros(image.shape, np.float32)
    depth = np.full(image.shape, depths[0], np.float32)
    steps = steps if steps is not None else Steps(depths.size, progress=None, should_stop=None)
    for start, stop, field in backpropagated_blocks(image, depths, wavelength_um=optics.wavelength_um, pixel_um=optics.pixel_um,
                                                    medium_index=optics.medium_index, steps=steps):
        for k in range(stop - start):
            energy = gaussian_blur((np.abs(field[k]) - 1.0) ** 2, max(radius_px, 1.0))
            better = energy > best
            best[better] = energy[better]
            depth[better] = depths[start + k]
    median = float(np.median(best))
    spread = 1.4826 * float(np.median(np.abs(best - median))) or 1e-12
    from skimage.feature import peak_local_max

    # a particle centred a few pixels inside the edge is as much the frame's as any (its rings
    # are mostly in the frame): peaks are kept up to the last pixel but one
    peaks = peak_local_max(best, min_distance=max(int(round(2 * radius_px)), 1), threshold_abs=median + _PEAK_SPREADS * spread,
                           num_peaks=max_particles, exclude_border=1)
    rows, cols = (peaks[:, 0], peaks[:, 1]) if peaks.size else (np.empty(0, int), np.empty(0, int))
    return {
        "x_um": cols * optics.pixel_um,
        "y_um": rows * optics.pixel_um,
        "z_um": depth[rows, cols].astype(np.float64),
        "diameter_um": np.full(rows.size, diameter_um),
        "focus": (best[rows, cols] - median) / spread,
    }
