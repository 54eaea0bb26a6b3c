"""The effect catalog's physics (the diagnosis itself: tests/test_nested_effects.py and tests/test_diagnosis.py)."""

import numpy as np
import pytest

from napari_lbs._core import EFFECTS, ExperimentConfig, InputError, random_particle_field, simulate_hologram
from napari_lbs._core.physics._effects import BASELINE, optical_hologram, sensor_image

CONFIG = ExperimentConfig()
NEUTRAL = dict(BASELINE.neutral)


def field(shape=(64, 64), count=2, seed=0):
    return random_particle_field(shape, count=count, diameter_min_um=20, diameter_max_um=30, layers_um=CONFIG.layer_depths_um(), pixel_um=2.2, seed=seed)


def test_every_contract_effect_is_in_the_catalog_with_bounds_containing_its_injections():
    assert set(EFFECTS) >= {"illumination", "shot_noise", "quantization", "sensor_blur", "coherence", "particle_phase", "multiple_scattering", "parasitic_fringes", "spherical_wave"}
    for effect in EFFECTS.values():
        for injection in effect.injections:
            for name, value in injection.items():
                low, high = effect.bounds[name]
                assert low <= value <= high, (effect.id, name)


def test_neutral_settings_reproduce_the_seed_simulator_exactly():
    particles = field()
    reference = simulate_hologram(particles, wavelength_um=0.66)
    neutral = {e.id: dict(e.neutral) for e in EFFECTS.values()}
    np.testing.assert_allclose(optical_hologram(particles, {k: v for k, v in neutral.items() if k in ("coherence", "particle_phase", "multiple_scattering", "spherical_wave")}, wavelength_um=0.66), reference, atol=2e-5)
    noise = np.zeros((64, 64), np.float32)
    np.testing.assert_allclose(sensor_image(reference, NEUTRAL, {k: v for k, v in neutral.items() if k not in ("coherence", "particle_phase", "multiple_scattering", "spherical_wave")}, noise=noise), reference, atol=1e-5)


def test_shot_noise_variance_grows_with_the_signal_as_poisson():
    rng = np.random.default_rng(0)
    flat = np.full((200, 200), 1.0, np.float32)
    for level in (0.5, 2.0):
        image = sensor_image(flat * level, NEUTRAL, {"shot_noise": {"log10_photons": 2.0}}, noise=rng.standard_normal(flat.shape).astype(np.float32))
        # Poisson: var(N I)/N² = I / N, within 5 % (40 000 samples)
        assert image.var() == pytest.approx(level / 100.0, rel=0.05)


def test_quantization_leaves_at_most_2_to_the_bits_levels_and_clips_at_saturation():
    rng = np.random.default_rng(1)
    intensity = rng.uniform(0.0, 2.0, (64, 64)).astype(np.float32)
    image = sensor_image(intensity, NEUTRAL, {"quantization": {"bits": 4.0, "saturation": 1.5}}, noise=np.zeros((64, 64), np.float32))
    assert np.unique(image).size <= 16 and image.max() == pytest.approx(1.5)


def test_sensor_blur_removes_high_frequencies_and_keeps_the_mean():
    particles = field(seed=2)
    sharp = simulate_hologram(particles, wavelength_um=0.66)
    blurred = sensor_image(sharp, NEUTRAL, {"sensor_blur": {"sigma_px": 1.5}}, noise=np.zeros_like(sharp))
    window = np.outer(np.hanning(64), np.hanning(64))  # no edge leakage
    high = lambda a: np.abs(np.fft.fft2((a - a.mean()) * window))[20:44, 20:44].sum()  # noqa: E731 - the highest frequencies
    assert high(blurred) < 0.2 * high(sharp) and blurred.mean() == pytest.approx(sharp.mean(), rel=1e-3)


def test_sensor_blur_acts_on_the_light_and_the_noise_added_after_it_stays_white():
    # crosstalk / MTF spreads the light; the read noise comes from the electronics afterwards
    from scipy import ndimage

    sharp = simulate_hologram(field((128, 128), count=6, seed=4), wavelength_um=0.66)
    noise = np.random.default_rng(5).standard_normal(sharp.shape).astype(np.float32)
    blur = {"sensor_blur": {"sigma_px": 1.5}}
    clean = sensor_image(sharp, NEUTRAL, blur, noise=np.zeros_like(sharp))
    np.testing.assert_allclose(clean, ndimage.gaussian_filter(sharp, 1.5), atol=1e-6)
    residual = sensor_image(sharp, {**NEUTRAL, "sigma": 0.05}, blur, noise=noise) - clean
    neighbours = np.corrcoef(residual[:, 1:].ravel(), residual[:, :-1].ravel())[0, 1]
    assert residual.std() == pytest.approx(0.05, rel=0.05) and abs(neighbours) < 0.05  # blurred noise: correlation 0.90


def test_transparent_spheres_conserve_light_where_opaque_discs_remove_it():
    from napari_lbs._core import ParticleField
    from napari_lbs._core.physics._synthesis import disc_coverage

    one = ParticleField(np.array([140.8]), np.array([140.8]), np.array([2000.0]), np.array([30.0]), (128, 128), 2.2)
    area = disc_coverage((128, 128), one.x_um, one.y_um, one.diameter_um, pixel_um=2.2).mean()
    opaque = optical_hologram(one, {}, wavelength_um=0.66)
    glass = optical_hologram(one, {"particle_phase": {"index_contrast": 0.0126, "transmission": 1.0}}, wavelength_um=0.66)
    # <|1 + s|²> = 1 - a for an opaque disc of area fraction a (extinction), 1 for a lossless sphere
    assert opaque.mean() == pytest.approx(1.0 - area, abs=0.1 * area)
    assert glass.mean() == pytest.approx(1.0, abs=0.1 * area)
    assert np.std(glass) > 0.01  # the phase still makes a hologram


def test_spherical_wave_magnifies_far_layers():
    from napari_lbs._core import ParticleField

    one = ParticleField(np.array([100.0]), np.array([70.4]), np.array([4000.0]), np.array([25.0]), (64, 64), 2.2)
    plane = optical_hologram(one, {}, wavelength_um=0.66)
    spherical = optical_hologram(one, {"spherical_wave": {"source_mm": 20.0}}, wavelength_um=0.66)
    # the shadow's centre moves away from the window centre by M = L / (L - z) = 1.25
    centre = lambda h: np.average(np.arange(64), weights=(1 - h).clip(0).sum(axis=0))  # noqa: E731
    assert centre(spherical) - 31.5 == pytest.approx(1.25 * (centre(plane) - 31.5), abs=1.0)


def test_shadowing_between_layers_grows_with_the_injection_density():
    effect = EFFECTS["multiple_scattering"]
    weak, strong = effect.injection_density
    assert 1.0 < weak < strong  # its strength is the scene's density, not a parameter

    def departure(count):
        # rms of layered minus additive superposition, averaged over 3 scenes of 128²
        fields = [field((128, 128), count=count, seed=seed) for seed in range(3)]
        return np.mean([np.std(optical_hologram(f, {"multiple_scattering": {"on": 1.0}}, wavelength_um=0.66) - optical_hologram(f, {}, wavelength_um=0.66)) for f in fields])

    # overlaps in projection grow with the density, and the departure from additivity with them
    # (measured: rms 0.050 at 12 per 128², 0.58 at 144)
    base, dense = departure(12), departure(round(12 * strong))
    assert dense > 3.0 * base
    assert departure(1) < 1e-3  # one particle: nothing to shadow


def test_a_dust_grains_fresnel_shadow_has_the_arago_spot_and_conserves_light():
    from napari_lbs._core.physics._effects import _dust_mask, _dust_pattern, _fresnel_intensity

    diffract = lambda opaque, zone_px: _fresnel_intensity(np.fft.fft2(opaque.astype(np.complex64)), zone_px)  # noqa: E731
    yy, xx = np.mgrid[-128:128, -128:128]
    grain = xx**2 + yy**2 <= 6**2  # an opaque disc, 6 px in radius
    np.testing.assert_allclose(diffract(grain, 0.01), 1.0 - grain, atol=1e-3)  # no distance: the geometric shadow
    for zone_px in (12.0, 25.0):
        far = diffract(grain, zone_px)
        # light is conserved (the propagation is unitary: mean |1 - mask|² = 1 - fill on the periodic grid)
        assert far.mean() == pytest.approx(1.0 - grain.mean(), rel=1e-4)
        # Poisson's (Arago's) spot: on the axis behind an opaque disc the light is back to the incident
        assert far[128, 128] == pytest.approx(1.0, abs=0.1)
    # the distance itself: on the axis behind a circular aperture of radius r, I = 4 sin²(π r² / 2N), N = zone²
    aperture = ~(xx**2 + yy**2 <= 20**2)  # opaque outside
    for zone_px in (10.0, 14.0, 20.0):
        expected = 4 * np.sin(np.pi * 20**2 / (2 * zone_px**2)) ** 2
        assert diffract(aperture, zone_px)[128, 128] == pytest.approx(expected, abs=0.15)
    # the catalog's dust: static, and more grains keep the fewer ones' places
    fewer, more = _dust_mask((256, 256), 10, 5), _dust_mask((256, 256), 20, 5)
    assert fewer.any() and np.all(more[fewer]) and more.sum() > fewer.sum()
    pattern = _dust_pattern((128, 128), 100.0, 20.0)
    assert pattern.std() > 0.01 and _dust_pattern((128, 128), 200.0, 20.0).std() > pattern.std()
    np.testing.assert_array_equal(pattern, _dust_pattern((128, 128), 100.0, 20.0))


def test_dust_on_a_window_is_part_of_the_static_fringes_and_optional_in_a_stated_setting():
    from napari_lbs._core.physics._effects import parse_effect

    etalon = parse_effect("parasitic_fringes:amplitude=0.05,period_px=10,angle_rad=0")["parasitic_fringes"]
    assert etalon["dust_per_mpx"] == 0.0  # left out: that part is off
    dusty = parse_effect("parasitic_fringes:amplitude=0,period_px=10,angle_rad=0,dust_per_mpx=150,dust_zone_px=25")["parasitic_fringes"]
    rng = np.random.default_rng(5)
    intensity = simulate_hologram(field((128, 128), count=4, seed=rng), wavelength_um=0.66)
    noise = np.zeros((128, 128), np.float32)
    clean = sensor_image(intensity, NEUTRAL, {"parasitic_fringes": etalon | {"amplitude": 0.0}}, noise=noise)
    np.testing.assert_allclose(clean, intensity, atol=1e-6)
    assert np.abs(sensor_image(intensity, NEUTRAL, {"parasitic_fringes": dusty}, noise=noise) - intensity).std() > 0.01
    dust_only = parse_effect("parasitic_fringes:dust_per_mpx=100,dust_zone_px=30,dust_grain_px=12")["parasitic_fringes"]
    assert dust_only["amplitude"] == 0.0 and dust_only["dust_grain_px"] == 12.0  # each part may be stated alone
    with pytest.raises(InputError, match="dust_size"):
        parse_effect("parasitic_fringes:dust_size=3")


def test_a_sources_bandwidth_washes_out_high_order_fringes_and_keeps_the_low_order_ones():
    from napari_lbs._core import ParticleField

    one = ParticleField(np.array([280.5]), np.array([280.5]), np.array([3000.0]), np.array([25.0]), (256, 256), 2.2)
    narrow = optical_hologram(one, {}, wavelength_um=0.66, periodic=True)
    broad = optical_hologram(one, {"coherence": {"theta_mrad": 0.0, "bandwidth_nm": 60.0}}, wavelength_um=0.66, periodic=True)
    y, x = np.mgrid[:256, :256] - 127.5
    r = np.hypot(x, y)
    inner, outer = r < 20, (r > 90) & (r < 120)  # fringe orders below 2, and 20-36
    # fringe order grows with r²: a spread of wavelengths dephases the outer rings, not the inner ones
    assert np.std((broad - 1)[outer]) < 0.7 * np.std((narrow - 1)[outer])
    assert np.std((broad - 1)[inner]) > 0.8 * np.std((narrow - 1)[inner])
    assert abs(float(broad.mean()) - float(narrow.mean())) < 0.01


def test_a_tile_sees_the_envelope_and_fringe_of_its_place_on_the_sensor():
    rng = np.random.default_rng(8)
    frame = 1.0 + 0.05 * rng.standard_normal((96, 128)).astype(np.float32)
    effects = {"illumination": {"depth": 0.5, "x0": 0.2, "y0": -0.1}, "parasitic_fringes": {"amplitude": 0.05, "period_px": 9.0, "angle_rad": 0.7}}
    noise = np.zeros_like(frame)
    whole = sensor_image(frame, NEUTRAL, effects, noise=noise)
    rows, cols = np.arange(40, 72), np.arange(64, 112)
    tile = sensor_image(frame[40:72, 64:112], NEUTRAL, effects, noise=noise[40:72, 64:112], frame_px=(rows, cols, frame.shape))
    np.testing.assert_allclose(tile, whole[40:72, 64:112], rtol=1e-5)


DUST = {**EFFECTS["parasitic_fringes"].neutral, "dust_per_mpx": 200.0, "dust_zone_px": 12.0}


@pytest.mark.parametrize("effects", [
    {"illumination": {"depth": 0.5, "waist": 0.5, "x0": 0.2, "y0": -0.1}, "parasitic_fringes": {"amplitude": 0.05, "period_px": 9.0, "angle_rad": 0.7}},
    {"illumination": {"depth": 0.3, "waist": 0.4, "x0": 0.0, "y0": 0.1}, "sensor_blur": {"sigma_px": 1.3}, "shot_noise": {"log10_photons": 3.0},
     "quantization": {"bits": 6.0, "saturation": 1.5}},
    {"parasitic_fringes": DUST},
    {"parasitic_fringes": DUST, "sensor_blur": {"sigma_px": 0.8}},
])
def test_the_kept_rows_and_columns_are_those_of_the_whole_image(effects):
    """``keep`` computes a part of the image, not an approximation of it: the same numbers, blur or none."""
    rng = np.random.default_rng(9)
    frame = 1.0 + 0.1 * rng.standard_normal((96, 130)).astype(np.float32)
    noise = rng.standard_normal(frame.shape).astype(np.float32)
    baseline = {**NEUTRAL, "contrast": 0.8, "gamma": 1.2, "sigma": 0.01}
    every_other = (slice(0, None, 2), slice(1, None, 2))
    whole = sensor_image(frame, baseline, effects, noise=noise)
    np.testing.assert_array_equal(sensor_image(frame, baseline, effects, noise=noise, keep=every_other), whole[every_other])


def test_the_spectral_average_of_the_interference_term_matches_an_average_over_wavelengths():
    from napari_lbs._core import ParticleField
    from napari_lbs._core.physics._optics import superpose
    from napari_lbs._core.physics._synthesis import layer_images

    one = ParticleField(np.array([280.5]), np.array([280.5]), np.array([3000.0]), np.array([25.0]), (256, 256), 2.2)
    depths, images = layer_images(one)
    fields = [-image for image in images]
    bandwidth_um, optics = 0.04, {"pixel_um": 2.2, "periodic": True}
    sigma = bandwidth_um / (2 * np.sqrt(2 * np.log(2)))
    wavelengths = 0.66 + np.linspace(-4, 4, 81) * sigma
    weights = np.exp(-0.5 * ((wavelengths - 0.66) / sigma) ** 2)
    brute = sum(w * superpose(fields, depths, wavelength_um=lam, **optics) for w, lam in zip(weights / weights.sum(), wavelengths, strict=True))
    averaged = superpose(fields, depths, wavelength_um=0.66, bandwidth_um=bandwidth_um, **optics)
    narrow = superpose(fields, depths, wavelength_um=0.66, **optics)
    assert np.sqrt(np.mean((averaged.real - brute.real) ** 2)) < 0.01 * np.sqrt(np.mean(narrow.real**2))
