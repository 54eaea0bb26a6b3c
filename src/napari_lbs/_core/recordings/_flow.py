"""A ground-truth recording: particles moving with a known flow, one hologram per frame.

Three flows, each with a maximum displacement of ``speed_um`` per frame:

- ``uniform``: every particle moves by ``speed_um x (0.6, 0.48, 0.64)`` (x, y, z) per frame;
- ``vortex``: solid-body rotation about the optical axis through the window's centre, at
  ``speed_um`` per frame on the inscribed circle (particles start inside it and stay there);
- ``shear``: ``dx = speed_um x (y - y_centre) / (rows / 2)`` per frame, nothing else.

A particle that leaves the window (or, along z, the config's volume) re-enters on the
opposite side as a new track, so the number of particles stays constant. Each frame's
hologram is simulated exactly as `napari-lbs simulate` simulates one (`simulate_hologram`:
opaque discs, unit plane wave, unobstructed light = 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback
from napari_lbs._core.physics import ParticleField, random_particle_field, simulate_hologram

__all__ = ["FLOWS", "SimulatedSequence", "flow_positions", "simulate_sequence"]

FLOWS = ("uniform", "vortex", "shear")
_UNIFORM_DIRECTION = np.array([0.6, 0.48, 0.64])  # a unit vector with a component along every axis


@dataclass(frozen=True)
class SimulatedSequence:
    """A simulated recording and its truth.

    Attributes
    ----------
    frames : (frames, rows, cols) float32 array
        The holograms (the ``out`` array when one was given).
    truth : dict of arrays
        Every particle of every frame: ``x_um, y_um, z_um, diameter_um`` (docs/formats.md), ``frame``
        (0-based) and ``track`` (one id per particle from entering to leaving the window).
    """

    frames: np.ndarray
    truth: dict[str, np.ndarray]


def flow_positions(
    start: ParticleField, *, flow: str, frames: int, speed_um: float, z_range_um: tuple[float, float]
) -> dict[str, np.ndarray]:
    """Positions of ``start``'s particles in each frame of a flow (see the module docstring).

    Parameters
    ----------
    start : ParticleField
        Positions at frame 0 (for ``vortex``, inside the circle inscribed in the window).
    flow : {"uniform", "vortex", "shear"}
    frames : int
        Number of frames.
    speed_um : float
        Largest displacement of a particle between two frames (µm).
    z_range_um : (float, float)
        Depths a particle may take; beyond them it re-enters at the other end.

    Returns
    -------
    dict of arrays
        The truth table (``x_um, y_um, z_um, diameter_um, frame, track``), frame by frame.
    """
    if flow not in FLOWS:
        raise InputError(f"flow: expected one of {', '.join(FLOWS)}, got {flow!r}")
    rows, cols = start.shape
    width_um, height_um = cols * start.pixel_um, rows * start.pixel_um  # a pixel spans ±0.5 px about its centre
    origin_um = -0.5 * start.pixel_um
    centre_x, centre_y = (cols - 1) * start.pixel_um / 2, (rows - 1) * start.pixel_um / 2
    z_low, z_high = z_range_um
    x, y, z = start.x_um.copy(), start.y_um.copy(), start.z_um.copy()
    track = np.arange(len(start))
    next_track = len(start)
    radius_um, angle = np.hypot(x - centre_x, y - centre_y), np.arctan2(y - centre_y, x - centre_x)
    columns: dict[str, list] = {name: [] for name in ("x_um", "y_um", "z_um", "diameter_um", "frame", "track")}
    for frame in range(frames):
        if frame:
            if flow == "uniform":
                x, y, z = x + speed_um * _UNIFORM_DIRECTION[0], y + speed_um * _UNIFORM_DIRECTION[1], z + speed_um * _UNIFORM_DIRECTION[2]
            elif flow == "vortex":  # exact rotation: every particle keeps its radius
                angle = angle + speed_um / (min(width_um, height_um) / 2)
                x, y = centre_x + radius_um * np.cos(angle), centre_y + radius_um * np.sin(angle)
            else:
                x = x + speed_um * (y - centre_y) / (height_um / 2)
            wrapped = (x < origin_um) | (x >= origin_um + width_um) | (y < origin_um) | (y >= origin_um + height_um) | (z < z_low) | (z > z_high)
            x = origin_um + np.mod(x - origin_um, width_um)
            y = origin_um + np.mod(y - origin_um, height_um)
            z = z_low + np.mod(z - z_low, z_high - z_low) if z_high > z_low else z
            track = track.copy()
            track[wrapped] = next_track + np.arange(int(wrapped.sum()))
            next_track += int(wrapped.sum())
        for name, values in (("x_um", x), ("y_um", y), ("z_um", z), ("diameter_um", start.diameter_um), ("track", track)):
            columns[name].append(np.array(values))
        columns["frame"].append(np.full(len(start), frame))
    return {name: np.concatenate(values) if values else np.zeros(0) for name, values in columns.items()}


def simulate_sequence(
    config: ExperimentConfig,
    *,
    frames: int,
    flow: str,
    size: int,
    count: int,
    speed_um: float = 8.0,
    seed: int | None = None,
    shadowing: bool = False,
    out: np.ndarray | None = None,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> SimulatedSequence:
    """Simulate a recording of ``count`` particles moving with a known ``flow``.

    Parameters
    ----------
    config : ExperimentConfig
        Optics, volume (the depths particles take) and particle diameters.
    frames : int
        Number of frames (at least 1).
    flow : {"uniform", "vortex", "shear"}
    size : int
        Window edge (pixels).
    count : int
        Particles in every frame.
    speed_um : float
        Largest displacement of a particle between two frames (µm).
    seed : int, optional
        Starting positions and diameters.
    shadowing : bool
        As `simulate_hologram`.
    out : (frames, size, size) float32 array, optional
        Where to write the holograms (e.g. a memory-mapped TIFF), so a long recording never
        has to fit in memory.
    progress, should_stop
        One step per frame; a stop raises `Stopped`.
    """
    if frames < 1:
        raise InputError(f"frames: expected at least 1, got {frames}")
    if not speed_um >= 0:
        raise InputError(f"speed_um: expected a non-negative displacement, got {speed_um}")
    pixel_um = config.optics.pixel_um
    start = random_particle_field(
        (size, size),
        count=count,
        diameter_min_um=config.particles.diameter_min_um,
        diameter_max_um=config.particles.diameter_max_um,
        layers_um=(config.volume.z_min_um, config.volume.z_max_um),
        pixel_um=pixel_um,
        seed=seed,
        continuous=True,
    )
    if flow == "vortex":  # start inside the inscribed circle, uniformly over its area
        rng = np.random.default_rng(None if seed is None else seed + 1)
        radius_um, angle = (size - 1) * pixel_um / 2 * np.sqrt(rng.uniform(0.0, 1.0, count)), rng.uniform(0.0, 2 * np.pi, count)
        centre_um = (size - 1) * pixel_um / 2
        start = ParticleField(centre_um + radius_um * np.cos(angle), centre_um + radius_um * np.sin(angle), start.z_um, start.diameter_um, start.shape, pixel_um)
    truth = flow_positions(start, flow=flow, frames=frames, speed_um=speed_um, z_range_um=(config.volume.z_min_um, config.volume.z_max_um))
    expected = (frames, size, size)
    if out is None:
        out = np.empty(expected, np.float32)
    elif tuple(out.shape) != expected:
        raise InputError(f"out: expected shape {expected}, got {tuple(out.shape)}")
    steps = Steps(frames, progress=progress, should_stop=should_stop)
    for frame in range(frames):
        steps.check()
        here = truth["frame"] == frame
        field = ParticleField(truth["x_um"][here], truth["y_um"][here], truth["z_um"][here], truth["diameter_um"][here], (size, size), pixel_um)
        out[frame] = simulate_hologram(field, wavelength_um=config.optics.wavelength_um, medium_index=config.optics.medium_index, shadowing=shadowing)
        steps.advance()
    return SimulatedSequence(out, truth)
