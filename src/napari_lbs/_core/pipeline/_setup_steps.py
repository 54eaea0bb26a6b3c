"""The steps that start from one hologram or none: simulate, backprop and calibrate."""

from __future__ import annotations

import time
from dataclasses import KW_ONLY, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from napari_lbs._core.foundation import ExperimentConfig, InputError
from napari_lbs._core.foundation import ProgressCallback, ReportCallback, StopCallback
from napari_lbs._core.foundation import write_json
from napari_lbs._core.pipeline._common import Log, StepResult, _background, _hologram, _quiet, _source, check_outputs, provenance

if TYPE_CHECKING:  # for the annotations only: the steps import these modules when they run
    import numpy as np

    from napari_lbs._core.calibration import CalibrationSettings

__all__ = ["SimulateRequest", "simulate", "BackpropRequest", "backprop", "CalibrateRequest", "calibrate"]


# --- simulate ------------------------------------------------------------------------------

# Peak memory of a simulation per pixel of its padded FFT grid (bytes), with a margin: the
# default config's 16 layers peak at 103 (256² window) to 141 (1024²) bytes (tracemalloc).
_SIMULATION_BYTES_PER_PX = 160


@dataclass(frozen=True)
class SimulateRequest:
    """A simulated hologram with its truth, or a recording with its tracks.

    Attributes
    ----------
    out_dir : Path
        Gets ``hologram.tif`` (``frames.tif`` for a recording) and ``particles.csv``.
    config : ExperimentConfig
    size_px : int, optional
        Window edge in pixels (default: ``config.tile.size``).
    particles : int, optional
        Number of particles (default: ``config.particles.per_tile``).
    seed : int
    shadowing : bool
        Propagate layer by layer so particles shadow each other.
    frames : int, optional
        A recording of this many frames instead of one hologram.
    flow : str
        A recording's flow: ``uniform``, ``vortex`` or ``shear``.
    speed_um : float
        A recording's largest displacement of a particle between frames (µm).
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    out_dir: Path
    config: ExperimentConfig = ExperimentConfig()
    _: KW_ONLY  # the data above, the options below
    size_px: int | None = None
    particles: int | None = None
    seed: int = 0
    shadowing: bool = False
    frames: int | None = None
    flow: str = "uniform"
    speed_um: float = 8.0
    replace: bool = False

    def outputs(self) -> tuple[Path, Path]:
        """The files the step writes into ``out_dir``: the hologram (or frames) and the truth."""
        return Path(self.out_dir) / ("hologram.tif" if self.frames is None else "frames.tif"), Path(self.out_dir) / "particles.csv"


def simulate(request: SimulateRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> StepResult:
    """Simulate a hologram (or a recording) of a random particle field and write it with its truth."""
    from napari_lbs._core.foundation import tiff_pages, write_particles
    from napari_lbs._core.physics import padded_shape
    from napari_lbs._core.physics import random_particle_field, simulate_hologram
    from napari_lbs._core.foundation import MAX_PARTICLES, check_memory

    config, out = request.config, Path(request.out_dir)
    size = request.size_px if request.size_px is not None else config.tile.size
    count = request.particles if request.particles is not None else config.particles.per_tile
    if isinstance(count, bool) or not isinstance(count, int) or not 0 <= count <= MAX_PARTICLES:
        raise InputError(f"--particles: expected an integer in [0, {MAX_PARTICLES}], got {count!r}")
    optics = config.optics
    check_outputs(request.outputs(), replace=request.replace)
    grid = padded_shape((size, size), z_max_um=config.volume.z_max_um, wavelength_um=optics.wavelength_um, pixel_um=optics.pixel_um, medium_index=optics.medium_index)
    check_memory(_SIMULATION_BYTES_PER_PX * grid[0] * grid[1], what=f"a {size}x{size} simulation ({grid[0]}x{grid[1]} padded)", remedy="use a smaller --size")
    if request.frames is not None:
        return _simulate_recording(request, size=size, count=count, progress=progress, should_stop=should_stop)
    field_ = random_particle_field(
        (size, size),
        count=count,
        diameter_min_um=config.particles.diameter_min_um,
        diameter_max_um=config.particles.diameter_max_um,
        layers_um=config.layer_depths_um(),
        pixel_um=optics.pixel_um,
        seed=request.seed,
    )
    hologram = simulate_hologram(field_, wavelength_um=optics.wavelength_um, medium_index=optics.medium_index, shadowing=request.shadowing)
    out.mkdir(parents=True, exist_ok=True)
    description = provenance(config, seed=request.seed, particles=len(field_), shadowing=request.shadowing, pixel_um=optics.pixel_um)
    with tiff_pages(out / "hologram.tif", hologram.shape, description=description, force=request.replace) as page:
        page[:] = hologram
    write_particles(out / "particles.csv", field_.table(), force=request.replace)
    paths = (out / "hologram.tif", out / "particles.csv")
    return StepResult(f"simulated a {size}x{size} hologram of {len(field_)} particles -> {paths[0]}, {paths[1]}", field_, paths)


def _simulate_recording(request: SimulateRequest, *, size: int, count: int, progress, should_stop) -> StepResult:
    """``frames.tif`` (one page per frame, written as it is simulated) and the truth with frame and track."""
    import numpy as np

    from napari_lbs._core.recordings import simulate_sequence
    from napari_lbs._core.foundation import tiff_pages, write_particles
    from napari_lbs._core.foundation import check_disk

    config, out, frames = request.config, Path(request.out_dir), request.frames
    check_disk(frames * size * size * np.dtype(np.float32).itemsize, out, what=f"{frames} frames of {size}x{size} pixels", remedy="use fewer --frames or a smaller --size")
    out.mkdir(parents=True, exist_ok=True)
    description = provenance(config, seed=request.seed, particles=count, shadowing=request.shadowing, pixel_um=config.optics.pixel_um, flow=request.flow,
                             speed_um=request.speed_um, frames=frames)
    with tiff_pages(out / "frames.tif", (frames, size, size), description=description, force=request.replace) as pages:
        truth = simulate_sequence(config, frames=frames, flow=request.flow, size=size, count=count, speed_um=request.speed_um, seed=request.seed,
                                  shadowing=request.shadowing, out=pages, progress=progress, should_stop=should_stop).truth
    write_particles(out / "particles.csv", truth, force=request.replace)
    tracks = len(np.unique(truth["track"]))
    paths = (out / "frames.tif", out / "particles.csv")
    return StepResult(f"simulated {frames} frames of {size}x{size} pixels, {count} particles in a {request.flow} flow ({tracks} tracks) -> {paths[0]}, {paths[1]}", truth, paths)


# --- backprop ------------------------------------------------------------------------------


@dataclass(frozen=True)
class BackpropRequest:
    """A hologram back-propagated to the config's planes, as a float32 ``(z, y, x)`` TIFF.

    Attributes
    ----------
    hologram : path or 2-D array
    out_path : Path
        The stack; its ImageDescription JSON holds ``z_um`` and the provenance.
    config : ExperimentConfig
    background_path : path, optional
        A hologram taken without particles, divided out.
    source : str, optional
        The hologram's name in the provenance (default: its path).
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    hologram: str | Path | np.ndarray
    out_path: Path
    config: ExperimentConfig = ExperimentConfig()
    _: KW_ONLY  # the data above, the options below
    background_path: str | Path | None = None
    source: str | None = None
    replace: bool = False

    def outputs(self) -> tuple[Path]:
        """The file the step writes."""
        return (Path(self.out_path),)


def backprop(request: BackpropRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Back-propagate a hologram into a z-stack TIFF, written plane by plane to disk."""
    import numpy as np

    from napari_lbs._core.foundation import tiff_pages
    from napari_lbs._core.physics import backpropagate
    from napari_lbs._core.foundation import check_disk

    config, out = request.config, Path(request.out_path)
    check_outputs(request.outputs(), replace=request.replace)
    hologram = _hologram(request.hologram, log=log)
    background = _background(request.background_path, hologram.shape, log=log)
    z_um = config.volume.planes_um()
    check_disk(len(z_um) * hologram.size * np.dtype(np.float32).itemsize, out, what=f"{len(z_um)} planes of {hologram.shape[0]}x{hologram.shape[1]} pixels",
               remedy="raise volume.z_step_um or write elsewhere")
    source = _source(request.hologram, request.source)
    description = {"z_um": list(z_um), **provenance(config, source=source, background=request.background_path and str(request.background_path))}
    start = time.perf_counter()
    # Written straight into a memory-mapped TIFF: a deep stack never has to fit in RAM.
    with tiff_pages(out, (len(z_um),) + hologram.shape, description=description, force=request.replace) as stack:
        backpropagate(hologram, z_um, wavelength_um=config.optics.wavelength_um, pixel_um=config.optics.pixel_um, medium_index=config.optics.medium_index,
                      background=background, out=stack, progress=progress, should_stop=should_stop)
    seconds = time.perf_counter() - start
    return StepResult(f"back-propagated {source} to {len(z_um)} planes ({z_um[0]:g}-{z_um[-1]:g} µm) in {seconds:.1f} s -> {out}", z_um, (out,))


# --- calibrate -----------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrateRequest:
    """Holo-processing fitted to one tile of a real hologram, written as calibration JSON.

    Attributes
    ----------
    hologram : path or 2-D array
    out_path : Path
    config : ExperimentConfig
    settings : CalibrationSettings, optional
        How to fit (default: `CalibrationSettings`'s defaults).
    roi : (x, y), optional
        Top-left pixel of the reference tile (default: the tool picks).
    background_path : path, optional
    source : str, optional
        The hologram's name in the provenance (default: its path).
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    hologram: str | Path | np.ndarray
    out_path: Path
    config: ExperimentConfig = ExperimentConfig()
    _: KW_ONLY  # the data above, the options below
    settings: CalibrationSettings | None = None
    roi: tuple[int, int] | None = None
    background_path: str | Path | None = None
    source: str | None = None
    replace: bool = False

    def outputs(self) -> tuple[Path]:
        """The file the step writes."""
        return (Path(self.out_path),)


def calibrate(request: CalibrateRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet,
              report: ReportCallback | None = None) -> StepResult:
    """Calibrate Holo-processing (`calibrate_hologram`) and write the calibration JSON with its provenance.

    ``report(record)`` receives each generation's best fitness as it is made (the widget's live curve).
    """
    from napari_lbs._core.calibration import CalibrationSettings, calibrate_hologram

    config, settings = request.config, request.settings or CalibrationSettings()
    check_outputs(request.outputs(), replace=request.replace)
    hologram = _hologram(request.hologram, log=log)
    background = _background(request.background_path, hologram.shape, log=log)
    result = calibrate_hologram(hologram, config, roi=request.roi, background=background, settings=settings, progress=progress, should_stop=should_stop,
                                report=report)
    payload = result.to_json()
    payload["provenance"] = provenance(config, source=_source(request.hologram, request.source), background=request.background_path and str(request.background_path), seed=settings.seed)
    write_json(request.out_path, payload, force=request.replace)
    p = result.params
    x, y, size = result.roi
    chosen = "" if request.roi else f" (chosen: {result.roi_choice})"
    summary = (f"calibrated on the {size}² tile at x={x}, y={y}{chosen}: N_R={p.N_R:.4f}, N_sigma={p.N_sigma:.4f}, gamma={p.gamma:.4f}, "
               f"SSIM={result.ssim:.4f}, {result.evaluations} evaluations in {result.seconds:.1f} s -> {request.out_path}")
    return StepResult(summary, result, (Path(request.out_path),))
