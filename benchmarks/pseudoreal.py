"""Pseudo-real holograms with ground truth, from a forward model napari-lbs never trains on.

Lorenz–Mie theory (pylorenzmie, a benchmark extra) for transparent polystyrene spheres
(n = 1.59) in water (n = 1.33) at 660 nm on 2.2 µm pixels, each pixel integrated over its
area (3 × 3 samples), under a Gaussian illumination envelope, with photon noise and 8-bit
quantisation: what a real camera records, none of it written with the project's `_effects`.

Speed: a sphere under plane-wave illumination scatters a field whose Cartesian components
depend on the azimuth φ around it only as (exact for every multipole order; Bohren &
Huffman, Sec. 4.4: the vector harmonics of plane-wave scattering all have m = 1)::

    E_x(ρ, φ) = cos²φ · E_x(ρ, 0) + sin²φ · E_x(ρ, 90°)
    E_y(ρ, φ) = cos φ sin φ · (E_x(ρ, 0) − E_x(ρ, 90°))
    E_z(ρ, φ) = cos φ · E_z(ρ, 0)

so pylorenzmie evaluates each sphere on two radial lines (finely sampled) and the plane is
filled by interpolation. `check_azimuthal` compares this with pylorenzmie on the full plane.
Each sphere's field is kept out to the radius where its fringes reach the pixel's first
zero (frequency 1/pixel; beyond it the pixel average removes them), with a cosine taper.

Depths: the spheres sit at physical depths ``z_w`` in water; the truth table gives the
air-equivalent depth ``z_um = z_w / 1.33`` — the convention of the seed and of the default
config (``medium_index = 1``, z as optical distances), for which the angular spectrum at
``z_w`` in water equals that at ``z_w / n`` in air to second order in the angle.
"""

from __future__ import annotations

import numpy as np

WAVELENGTH_UM = 0.66
PIXEL_UM = 2.2
N_MEDIUM = 1.33
N_PARTICLE = 1.59
SUPERSAMPLE = 3
_PROFILE_STEP_PX = 0.05
_TAPER = 0.8  # the field is tapered from this fraction of its cut-off radius to the cut-off


_EXTRA_ORDERS = 40


def _lorenz_mie(points_px: np.ndarray, radius_um: float, z_water_um: float, n_particle: float = N_PARTICLE):
    from pylorenzmie.theory import LorenzMie, Sphere
    from pylorenzmie.theory.Instrument import Instrument

    instrument = Instrument(wavelength=WAVELENGTH_UM, magnification=PIXEL_UM, n_m=N_MEDIUM)
    # pylorenzmie is wrong where k_m a is a multiple of pi: a radius off by 1e-6 um avoids it
    # a complex index n + ik is an absorbing sphere
    sphere = Sphere(a_p=radius_um + 1e-6, n_p=float(np.real(n_particle)), k_p=float(np.imag(n_particle)), x_p=0.0, y_p=0.0, z_p=z_water_um / PIXEL_UM)
    # pylorenzmie 3.4.0 starts the downward recurrence of D_n(mx) at its truncation order, where
    # for a non-absorbing sphere of size parameter >= 50 it has not forgotten its start: a_n
    # wrong by up to order 1, the hologram's modulation by about 20 % rms (25 um polystyrene in
    # water). Forty more orders start it where the Bessel functions decay (tests/test_refine.py).
    stock = Sphere.wiscombe_yang
    Sphere.wiscombe_yang = staticmethod(lambda x, m: stock(x, m) + _EXTRA_ORDERS)
    try:
        model = LorenzMie(coordinates=points_px, particle=[sphere], instrument=instrument)
        return model.field().copy()
    finally:
        Sphere.wiscombe_yang = staticmethod(stock)


def cutoff_px(z_water_um: float) -> float:
    """Radius (pixels) where a sphere's fringe frequency reaches 1/pixel (sin θ = λ_m / pixel)."""
    sin_theta = WAVELENGTH_UM / N_MEDIUM / PIXEL_UM
    return z_water_um * sin_theta / np.sqrt(1 - sin_theta**2) / PIXEL_UM


def radial_profiles(radius_um: float, z_water_um: float, length_px: float, n_particle: float = N_PARTICLE) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(rho_px, E_x along +x, E_x along +y, E_z along +x)`` of one sphere's scattered field."""
    rho = np.arange(0.0, length_px + 2 * _PROFILE_STEP_PX, _PROFILE_STEP_PX)
    zeros = np.zeros_like(rho)
    along_x = _lorenz_mie(np.stack([rho, zeros, zeros]), radius_um, z_water_um, n_particle)
    along_y = _lorenz_mie(np.stack([zeros, rho, zeros]), radius_um, z_water_um, n_particle)
    return rho, along_x[0], along_y[0], along_x[2]


def sphere_field(points_x_px: np.ndarray, points_y_px: np.ndarray, radius_um: float, z_water_um: float, *, length_px: float, taper: bool = True, n_particle: float = N_PARTICLE):
    """``(E_x, E_y, E_z)`` of one sphere at the origin, at the given points (pixels), via its radial profiles."""
    rho_grid, px, py, pz = radial_profiles(radius_um, z_water_um, length_px, n_particle)
    rho = np.hypot(points_x_px, points_y_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_phi = np.where(rho > 0, points_x_px / rho, 1.0)
        sin_phi = np.where(rho > 0, points_y_px / rho, 0.0)
    # linear interpolation on the uniform profile grid, the weights shared by the three profiles
    position = np.minimum(rho / _PROFILE_STEP_PX, rho_grid.size - 1.001)
    index = position.astype(np.int64)
    weight = (position - index).astype(np.float32)
    ex0, ex90, ez0 = ((1 - weight) * p[index] + weight * p[index + 1] for p in (px.astype(np.complex64), py.astype(np.complex64), pz.astype(np.complex64)))
    fields = (cos_phi**2 * ex0 + sin_phi**2 * ex90, cos_phi * sin_phi * (ex0 - ex90), cos_phi * ez0)
    if not taper:
        return fields
    u = np.clip((rho / length_px - _TAPER) / (1 - _TAPER), 0.0, 1.0)
    window = np.where(rho <= length_px, 0.5 * (1 + np.cos(np.pi * u)), 0.0)
    return tuple(f * window for f in fields)


def mie_fields(shape: tuple[int, int], x_um, y_um, z_air_um, diameter_um, n_particle=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The spheres' scattered field ``(E_x, E_y, E_z)`` relative to the incident wave (x-polarised, amplitude 1), complex64.

    Sampled at the centres of `SUPERSAMPLE` × `SUPERSAMPLE` sub-pixels of every pixel: arrays of
    ``(rows · SUPERSAMPLE, cols · SUPERSAMPLE)``. The total field is ``(1 + E_x, E_y, E_z)``;
    `mie_intensity` is its squared modulus averaged over each pixel.
    """
    rows, cols = shape
    s = SUPERSAMPLE
    ex = np.zeros((rows * s, cols * s), np.complex64)
    ey = np.zeros_like(ex)
    ez = np.zeros_like(ex)
    offsets = (np.arange(s) + 0.5) / s - 0.5
    sub_rows = (np.arange(rows)[:, None] + offsets).ravel()
    sub_cols = (np.arange(cols)[:, None] + offsets).ravel()
    indices = np.full(len(x_um), N_PARTICLE, complex) if n_particle is None else np.broadcast_to(np.asarray(n_particle, complex), (len(x_um),))
    for x, y, z_air, d, n in zip(x_um, y_um, z_air_um, diameter_um, indices, strict=True):
        z_water = z_air * N_MEDIUM
        length = cutoff_px(z_water)
        col, row = x / PIXEL_UM, y / PIXEL_UM
        r0, r1 = np.searchsorted(sub_rows, row - length), np.searchsorted(sub_rows, row + length)
        c0, c1 = np.searchsorted(sub_cols, col - length), np.searchsorted(sub_cols, col + length)
        dy, dx = np.meshgrid((sub_rows[r0:r1] - row).astype(np.float32), (sub_cols[c0:c1] - col).astype(np.float32), indexing="ij")
        fx, fy, fz = sphere_field(dx, dy, d / 2, z_water, length_px=length, n_particle=n)
        ex[r0:r1, c0:c1] += fx
        ey[r0:r1, c0:c1] += fy
        ez[r0:r1, c0:c1] += fz
    return ex, ey, ez


def pixel_average(sub_intensity: np.ndarray) -> np.ndarray:
    """A sub-pixel intensity (`mie_fields`' grid) averaged over each pixel, float32."""
    s = SUPERSAMPLE
    rows, cols = sub_intensity.shape[0] // s, sub_intensity.shape[1] // s
    return sub_intensity.reshape(rows, s, cols, s).mean(axis=(1, 3)).astype(np.float32)


def mie_intensity(shape: tuple[int, int], x_um, y_um, z_air_um, diameter_um, n_particle=None) -> np.ndarray:
    """Pixel-integrated Lorenz–Mie intensity of spheres (unobstructed light = 1), float32; ``n_particle`` per sphere (default polystyrene; complex: absorbing)."""
    ex, ey, ez = mie_fields(shape, x_um, y_um, z_air_um, diameter_um, n_particle)
    return pixel_average(np.abs(1 + ex) ** 2 + np.abs(ey) ** 2 + np.abs(ez) ** 2)


def camera(intensity: np.ndarray, *, rng: np.random.Generator, photons: float = 2000.0, mean_level: float = 180.0, envelope_waist: float = 3.0) -> np.ndarray:
    """An 8-bit camera frame: Gaussian beam envelope (off-centre), Poisson photons, rounding and clipping to 0–255.

    ``photons`` at unobstructed light in the beam's centre; that light reads ``mean_level``
    (the seed's real hologram: mean 161). ``envelope_waist``: 1/e² radius in units of the
    image half-width.
    """
    rows, cols = intensity.shape
    y = (np.arange(rows) - 0.45 * rows) / (rows / 2)
    x = (np.arange(cols) - 0.55 * cols) / (cols / 2)
    envelope = np.exp(-2 * (x[None, :] ** 2 + y[:, None] ** 2) / envelope_waist**2)
    counts = rng.poisson(photons * intensity * envelope)
    return np.clip(np.round(counts * (mean_level / photons)), 0, 255).astype(np.uint8)


IMPURITY_INDEX = 1.45  # debris: not the particles' material (silica-like), so not what training assumed


def _diameters(rng: np.random.Generator, count: int, sd_um: float | None) -> np.ndarray:
    """Sphere diameters (µm): uniform over 20–30, or normal around 25 with ``sd_um`` clipped to 20–30."""
    return rng.uniform(20.0, 30.0, count) if sd_um is None else np.clip(rng.normal(25.0, sd_um, count), 20.0, 30.0)


def pseudo_real(count: int, *, size: int = 1024, seed: int = 0, z_air_um: tuple[float, float] = (1900.0, 4700.0),
                impurities: int = 0, impurity_diameter_um: tuple[float, float] = (3.0, 12.0), margin_px: int = 0,
                impurities_truth: bool = False, diameter_sd_um: float | None = None) -> tuple[np.ndarray, dict] | tuple[np.ndarray, dict, dict]:
    """An 8-bit pseudo-real hologram of ``count`` polystyrene spheres and its truth table (air-equivalent depths).

    With ``impurities``, that many small spheres of index `IMPURITY_INDEX` (diameters uniform
    in ``impurity_diameter_um``) per window area scatter too, at depths over the volume; with
    ``margin_px`` the field is simulated over the window widened by that margin, spheres and
    impurities at the same density there, and the window is kept, as a crop of a real sensor.
    Neither is in the truth table. The ``count`` spheres of the window are the same as without
    them (drawn first, from the same seed). ``impurities_truth`` returns a third table, the
    impurities whose centres lie in the window (window coordinates). The spheres' diameters
    are uniform over 20–30 µm or, with ``diameter_sd_um``, normal around 25 µm with that
    spread (clipped to 20–30 µm): a monodisperse sample's.
    """
    rng = np.random.default_rng(seed)
    extent = (size - 1) * PIXEL_UM
    table = {
        "x_um": rng.uniform(0, extent, count),
        "y_um": rng.uniform(0, extent, count),
        "z_um": rng.uniform(*z_air_um, count),
        "diameter_um": _diameters(rng, count, diameter_sd_um),
    }
    if not (impurities or margin_px):
        intensity = mie_intensity((size, size), table["x_um"], table["y_um"], table["z_um"], table["diameter_um"])
        empty = {name: np.empty(0) for name in table}
        return (camera(intensity, rng=rng), table, empty) if impurities_truth else (camera(intensity, rng=rng), table)
    extra = np.random.default_rng([seed, 1])
    big = size + 2 * margin_px
    ratio = (big / size) ** 2
    shift = margin_px * PIXEL_UM
    neighbours = int(round(count * (ratio - 1)))
    nx, ny = [], []
    while len(nx) < neighbours:  # uniform over the margin
        x, y = extra.uniform(0, (big - 1) * PIXEL_UM, 2)
        if not (shift <= x <= shift + extent and shift <= y <= shift + extent):
            nx.append(x)
            ny.append(y)
    n_imp = int(round(impurities * ratio))
    x = np.concatenate([table["x_um"] + shift, nx, extra.uniform(0, (big - 1) * PIXEL_UM, n_imp)])
    y = np.concatenate([table["y_um"] + shift, ny, extra.uniform(0, (big - 1) * PIXEL_UM, n_imp)])
    z = np.concatenate([table["z_um"], extra.uniform(*z_air_um, neighbours), extra.uniform(*z_air_um, n_imp)])
    d = np.concatenate([table["diameter_um"], _diameters(extra, neighbours, diameter_sd_um), extra.uniform(*impurity_diameter_um, n_imp)])
    n = np.concatenate([np.full(count + neighbours, N_PARTICLE), np.full(n_imp, IMPURITY_INDEX)])
    intensity = mie_intensity((big, big), x, y, z, d, n)[margin_px : margin_px + size, margin_px : margin_px + size]
    image = camera(np.ascontiguousarray(intensity), rng=rng)
    if not impurities_truth:
        return image, table
    small = slice(count + neighbours, None)
    inside = (x[small] >= shift) & (x[small] <= shift + extent) & (y[small] >= shift) & (y[small] <= shift + extent)
    return image, table, {"x_um": x[small][inside] - shift, "y_um": y[small][inside] - shift, "z_um": z[small][inside], "diameter_um": d[small][inside]}


def check_azimuthal(size: int = 96, z_air_um: float = 2000.0, diameter_um: float = 25.0) -> float:
    """Largest difference between the radial-profile field and pylorenzmie's on a full plane (one sphere)."""
    z_water = z_air_um * N_MEDIUM
    grid = np.arange(size) - size / 2 + 0.3  # off the axes: every azimuth is exercised
    dy, dx = np.meshgrid(grid, grid, indexing="ij")
    direct = _lorenz_mie(np.stack([dx.ravel(), dy.ravel(), np.zeros(dx.size)]), diameter_um / 2, z_water)
    fast = sphere_field(dx.ravel(), dy.ravel(), diameter_um / 2, z_water, length_px=size, taper=False)
    return float(max(np.abs(direct[i] - fast[i]).max() for i in range(3)) / np.abs(direct[0]).max())
