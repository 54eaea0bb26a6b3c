"""The Lorenz–Mie hologram of a whole particle table, and what a hologram holds beyond it.

A refined table (`refine_particles`) describes every sphere it kept by its position, depth,
diameter, index contrast and absorption: `particle_hologram` renders their hologram over a
whole frame, the fields of all spheres added coherently, so that dividing it out of the
data (`residual_hologram`) leaves what the table does not explain — a particle the network
did not propose (hidden by a neighbour's fringes, or of a size it never saw) among the
remains of the fits.

Each sphere is rendered on the square around the disc where its fringes lie below
``reach_cycles_per_px``. At the default, the pixel's Nyquist frequency (``0.5``; at most
``2 * patch_px`` pixels wide), the hologram is what the fit modelled: beyond it the camera
aliases the fringes and the fit does not model them either. A pitch that samples every
propagating angle (a microscope's, `samples_every_angle`) aliases nothing: each sphere is
rendered over the whole frame, as the fit models its neighbours. A camera records more than
that: a pixel integrating its square passes fringes up to 1 cycle per pixel (its transfer
``sinc`` falls to zero there), aliased. A sphere 3 mm away at 2.2 µm pixels leaves rings to
twice the Nyquist radius, over most of a 512² frame: rendered with ``reach_cycles_per_px=1``
(and no patch limit) the true spheres of a pixel-integrated Lorenz–Mie frame are reproduced
to 0.002 rms, to 0.017 at the Nyquist disc.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import PARTICLE_COLUMNS, InputError
from napari_lbs._core.refine._material import MATERIAL_TOLERANCE, same_material
from napari_lbs._core.physics import fields_from_profiles, holograms_from_fields, radial_profiles, term_count
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback, WorkerPool
from napari_lbs._core.refine._patches import check_table as _check_table
from napari_lbs._core.refine._patches import samples_every_angle
from napari_lbs._core.refine._refine import RefineSettings, refine_particles

__all__ = ["particle_hologram", "particle_holograms", "residual_hologram", "residual_particles"]

_BLOCK_POINTS = 1 << 18  # points (of all the materials) rendered at once: 4 MB a complex field


def _render_edge(z_um: float, *, reach_cycles_per_px: float, limit_px: int, wavelength_um: float, medium_index: float, pixel_um: float) -> int:
    """Edge (px) of the square holding a sphere's fringes up to ``reach_cycles_per_px``, at most ``limit_px``."""
    sin_reach = min(reach_cycles_per_px * wavelength_um / medium_index / pixel_um, 0.99)
    radius_px = z_um * sin_reach / math.sqrt(1.0 - sin_reach**2) / pixel_um
    return int(max(16, min(limit_px, 2 * round(radius_px))))


def particle_hologram(shape: tuple[int, int], table, config: ExperimentConfig, *, settings: RefineSettings | None = None,
                      reach_cycles_per_px: float = 0.5, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> np.ndarray:
    """The normalised Lorenz–Mie hologram of the spheres of ``table`` on a frame of ``shape``.

    Parameters
    ----------
    shape : (rows, cols)
        The frame (pixels of ``config.optics.pixel_um``).
    table : pandas.DataFrame or dict of arrays
        ``x_um, y_um, z_um, diameter_um`` (depths in the config's convention) and, when
        present, ``index_contrast`` and ``absorption`` (else ``settings``' starts): a refined
        table as `refine_particles` returns it.
    config : ExperimentConfig
    settings : RefineSettings, optional
        The medium's index, the pixel integration and the largest patch, as the fit used
        them.
    reach_cycles_per_px : float
        Fringe frequency (cycles per pixel) up to which each sphere is rendered: ``0.5``
        (Nyquist, within ``2 * settings.patch_px`` pixels, or the whole frame at a pitch that
        samples every angle) as the fit modelled it; ``1``
        (the pixel's box transfer falls to zero there; no patch limit) for everything a
        camera records, aliased fringes included (module docstring).
    progress, should_stop : callable, optional
        ``progress`` hears of each sphere rendered; ``should_stop`` is polled before each
        one, and `Stopped` is raised when it returns True.

    Returns
    -------
    (rows, cols) float64 array: ``|x̂ + Σ E_s|²`` with unobstructed light 1. Each sphere's
    interference with the plane wave goes through its pixel transfer; the intensity of the
    summed field adds last, so overlapping spheres interfere as fields do.
    """
    import pandas as pd

    settings = settings or RefineSettings()
    frame = _check_table(table)
    column = lambda name, default: (pd.to_numeric(frame[name], errors="coerce").fillna(default).to_numpy(np.float64)
                                    if name in frame else np.full(len(frame), default))
    materials = (column("index_contrast", settings.index_contrast)[None], column("absorption", settings.absorption)[None])
    return _rendered(shape, frame, config, materials, settings=settings, reach_cycles_per_px=reach_cycles_per_px, progress=progress,
                     should_stop=should_stop)[0]


def particle_holograms(shape: tuple[int, int], table, config: ExperimentConfig, *, materials, settings: RefineSettings | None = None,
                       reach_cycles_per_px: float = 0.5, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> np.ndarray:
    """`particle_hologram` of ``table``'s spheres made of each of ``materials`` in turn: (M, rows, cols).

    ``materials``: a sequence of mappings ``{"index_contrast": n_p - n_m, "absorption": κ}``,
    each given to every sphere of ``table`` (its own optics columns are not used). The
    spheres' places, the radial grids and the fringes' carrier are computed once for all the
    materials; each hologram is the one `particle_hologram` renders of the table with those
    optics (to rounding: the partial-wave sums of several materials are matrix products).
    Other arguments as `particle_hologram`.
    """
    settings = settings or RefineSettings()
    frame = _check_table(table)
    chosen = list(materials)
    if not chosen or not all(isinstance(m, dict) and set(m) == {"index_contrast", "absorption"} for m in chosen):
        raise InputError("particle holograms: materials must be a non-empty sequence of {'index_contrast': ..., 'absorption': ...}")
    values = [np.array([[float(m[name])] * len(frame) for m in chosen]).reshape(len(chosen), len(frame)) for name in ("index_contrast", "absorption")]
    if not all(np.all(np.isfinite(v)) for v in values):
        raise InputError("particle holograms: a material's index contrast or absorption is not a finite number")
    return _rendered(shape, frame, config, tuple(values), settings=settings, reach_cycles_per_px=reach_cycles_per_px, progress=progress,
                     should_stop=should_stop)


def _rendered(shape: tuple[int, int], frame, config: ExperimentConfig, materials: tuple[np.ndarray, np.ndarray], *, settings: RefineSettings,
              reach_cycles_per_px: float, progress: ProgressCallback | None, should_stop: StopCallback | None) -> np.ndarray:
    """The holograms (M, rows, cols) of the checked table ``frame`` with (M, N) index contrasts and absorptions ``materials``."""
    if len(tuple(shape)) != 2:
        raise InputError(f"particle hologram: expected a frame shape (rows, cols), got {tuple(shape)}")
    rows, cols = (int(n) for n in shape)
    if rows < 1 or cols < 1:
        raise InputError(f"particle hologram: expected a frame of at least one pixel, got shape {tuple(shape)}")
    optics = config.optics
    pixel = optics.pixel_um
    to_physical = settings.medium_index / optics.medium_index
    x, y = frame["x_um"].to_numpy(np.float64), frame["y_um"].to_numpy(np.float64)
    z, diameter = frame["z_um"].to_numpy(np.float64) * to_physical, frame["diameter_um"].to_numpy(np.float64)
    contrast, absorption = materials
    count = contrast.shape[0]
    cross = np.zeros((count, rows, cols))
    summed = np.zeros((count, 3, rows, cols), dtype=np.complex128)
    optics_kw = {"wavelength_um": optics.wavelength_um, "medium_index": settings.medium_index}
    if not (isinstance(reach_cycles_per_px, int | float) and 0.0 < reach_cycles_per_px <= 1.0):
        raise InputError(f"particle hologram: reach_cycles_per_px must be in (0, 1], got {reach_cycles_per_px!r}")
    # as the fit's neighbours: within 2 patches, or over the whole frame where the pitch samples every angle
    fine = samples_every_angle(wavelength_um=optics.wavelength_um, medium_index=settings.medium_index, pixel_um=pixel)
    limit = 2 * settings.patch_px if reach_cycles_per_px <= 0.5 and not fine else 2 * max(rows, cols) + 2
    steps = Steps(len(frame), progress=progress, should_stop=should_stop)
    for i in range(len(frame)):
        steps.check()
        edge = _render_edge(z[i], reach_cycles_per_px=reach_cycles_per_px, limit_px=limit, wavelength_um=optics.wavelength_um,
                            medium_index=settings.medium_index, pixel_um=pixel)
        half = edge // 2
        c0, r0 = round(x[i] / pixel) - half, round(y[i] / pixel) - half
        r_lo, r_hi, c_lo, c_hi = max(r0, 0), min(r0 + edge, rows), max(c0, 0), min(c0 + edge, cols)
        if r_lo >= r_hi or c_lo >= c_hi:
            steps.advance()
            continue  # a sphere whose fringes miss the frame
        depth = torch.tensor([z[i]], dtype=torch.float64)
        # (M, 1): the M materials of this sphere, at its one depth and its points
        sphere = [torch.full((count, 1), diameter[i], dtype=torch.float64)] + [torch.tensor(values[:, i : i + 1], dtype=torch.float64)
                                                                             for values in (contrast, absorption)]
        size = math.pi * settings.medium_index / optics.wavelength_um * diameter[i]
        corners_x, corners_y = np.array([c_lo, c_hi - 1]) * pixel - x[i], np.array([r_lo, r_hi - 1]) * pixel - y[i]
        rho_max = float(np.sqrt(np.max(corners_x**2) + np.max(corners_y**2)))
        # Wiscombe's count at the fitted size: what it leaves out is below 2e-9 of the hologram
        profiles, step = radial_profiles(depth, *sphere, rho_max_um=rho_max, terms=term_count(size, 1.0), **optics_kw)
        # rows a block: each field's temporaries stay below the size from which the C allocator maps
        # (and unmaps) memory at every call, which costs as much in page faults as the arithmetic
        block_rows = max(1, _BLOCK_POINTS // (count * (c_hi - c_lo)))
        for b_lo in range(r_lo, r_hi, block_rows):
            b_hi = min(b_lo + block_rows, r_hi)
            rr, cc = np.mgrid[b_lo:b_hi, c_lo:c_hi]
            dx = torch.as_tensor(cc.reshape(1, -1) * pixel - x[i], dtype=torch.float64)
            dy = torch.as_tensor(rr.reshape(1, -1) * pixel - y[i], dtype=torch.float64)
            fields = fields_from_profiles(profiles, step, dx, dy, depth, **optics_kw)
            single = holograms_from_fields(fields, dx, dy, depth, pixel_um=pixel if settings.pixel_integration else None, **optics_kw)
            own = sum(f.real**2 + f.imag**2 for f in fields)
            block = (slice(None), slice(b_lo, b_hi), slice(c_lo, c_hi))
            cross[block] += (single - 1.0 - own).reshape(count, *rr.shape).numpy()
            for axis in range(3):
                summed[(slice(None), axis, *block[1:])] += fields[axis].reshape(count, *rr.shape).numpy()
        steps.advance()
    return 1.0 + cross + np.sum(summed.real**2 + summed.imag**2, axis=1)


def residual_hologram(hologram: np.ndarray, table, config: ExperimentConfig, *, settings: RefineSettings | None = None,
                      background: np.ndarray | None = None, progress: ProgressCallback | None = None,
                      should_stop: StopCallback | None = None) -> np.ndarray:
    """``hologram`` less the hologram of ``table``'s spheres, in its own units.

    The data is divided by ``background`` (else by its mean, as `refine_particles` sees it
    from ``napari-lbs predict --refine``); the spheres' terms, ``particle_hologram - 1``,
    are taken away there and the result multiplied back, so a network or a fit sees the
    hologram the table's spheres would leave without them. ``progress`` and
    ``should_stop`` are `particle_hologram`'s (one step per sphere).
    """
    image = np.asarray(hologram, dtype=np.float64)
    if image.ndim != 2:
        raise InputError(f"hologram: expected a 2-D image, got shape {image.shape}")
    scale = np.asarray(background, dtype=np.float64) if background is not None else float(np.mean(image))
    if np.shape(scale) not in ((), image.shape) or not np.all(np.asarray(scale) > 0):
        raise InputError(f"background: expected positive values of the hologram's shape {image.shape}, got shape {np.shape(scale)}")
    model = particle_hologram(image.shape, table, config, settings=settings, progress=progress, should_stop=should_stop)
    return (image / scale - (model - 1.0)) * scale


def residual_particles(hologram: np.ndarray, table, config: ExperimentConfig, *, propose, settings: RefineSettings | None = None,
                       background: np.ndarray | None = None, valid: np.ndarray | None = None, progress: ProgressCallback | None = None,
                       should_stop: StopCallback | None = None, pool: WorkerPool | None = None):
    """Particles the residual of a refined ``table`` holds: proposed there, refined there.

    Parameters
    ----------
    hologram : (rows, cols) array
        The hologram ``table`` was refined on, in its own units.
    table : pandas.DataFrame
        A refined table (`refine_particles`), every scatterer it kept.
    config : ExperimentConfig
    propose : callable
        ``propose(image)`` -> a particle table of guesses for a hologram in ``hologram``'s
        units: the network's proposals (`predict_particles` down to its proposal threshold).
    settings : RefineSettings, optional
        How the table was refined; the new particles are refined the same way.
    background : (rows, cols) array, optional
        As `residual_hologram`.
    valid : (rows, cols) bool array, optional
        The pixels the fits compare (`refine_particles`); ``propose`` sees the unobstructed
        light at the others.
    progress, should_stop
        Passed to the rendering of the table's spheres (one step per sphere), then to the
        refinement (one step per batch); ``propose`` reports its own.
    pool : WorkerPool, optional
        Processes the finds are fitted in (`refine_particles`'s ``pool``).

    Returns
    -------
    pandas.DataFrame
        The new particles as `refine_particles` returns them, fitted on the residual (the
        table's spheres taken out of the data; their interference with a find is neither
        taken out nor modelled): those the fit refined and measured as the sample's material (an index contrast within `MATERIAL_TOLERANCE` of
        ``settings.index_contrast``, whatever its uncertainty), less those that refit onto a
        particle of ``table`` (within a quarter of the smaller diameter laterally and two
        diameters in depth: what the table's fit left of it). A particle hidden in a
        neighbour's fringes or along its line of sight is so fitted against the data its
        neighbours leave.
    """
    import pandas as pd

    settings = settings or RefineSettings()
    image = np.asarray(hologram, dtype=np.float64)
    scale = np.asarray(background, dtype=np.float64) if background is not None else float(np.mean(image))
    kept = pd.DataFrame(table).reset_index(drop=True)
    # the rows the fit measured: an unrefined row is a guess, whose hologram may be far off
    fitted = kept[kept["refined"].astype(bool)] if "refined" in kept else kept
    residual = residual_hologram(image, fitted, config, settings=settings, background=background, progress=progress, should_stop=should_stop)
    # the network sees an intensity: where a fit overshoots the data, none is left
    try:
        seen = np.maximum(residual, 0.0) if valid is None else np.where(valid, np.maximum(residual, 0.0), scale)
        guesses = pd.DataFrame({name: np.asarray(values) for name, values in dict(propose(seen)).items()})
    except (TypeError, ValueError) as error:
        raise InputError(f"propose: expected a particle table (columns of equal length), got {error}") from None
    if guesses.empty:
        guesses = pd.DataFrame({name: np.empty(0) for name in PARTICLE_COLUMNS})
    found = refine_particles(residual / scale, guesses, config, settings=settings, valid=valid, progress=progress, should_stop=should_stop, pool=pool)
    # a find is a particle of the sample, measured as one: the residual also holds debris and
    # what the fits left, which the network, seeing them without their context, proposes too
    # (whatever their uncertainty, sigmas=0: a loose index does not make a find)
    sample = same_material(found, index_contrast=settings.index_contrast, tolerance=MATERIAL_TOLERANCE, sigmas=0.0)
    found = found[found["refined"].to_numpy(bool) & sample].reset_index(drop=True)
    if found.empty or kept.empty:
        return found
    lateral = np.hypot(found["x_um"].to_numpy()[:, None] - kept["x_um"].to_numpy()[None], found["y_um"].to_numpy()[:, None] - kept["y_um"].to_numpy()[None])
    smaller = np.minimum(found["diameter_um"].to_numpy()[:, None], kept["diameter_um"].to_numpy()[None])
    # a find near a table particle in depth is that particle's misfit; one farther along its
    # line of sight was fitted where the particle was taken out and may be hidden behind it:
    # it joins, and the refit's `_refine._duplicates` keeps the better fitted of the two.
    # The table's depths are in the config's convention, the diameters in the medium.
    depth = np.abs(found["z_um"].to_numpy()[:, None] - kept["z_um"].to_numpy()[None]) * settings.medium_index / config.optics.medium_index
    twin = ((lateral < 0.25 * smaller) & (depth < 2.0 * smaller)).any(axis=1)
    return found[~twin].reset_index(drop=True)
