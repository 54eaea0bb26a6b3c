"""The effect catalog: parametric extensions of the seed's simulator, for diagnosis and for data.

The simulator is split in two stages so that fitting is cheap:

*optics* (`optical_hologram`)
    the intensity a sensor would see, from a particle field: the seed's opaque discs on
    superposed layers, optionally with ``particle_phase`` (transparent, refracting spheres),
    ``coherence`` (partial spatial coherence: a source of angular size θ blurs a layer's
    scattered field by σ = θ·z), ``multiple_scattering`` (layer-by-layer shadowing) and
    ``spherical_wave`` (a point source at distance L: a layer at z is magnified by
    M = L / (L − z) and seen at the equivalent distance M·z).
*sensor* (`sensor_image`)
    what the camera makes of it: the baseline's fringe contrast ``c``, read noise ``sigma``
    and response gamma (the seed's Gaussian noise + gamma, in the hologram domain so that
    experiment and simulation share one code path; the seed's noise offset N_R·R acts as a
    fringe contrast once the image is normalised by its mean), plus ``illumination``
    (a Gaussian beam envelope, off-centre), ``parasitic_fringes`` (static fringes: an etalon's
    straight fringe and the rings of dust on a window out of the volume),
    ``shot_noise`` (Poisson, signal dependent), ``sensor_blur`` (pixel crosstalk / MTF: it
    acts on the light reaching the pixels, so it blurs the intensity before the photon and
    read noise are added, and the noise stays white) and ``quantization`` (bit depth and
    saturation).

Every effect has physically sensible bounds, a neutral value (the effect switched off) and
two injection strengths used by the withheld-effect validation. Parameters are plain dicts
``{effect_id: {param: value}}``; an effect absent from the dict is off.

The same catalog makes training data more realistic (`effect_hologram`): the effects a
diagnosis names (`effects_from_report`) or that a user states (`parse_effect`) are added to
the synthetic holograms of `generate_dataset`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft

from napari_lbs._core.foundation import InputError
from napari_lbs._core.physics._gaussian_blur import gaussian_blur
from napari_lbs._core.physics._optics import superpose
from napari_lbs._core.physics._synthesis import ParticleField, layer_images, simulate_hologram

__all__ = [
    "Effect",
    "EFFECTS",
    "LIMITS",
    "BASELINE",
    "optical_hologram",
    "sensor_image",
    "OPTICAL_EFFECTS",
    "check_effects",
    "parse_effect",
    "parse_effects",
    "effects_from_report",
    "effect_hologram",
]


@dataclass(frozen=True)
class Effect:
    """One candidate effect.

    Attributes
    ----------
    id : str
        docs/formats.md id.
    bounds : dict of (low, high)
        Fit range of each parameter.
    neutral : dict
        Parameter values at which the effect does nothing.
    injections : tuple of dict
        A weak and a strong setting for the injection–recovery suite.
    injection_density : tuple of float
        Particle density of the weak and the strong injection, relative to the suite's own
        density: an effect whose strength is set by the scene rather than by a parameter
        (shadowing between layers grows with how often particles overlap in projection).
    optional : tuple of str
        Parameters that may be left out of a stated setting (`check_effects`): they take
        their neutral value, i.e. that part of the effect is off.
    """

    id: str
    description: str
    bounds: dict
    neutral: dict
    injections: tuple
    injection_density: tuple = (1.0, 1.0)
    optional: tuple = ()


_WAIST = float(np.sqrt(0.18))  # the envelope's waist where a setting leaves it out

BASELINE = Effect("baseline", "seed's simulator: opaque discs, Gaussian noise, gamma", {"contrast": (0.2, 1.6), "sigma": (0.001, 0.3), "gamma": (0.5, 2.0)}, {"contrast": 1.0, "sigma": 0.0, "gamma": 1.0}, ())

EFFECTS: dict[str, Effect] = {e.id: e for e in (
    # waist: the envelope's 1/e radius in units of the frame's side; a wide one with a large depth
    # is the gentle fall-off of an objective's or a window's vignetting, a narrow one a laser's beam
    Effect("illumination", "Gaussian beam envelope / vignetting", {"depth": (0.0, 0.8), "x0": (-0.5, 0.5), "y0": (-0.5, 0.5), "waist": (0.2, 1.5)},
           {"depth": 0.0, "x0": 0.0, "y0": 0.0, "waist": _WAIST}, ({"depth": 0.25, "x0": 0.2, "y0": -0.1}, {"depth": 0.5, "x0": 0.2, "y0": -0.1}), optional=("waist",)),
    Effect("shot_noise", "Poisson photon noise", {"log10_photons": (0.5, 4.0)}, {"log10_photons": 9.0}, ({"log10_photons": 1.9}, {"log10_photons": 1.4})),
    Effect("quantization", "bit depth and saturation", {"bits": (3.0, 10.0), "saturation": (1.05, 3.0)}, {"bits": 16.0, "saturation": 1e3}, ({"bits": 5.0, "saturation": 1.6}, {"bits": 4.0, "saturation": 1.25})),
    Effect("sensor_blur", "pixel integration / sensor MTF", {"sigma_px": (0.0, 2.0)}, {"sigma_px": 0.0}, ({"sigma_px": 0.8}, {"sigma_px": 1.4})),
    # spatial (a source of angular size θ) and temporal (a spectrum of full width Δλ at half
    # maximum, e.g. an LED or a laser diode): the first washes fringes out with depth, the second
    # with fringe order (far from the particle's axis), at every depth
    Effect(
        "coherence", "partial spatial (source size) and temporal (bandwidth) coherence", {"theta_mrad": (0.0, 3.0), "bandwidth_nm": (0.0, 60.0)}, {"theta_mrad": 0.0, "bandwidth_nm": 0.0},
        ({"theta_mrad": 1.2}, {"theta_mrad": 2.4}), optional=("bandwidth_nm", "theta_mrad"),
    ),
    # index contrast Δn = n_particle − n_medium: the range reaches polystyrene in water (0.26) and
    # in air (0.59); a range of 0 … 0.025 cannot hold polystyrene in water, and data made with
    # such a Δn lost a third of the detections on a pseudo-real hologram of it
    Effect("particle_phase", "transparent, refracting spheres", {"index_contrast": (0.0, 0.6), "transmission": (0.0, 1.0)}, {"index_contrast": 0.0, "transmission": 0.0}, ({"index_contrast": 0.0084, "transmission": 0.6}, {"index_contrast": 0.0168, "transmission": 0.9})),
    Effect("multiple_scattering", "shadowing between particle layers", {"on": (1.0, 1.0)}, {"on": 0.0}, ({"on": 1.0}, {"on": 1.0}), (6.0, 12.0)),
    # static fringes: an etalon's straight fringe, and dust grains on a window out of the volume
    # (`_dust_pattern`: grains per megapixel, and the first Fresnel zone √(λz) in pixels, which
    # sets the rings' spacing: 6 … 60 px is z ≈ 0.26 … 26 mm at 660 nm and 2.2 µm pixels)
    Effect(
        "parasitic_fringes", "static fringes: etalon, dust on a window",
        {"amplitude": (0.0, 0.2), "period_px": (4.0, 24.0), "angle_rad": (0.0, 3.1416), "phase_rad": (-2 * math.pi, 2 * math.pi),
         "dust_per_mpx": (0.0, 300.0), "dust_zone_px": (6.0, 60.0), "dust_grain_px": (1.0, 25.0)},
        {"amplitude": 0.0, "period_px": 20.0, "angle_rad": 0.0, "phase_rad": 0.0, "dust_per_mpx": 0.0, "dust_zone_px": 30.0, "dust_grain_px": 5.0},
        ({"amplitude": 0.04, "period_px": 14.0, "angle_rad": 0.7}, {"amplitude": 0.1, "period_px": 14.0, "angle_rad": 0.7}),
        optional=("dust_per_mpx", "dust_zone_px", "dust_grain_px", "amplitude", "period_px", "angle_rad", "phase_rad"),
    ),
    Effect("spherical_wave", "diverging illumination (point source at L)", {"source_mm": (8.0, 200.0)}, {"source_mm": 1e9}, ({"source_mm": 40.0}, {"source_mm": 15.0})),
)}
OPTICAL_EFFECTS = ("coherence", "particle_phase", "multiple_scattering", "spherical_wave")

# Physical limits of every parameter, wider than the fit bounds (`Effect.bounds`): a stated or
# reported value outside them makes no physical sense and would give NaN or all-zero data
# (0 bits, a period under the sampling limit, no photons) or a kernel no filter finishes in
# reasonable time (a blur of 1e7 pixels); `check_effects` refuses it.
LIMITS: dict[str, dict[str, tuple[float, float]]] = {
    "illumination": {"depth": (0.0, 1.0), "x0": (-2.0, 2.0), "y0": (-2.0, 2.0), "waist": (0.05, 10.0)},
    "shot_noise": {"log10_photons": (0.0, 12.0)},
    "quantization": {"bits": (1.0, 16.0), "saturation": (0.1, 1e3)},
    "sensor_blur": {"sigma_px": (0.0, 50.0)},
    "coherence": {"theta_mrad": (0.0, 50.0), "bandwidth_nm": (0.0, 200.0)},
    "particle_phase": {"index_contrast": (0.0, 2.0), "transmission": (0.0, 1.0)},
    "multiple_scattering": {"on": (0.0, 1.0)},
    "parasitic_fringes": {
        "amplitude": (0.0, 1.0), "period_px": (2.0, 1e6), "angle_rad": (-2 * math.pi, 2 * math.pi), "phase_rad": (-2 * math.pi, 2 * math.pi),
        "dust_per_mpx": (0.0, 2000.0), "dust_zone_px": (0.0, 500.0), "dust_grain_px": (0.5, 100.0),
    },
    "spherical_wave": {"source_mm": (1.0, 1e9)},
}


def _param(effects: dict, effect: str, name: str) -> float:
    """A parameter of ``effects`` (the effect's neutral setting where it is absent; an optional parameter left out is neutral)."""
    catalog = EFFECTS[effect]
    return float({**{n: catalog.neutral[n] for n in catalog.optional}, **effects.get(effect, catalog.neutral)}[name])


_DUST_SEED = 2718  # static grains: the same places in every hologram of a shape


def _fresnel_intensity(opaque_spectrum: np.ndarray, zone_px: float) -> np.ndarray:
    """Intensity (unobstructed = 1) behind an opaque mask, after Fresnel diffraction on its periodic grid.

    ``opaque_spectrum`` is the FFT of the mask (1 where opaque). The transfer function
    ``exp(-iπ N |f|²)``, ``N = zone_px²`` = λz over the pixel area (f in cycles per pixel), is
    the paraxial propagation of the mask's scattered field ``-opaque``; it factorises over the
    two axes. A propagator of its own, in pixel units, because `sensor_image` knows no
    wavelength or pitch (`_optics.propagate` works in µm).
    """
    rows, cols = opaque_spectrum.shape
    along = [np.exp(-1j * np.pi * zone_px**2 * np.fft.fftfreq(n) ** 2).astype(np.complex64) for n in (rows, cols)]
    scattered = scipy.fft.ifft2(-opaque_spectrum * along[0][:, None] * along[1][None, :])
    return (np.abs(1.0 + scattered) ** 2).astype(np.float32)


def _dust_mask(grid: tuple[int, int], count: int, grain_px: int) -> np.ndarray:
    """(grid) bool: ``count`` opaque grains of radius ``grain_px`` at fixed random places (seed `_DUST_SEED`), periodic.

    The places are drawn in a fixed order, so the mask of fewer grains is part of the mask of more.
    """
    places = (np.random.default_rng(_DUST_SEED).random((count, 2)) * grid).astype(int)
    r = grain_px
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disc = yy**2 + xx**2 <= r**2
    mask = np.zeros(grid, bool)
    for row, col in places:
        at = np.ix_(np.arange(row - r, row + r + 1) % grid[0], np.arange(col - r, col + r + 1) % grid[1])
        mask[at] |= disc
    return mask


@functools.lru_cache(maxsize=4)
def _dust_spectrum(grid: tuple[int, int], count: int, grain_px: int) -> np.ndarray:
    """FFT (complex64, read-only) of `_dust_mask`: data sets vary the grains' distance more often than their number and size."""
    spectrum = scipy.fft.fft2(_dust_mask(grid, count, grain_px).astype(np.complex64))
    spectrum.flags.writeable = False
    return spectrum


def _dust_pattern(shape: tuple[int, int], count_per_mpx: float, zone_px: float, grain_px: float = 5.0) -> np.ndarray:
    """Intensity (unobstructed = 1, float32) of dust grains on a window out of the volume.

    Opaque grains (`_dust_mask`, radius ``grain_px``: 5 px is 22 µm across at 2.2 µm pixels;
    dust on windows and cover glasses is 5–100 µm across; ``count_per_mpx`` per megapixel, over the window and a border
    of half its size, whose rings reach in), diffracted to the sensor (`_fresnel_intensity`)
    on a periodic grid twice the window's size: rings that spread further (a 5 px grain at
    ``zone_px`` 60 spreads over about 360 px) wrap around, as a window evenly covered with dust
    would also send them in.
    """
    rows, cols = shape
    grid = (2 * rows, 2 * cols)
    count = int(round(count_per_mpx * grid[0] * grid[1] / 1e6))
    return _fresnel_intensity(_dust_spectrum(grid, count, max(1, int(round(grain_px)))), zone_px)[rows // 2 : rows // 2 + rows, cols // 2 : cols // 2 + cols]


_SPHERE_SUPERSAMPLE = 4  # fine samples per pixel and axis for a sphere's transmission
_SPHERE_PATCH_PX = 64  # smallest edge of the patch (pixels) holding one sphere's band-limited field


def _sphere_fields(field: ParticleField, depth: float, *, transmission: float, index_contrast: float, wavelength_um: float) -> np.ndarray:
    """Scattered field ``t - 1`` of the spheres of one layer, ``t = τ exp(iφ0 sqrt(1 - (r/R)²))`` inside, band-limited.

    ``φ0 = 2π Δn d / λ`` is the phase delay through the centre of a sphere of diameter ``d``
    (Δn = ``index_contrast``, λ the vacuum wavelength): a 20 µm polystyrene sphere in water
    delays by 50 rad, a 30 µm one by 74 rad, and their ball-lens foci differ accordingly.

    A sphere tens of radians thick bends light far beyond the angles a pixel grid can hold
    (the ball-lens focus of a polystyrene sphere sends it out at ~20°); sampled at pixel
    centres, that light aliases into a pattern no camera records. So the transmission is
    sampled ``_SPHERE_SUPERSAMPLE`` times finer, low-passed to the pixel grid's band
    (|f| < 1/(2 pixel)) and sampled at the pixel centres: what propagates within the recorded
    bandwidth, and no more. Measured against Lorenz–Mie theory (polystyrene, n 1.59, in water,
    d 25 µm at 3 mm, pixel-integrated): Δn = 0.26 (φ0 = 62 rad) gives the Mie sphere's bright focal spot
    and hologram correlation 0.97, where point sampling gave 0.75.
    """
    fine = _SPHERE_SUPERSAMPLE
    rows, cols = field.shape
    out = np.zeros(field.shape, np.complex64)
    mask = field.z_um == depth
    for x, y, d in zip(field.x_um[mask], field.y_um[mask], field.diameter_um[mask], strict=True):
        col, row, radius = x / field.pixel_um, y / field.pixel_um, d / 2 / field.pixel_um
        # the patch holds the sphere and its band-limited ringing (32 px beyond it), a power of two
        patch_px = max(_SPHERE_PATCH_PX, 2 ** int(np.ceil(np.log2(2 * radius + 32))))
        half = patch_px // 2
        in_band = np.abs(np.fft.fftfreq(patch_px * fine, d=1.0 / fine)) <= 0.5  # cycles per pixel
        offsets = np.arange(-half * fine, half * fine) / fine  # pixels, pixel centres at multiples of 1
        col0, row0 = int(round(col)), int(round(row))
        r2 = ((offsets[None, :] + col0 - col) ** 2 + (offsets[:, None] + row0 - row) ** 2) / radius**2
        inside = r2 <= 1.0
        scattered = np.zeros(r2.shape, np.complex128)
        phase_rad = 2.0 * np.pi * index_contrast * d / wavelength_um
        scattered[inside] = transmission * np.exp(1j * phase_rad * np.sqrt(1.0 - r2[inside])) - 1.0
        spectrum = np.fft.fft2(scattered)
        spectrum *= in_band[:, None] & in_band[None, :]
        patch = np.fft.ifft2(spectrum)[::fine, ::fine]  # the band-limited field at the pixel centres
        r0, c0 = row0 - half, col0 - half
        rr0, cc0 = max(r0, 0), max(c0, 0)
        rr1, cc1 = min(r0 + patch_px, rows), min(c0 + patch_px, cols)
        if rr0 < rr1 and cc0 < cc1:
            out[rr0:rr1, cc0:cc1] += patch[rr0 - r0 : rr1 - r0, cc0 - c0 : cc1 - c0]
    return out


def optical_hologram(field: ParticleField, effects: dict, *, wavelength_um: float, medium_index: float = 1.0, periodic: bool = False) -> np.ndarray:
    """Sensor intensity of a particle field with the optical effects of ``effects`` (float32, unobstructed = 1).

    ``periodic``: the window is one period of an endless field (`superpose`); the shadowing
    model (``multiple_scattering``) always pads. A source of spectral width
    ``coherence.bandwidth_nm`` (FWHM of a Gaussian spectrum) gives ``1 + 2 Re⟨s⟩ + |s|²``: the
    interference term averaged over the spectrum (`superpose`'s ``bandwidth_um``), the
    scattered light's own intensity at the centre wavelength (the shadowing model ignores it).
    """
    unknown = set(effects) - set(EFFECTS)
    if unknown:
        raise InputError(f"effects: unknown effect id {sorted(unknown)[0]!r}; expected one of {', '.join(EFFECTS)}")
    if _param(effects, "multiple_scattering", "on") >= 0.5:
        return simulate_hologram(field, wavelength_um=wavelength_um, medium_index=medium_index, shadowing=True)
    source_um = _param(effects, "spherical_wave", "source_mm") * 1000.0
    if source_um < 1e11:
        if field.z_um.size and source_um <= float(np.max(field.z_um)):
            raise InputError(f"effects: spherical_wave.source_mm: expected a source beyond the deepest particle ({np.max(field.z_um) / 1000:g} mm), got {source_um / 1000:g}")
        # a point source at L: the layer at z is seen magnified by M = L/(L - z), at distance M z
        centre_x, centre_y = (field.shape[1] - 1) * field.pixel_um / 2, (field.shape[0] - 1) * field.pixel_um / 2
        magnification = source_um / (source_um - field.z_um)
        field = ParticleField(centre_x + magnification * (field.x_um - centre_x), centre_y + magnification * (field.y_um - centre_y), field.z_um * magnification, field.diameter_um * magnification, field.shape, field.pixel_um)
    depths = field.layers_um()
    if depths.size == 0:
        return np.ones(field.shape, np.float32)
    transmission, contrast = _param(effects, "particle_phase", "transmission"), _param(effects, "particle_phase", "index_contrast")
    if transmission > 0 or contrast > 0:
        fields = [_sphere_fields(field, z, transmission=transmission, index_contrast=contrast, wavelength_um=wavelength_um) for z in depths]
    else:
        fields = [-image for image in layer_images(field)[1]]
    theta = _param(effects, "coherence", "theta_mrad") * 1e-3
    if theta > 0:
        fields = [_blur(f, theta * z / field.pixel_um) for f, z in zip(fields, depths, strict=True)]
    optics = {"wavelength_um": wavelength_um, "pixel_um": field.pixel_um, "medium_index": medium_index, "periodic": periodic}
    scattered = superpose(fields, depths, **optics)
    bandwidth_um = _param(effects, "coherence", "bandwidth_nm") * 1e-3
    if bandwidth_um > 0:
        averaged = superpose(fields, depths, bandwidth_um=bandwidth_um, **optics)
        return (1.0 + 2.0 * averaged.real + np.abs(scattered) ** 2).astype(np.float32)
    return (np.abs(1.0 + scattered) ** 2).astype(np.float32)


def _blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    if np.iscomplexobj(image):
        return (gaussian_blur(image.real, sigma_px) + 1j * gaussian_blur(image.imag, sigma_px)).astype(image.dtype)
    return gaussian_blur(image, sigma_px)


def sensor_image(intensity: np.ndarray, baseline: dict, effects: dict, *, noise: np.ndarray, frame_px: tuple | None = None,
                 keep: tuple[slice, slice] | None = None) -> np.ndarray:
    """What the camera records of ``intensity``, in the physical order: baseline contrast, envelope, fringes, blur, gamma, noise, quantisation.

    The optical terms (contrast, envelope, fringes) and the blur (pixel crosstalk / MTF) act
    on the light reaching the pixels; the response (gamma) and the noise (photon noise on the
    blurred signal, then read noise added by the electronics) come after, so the noise is not
    blurred; quantisation is last.

    ``noise`` is a standard-normal array of the image's shape (fixed per tile: common random
    numbers make the fit deterministic).

    ``frame_px``: ``(row_px, col_px, (frame_rows, frame_cols))``, where on the sensor each row
    and column of ``intensity`` lies (pixels) and the sensor's shape: the envelope and the
    etalon's fringe are then those of that place of the frame (a tile of a large sensor).
    Default: ``intensity`` is the whole frame.

    ``keep``: the rows and columns of the image wanted (``intensity[keep]``'s place), the
    others not computed: every stage acts pixel by pixel but the blur, so without a blur each
    acts on the kept pixels alone, and with one the stages after it do (a fit that samples
    every other pixel evaluates a quarter of the frame).
    """
    rows, cols = intensity.shape
    row_px, col_px, (frame_rows, frame_cols) = frame_px if frame_px is not None else (np.arange(rows), np.arange(cols), (rows, cols))
    row_px, col_px = np.asarray(row_px), np.asarray(col_px)
    blur = _param(effects, "sensor_blur", "sigma_px")
    dust = _param(effects, "parasitic_fringes", "dust_per_mpx")
    # the dust's grains are drawn over the whole intensity, then cut like it
    dust_image = _dust_pattern((rows, cols), dust, _param(effects, "parasitic_fringes", "dust_zone_px"), _param(effects, "parasitic_fringes", "dust_grain_px")) if dust > 0 else None
    if keep is not None and blur <= 0:
        intensity, noise, row_px, col_px = intensity[keep], noise[keep], row_px[keep[0]], col_px[keep[1]]
        dust_image = dust_image[keep] if dust_image is not None else None
        keep = None
    image = 1.0 + float(baseline["contrast"]) * (intensity.astype(np.float32) - 1.0)
    depth = _param(effects, "illumination", "depth")
    if depth > 0:  # 1 - depth (1 - e^{-r²/w²}), the Gaussian an outer product of its row and column factors
        waist = _param(effects, "illumination", "waist")
        y = np.asarray(row_px, np.float64) / max(frame_rows - 1, 1) - 0.5 - _param(effects, "illumination", "y0")
        x = np.asarray(col_px, np.float64) / max(frame_cols - 1, 1) - 0.5 - _param(effects, "illumination", "x0")
        gaussian = np.outer(np.exp(-y * y / waist**2), np.exp(-x * x / waist**2))
        image = image * (1.0 - depth + depth * gaussian).astype(np.float32)
    if dust_image is not None:  # the grains' rings, formed by the light on its way to the sensor
        image = image * dust_image
    amplitude = _param(effects, "parasitic_fringes", "amplitude")
    if amplitude > 0:  # 1 + a cos(u_x + u_y + φ), the cosine of a sum as two outer products
        angle, period = _param(effects, "parasitic_fringes", "angle_rad"), _param(effects, "parasitic_fringes", "period_px")
        phase = _param(effects, "parasitic_fringes", "phase_rad")  # at the sensor's first pixel
        u_y = 2 * np.pi * np.asarray(row_px, np.float64) * np.sin(angle) / period + phase
        u_x = 2 * np.pi * np.asarray(col_px, np.float64) * np.cos(angle) / period
        fringe = np.outer(np.cos(u_y), np.cos(u_x)) - np.outer(np.sin(u_y), np.sin(u_x))
        image = image * (1.0 + amplitude * fringe).astype(np.float32)
    if blur > 0:  # crosstalk / MTF spreads the light over neighbouring pixels; the electronics' read noise comes later, unblurred
        if keep is None:
            image = gaussian_blur(image, blur)
        else:  # the kept rows and columns alone
            image = gaussian_blur(image, blur, keep=keep)
            noise = noise[keep]
    image = np.clip(image, 0.0, None) ** float(baseline["gamma"])
    photons = 10.0 ** _param(effects, "shot_noise", "log10_photons")
    # Poisson(N I)/N by its normal approximation, and Gaussian read noise, from one fixed draw
    scale = np.sqrt(image / photons + float(baseline["sigma"]) ** 2)
    image = image + scale * noise
    bits, saturation = _param(effects, "quantization", "bits"), _param(effects, "quantization", "saturation")
    if bits < 16:
        levels = 2.0 ** round(bits) - 1
        image = np.round(np.clip(image / saturation, 0.0, 1.0) * levels) / levels * saturation
    return image.astype(np.float32)


def _short(value: object) -> str:
    """``repr(value)`` cut to 40 characters (an error message stays one short line)."""
    text = repr(value) if not isinstance(value, int) or abs(value) < 10**30 else f"an integer of {len(str(abs(value)))} digits"
    return text if len(text) <= 40 else text[:37] + "..."


def check_effects(effects: dict) -> dict:
    """A validated copy of ``{effect_id: {param: value}}``: known ids and names, every parameter a finite number.

    A parameter whose bounds are a single value (``multiple_scattering.on``) or that the effect
    lists as optional (`Effect.optional`: it takes its neutral value) may be left out.
    Values are not clipped to the fit bounds (a stated value such as 12 bits is legitimate);
    they must lie within the physical limits (`LIMITS`). Raises `InputError` naming the culprit
    (effect.param, the value and the range).
    """
    if not isinstance(effects, dict):
        raise InputError(f"effects: expected a mapping of effect id to parameters, got {type(effects).__name__}")
    checked = {}
    for effect_id, params in effects.items():
        if effect_id not in EFFECTS:
            raise InputError(f"effects: unknown effect id {effect_id!r}; expected one of {', '.join(EFFECTS)}")
        effect = EFFECTS[effect_id]
        if not isinstance(params, dict):
            raise InputError(f"effects: {effect_id}: expected a mapping of parameter to value, got {type(params).__name__}")
        unknown = set(params) - set(effect.bounds)
        if unknown:
            raise InputError(f"effects: {effect_id}: unknown parameter {sorted(unknown)[0]!r}; expected {', '.join(effect.bounds)}")
        values = {}
        for name, (low, high) in effect.bounds.items():
            if name not in params:
                if low != high and name not in effect.optional:
                    raise InputError(f"effects: {effect_id}: missing parameter {name!r} (fit range {low:g} to {high:g})")
                values[name] = float(low) if low == high else float(effect.neutral[name])
                continue
            try:
                value = float(params[name])
            except (TypeError, ValueError, OverflowError):
                raise InputError(f"effects: {effect_id}.{name}: expected a number, got {_short(params[name])}") from None
            lowest, highest = LIMITS[effect_id][name]
            if not lowest <= value <= highest:  # NaN fails too
                raise InputError(f"effects: {effect_id}.{name}: expected a finite number in [{lowest:g}, {highest:g}], got {value:g}")
            values[name] = value
        checked[effect_id] = values
    return checked


def parse_effect(text: str, *, flag: str = "--effect") -> dict:
    """One effect from its command-line form ``ID`` or ``ID:NAME=VALUE[,NAME=VALUE...]`` (``flag``: the option named in errors).

    Example: ``particle_phase:index_contrast=0.26,transmission=1`` → ``{"particle_phase": {...}}``.
    """
    effect_id, _, rest = text.strip().partition(":")
    params = {}
    for item in filter(None, (part.strip() for part in rest.split(","))):
        name, sep, value = item.partition("=")
        if not sep:
            raise InputError(f"{flag} {text}: expected NAME=VALUE after the effect id, got {item!r}")
        params[name.strip()] = value.strip()
    return check_effects({effect_id: params})


def parse_effects(texts, *, flag: str = "--effect") -> dict:
    """The effects of several command-line forms (`parse_effect`; blank ones skipped), a later one overriding an earlier one of the same id."""
    effects = {}
    for text in texts:
        if text.strip():
            effects.update(parse_effect(text, flag=flag))
    return effects


def effects_from_report(report: dict, *, name: str = "report") -> dict:
    """The effects a diagnosis report names, with their fitted parameters.

    The verdict's effects: one, or several joined by ``+`` (``"a+b"``). Parameters are each
    effect's entry in ``effects`` (keys ``baseline.*``, the hologram-domain baseline of an older
    report, are left out: the calibrated Holo-processing replaces them). A report whose verdict
    is ``null`` (nothing missing, or undecided) names nothing: the result is empty.
    """
    try:
        verdict = report["verdict"]["id"]
        fits = {str(entry["id"]): entry["params"] for entry in report["effects"]}
    except (KeyError, TypeError, IndexError) as error:
        raise InputError(f"{name}: not a diagnosis report (missing {error})") from None
    if verdict is None:
        return {}
    chosen = {}
    for effect_id in str(verdict).split("+"):
        source = fits.get(effect_id)
        if source is None:
            raise InputError(f"{name}: the report names {effect_id!r} but records no parameters for it")
        if not isinstance(source, dict):
            raise InputError(f"{name}: effects: {effect_id}: params: expected a JSON object, got {type(source).__name__}")
        chosen[effect_id] = {k: v for k, v in source.items() if not str(k).startswith("baseline.")}
    try:
        return check_effects(chosen)
    except InputError as error:
        raise InputError(f"{name}: {error}") from None


def effect_hologram(field: ParticleField, effects: dict, *, wavelength_um: float, medium_index: float = 1.0, crop_px: int = 0, rng: np.random.Generator) -> np.ndarray:
    """A synthetic hologram with ``effects`` added to the seed's opaque-disc model (float32, unobstructed ≈ 1).

    Optical effects change the intensity reaching the sensor (`optical_hologram`); sensor
    effects are then applied with the baseline neutral (contrast 1, no read noise, gamma 1),
    because the calibrated Holo-processing adds the seed's noise and gamma afterwards. The
    shot-noise draw comes from ``rng``, and only when a sensor effect is present.
    ``crop_px``: a border of that many pixels is cut from the light before it reaches the
    sensor (a field simulated with its neighbours, `distractor_scene`), so the sensor
    effects (illumination envelope, noise) see the window alone.
    """
    effects = check_effects(effects)
    intensity = optical_hologram(field, {k: v for k, v in effects.items() if k in OPTICAL_EFFECTS}, wavelength_um=wavelength_um, medium_index=medium_index)
    if crop_px:
        intensity = np.ascontiguousarray(intensity[crop_px:-crop_px, crop_px:-crop_px])
    sensor = {k: v for k, v in effects.items() if k not in OPTICAL_EFFECTS}
    if not sensor:
        return intensity
    return sensor_image(intensity, BASELINE.neutral, sensor, noise=rng.standard_normal(intensity.shape).astype(np.float32))
