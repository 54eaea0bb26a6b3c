"""Angular-spectrum propagation against analytic physics, each case with its stated tolerance."""

import numpy as np
import pytest
import scipy.fft

from napari_lbs._core import backpropagate, propagate
from napari_lbs._core.physics._optics import transfer_function
from napari_lbs._core.physics._synthesis import disc_coverage

PIXEL_UM = 2.2
WAVELENGTH_UM = 0.66


def grid_um(n, *, centre_px):
    axis = (np.arange(n) - centre_px) * PIXEL_UM
    return np.meshgrid(axis, axis, indexing="ij")


@pytest.mark.parametrize("z_um", [1800.0, 2000.0, 3300.0, 4800.0])
@pytest.mark.parametrize("radius_um", [12.5, 15.0])
def test_on_axis_aperture_and_disc_match_rayleigh_sommerfeld(z_um, radius_um):
    """Aperture: U(0,z) = e^{ikz} - (z/R) e^{ikR}; opaque disc (Babinet): |U|^2 = z^2/R^2.

    Tolerance 0.02 in intensity: the discs are sampled on 2.2 µm pixels (1/64 area steps).
    """
    n = 512
    coverage = disc_coverage((n, n), n // 2 * PIXEL_UM, n // 2 * PIXEL_UM, 2 * radius_um, pixel_um=PIXEL_UM).astype(np.float64)
    k = 2 * np.pi / WAVELENGTH_UM
    r = np.hypot(z_um, radius_um)
    aperture_exact = 1.0 - (z_um / r) * np.exp(1j * k * (r - z_um))  # carrier e^{ikz} removed
    aperture = propagate(coverage, z_um, wavelength_um=WAVELENGTH_UM, pixel_um=PIXEL_UM)[n // 2, n // 2]
    assert abs(aperture) ** 2 == pytest.approx(abs(aperture_exact) ** 2, abs=0.02)
    disc = propagate(1.0 - coverage, z_um, wavelength_um=WAVELENGTH_UM, pixel_um=PIXEL_UM)[n // 2, n // 2]
    assert abs(disc) ** 2 == pytest.approx((z_um / r) ** 2, abs=0.02)


def gaussian_beam(y, x, z_um, *, waist_um, wavelength_um):
    """Paraxial Gaussian beam relative to the carrier e^{ikz}, waist at z = 0, e^{-iωt} convention."""
    k = 2 * np.pi / wavelength_um
    z_r = np.pi * waist_um**2 / wavelength_um
    q = z_um - 1j * z_r  # complex beam parameter with the waist at 0
    return (-1j * z_r / q) * np.exp(1j * k * (x**2 + y**2) / (2 * q))


@pytest.mark.parametrize("z_um", [500.0, 2000.0, -2000.0])
def test_gaussian_beam_matches_paraxial_solution_and_pins_the_sign(z_um):
    """Complex field within 2e-3 of the paraxial beam (non-paraxial terms ~1e-4 here)."""
    n, waist = 512, 25.0
    y, x = grid_um(n, centre_px=n // 2)
    start = gaussian_beam(y, x, 0.0, waist_um=waist, wavelength_um=WAVELENGTH_UM)
    result = propagate(start.astype(np.complex128), z_um, wavelength_um=WAVELENGTH_UM, pixel_um=PIXEL_UM)
    expected = gaussian_beam(y, x, z_um, waist_um=waist, wavelength_um=WAVELENGTH_UM)
    assert np.max(np.abs(result - expected)) < 2e-3
    # A wrong sign would give the conjugate beam: converging instead of diverging.
    wrong = gaussian_beam(y, x, -z_um, waist_um=waist, wavelength_um=WAVELENGTH_UM)
    assert np.max(np.abs(result - wrong)) > 0.1


def test_composition_round_trip_and_energy():
    n = 256
    y, x = grid_um(n, centre_px=n / 2 - 0.3)
    start = gaussian_beam(y, x, -300.0, waist_um=15.0, wavelength_um=WAVELENGTH_UM)
    optics = {"wavelength_um": WAVELENGTH_UM, "pixel_um": PIXEL_UM}
    once = propagate(start, 700.0, **optics)
    twice = propagate(propagate(start, 300.0, **optics), 400.0, **optics)
    assert np.max(np.abs(once - twice)) < 1e-9  # complex128 composes to round-off
    back = propagate(once, -700.0, **optics)
    assert np.max(np.abs(back - start)) < 1e-9
    energy = np.sum(np.abs(start) ** 2)
    assert np.sum(np.abs(once) ** 2) == pytest.approx(energy, rel=1e-9)
    single = propagate(start.astype(np.complex64), 700.0, **optics)
    assert single.dtype == np.complex64
    assert np.max(np.abs(single - once)) < 2e-5  # complex64 with a float64-phase kernel


def test_evanescent_waves_are_dropped_not_amplified():
    rng = np.random.default_rng(0)
    noise = rng.normal(size=(128, 128)) + 1j * rng.normal(size=(128, 128))
    energy = np.sum(np.abs(noise) ** 2)
    for z in (-4800.0, 4800.0):
        out = propagate(noise, z, wavelength_um=0.5, pixel_um=0.2)  # pitch < λ/2: evanescent content exists
        assert np.sum(np.abs(out) ** 2) <= energy * (1 + 1e-9)


def test_kernel_phase_in_float32_storage_is_accurate():
    """The complex64 kernel's phase is within 1e-6 rad of the float64 one at 4.8 mm."""
    shape = (256, 256)
    k64 = transfer_function(shape, 4800.0, wavelength_um=WAVELENGTH_UM, pixel_um=PIXEL_UM, dtype=np.complex128)
    k32 = transfer_function(shape, 4800.0, wavelength_um=WAVELENGTH_UM, pixel_um=PIXEL_UM)
    lam = WAVELENGTH_UM
    fy = np.fft.fftfreq(256, PIXEL_UM)
    q = lam**2 * (fy[:, None] ** 2 + fy[None, :] ** 2)
    exact = 2 * np.pi * 4800.0 * (np.sqrt(1 - q) - 1) / lam
    assert np.max(np.abs(np.angle(k64 * np.exp(-1j * exact)))) < 1e-9
    assert np.max(np.abs(np.angle(k32 * np.exp(-1j * exact)))) < 1e-6
    assert np.array_equal(np.abs(k32) > 0, q <= 1)


@pytest.mark.parametrize("shape", [(9, 8), (8, 9), (65, 50)])
@pytest.mark.parametrize("spread_limit_um", [None, 2000.0])
def test_kernel_is_the_angular_spectrum_at_every_frequency_of_odd_even_and_unequal_grids(shape, spread_limit_um):
    """Negative frequencies included (the kernel is built on the non-negative quarter and mirrored):
    unit modulus with the phase within 1e-9 rad where light passes, zero where it is evanescent or
    beyond the band limit."""
    lam, pixel_um, z_um = 0.5, 0.2, -1234.5  # pitch < λ/2: evanescent frequencies exist
    kernel = transfer_function(shape, z_um, wavelength_um=lam, pixel_um=pixel_um, spread_limit_um=spread_limit_um, dtype=np.complex128, cache=False)
    fy, fx = np.fft.fftfreq(shape[0], pixel_um)[:, None], np.fft.fftfreq(shape[1], pixel_um)[None, :]
    q = lam**2 * (fy**2 + fx**2)
    passed = q <= 1
    if spread_limit_um is not None:
        limit = 1 / (lam * np.hypot(z_um / spread_limit_um, 1))
        passed &= (np.abs(fy) <= limit) & (np.abs(fx) <= limit)
    assert passed.any() and not passed.all()
    assert np.array_equal(kernel != 0, passed)
    exact = 2 * np.pi * z_um * (np.sqrt(1 - q[passed]) - 1) / lam
    assert np.allclose(np.abs(kernel[passed]), 1, atol=1e-12)
    assert np.max(np.abs(np.angle(kernel[passed] * np.exp(-1j * exact)))) < 1e-9


@pytest.mark.parametrize("z0_um", [2000.0, 4000.0])
def test_point_source_refocuses_at_its_depth_and_position(z0_um):
    """A Rayleigh–Sommerfeld point source at (row 130, col 121.0), depth z0 refocuses there.

    Depth within 3 µm (a stretched linspace grid puts it ~16 µm off at 2 mm); lateral
    centroid within 0.05 px (a half-bin grid shift moves it 0.33 px).
    """
    n = 256
    row0, col0 = 130.0, 121.0
    rows, cols = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    dy, dx = (rows - row0) * PIXEL_UM, (cols - col0) * PIXEL_UM
    k = 2 * np.pi / WAVELENGTH_UM
    r = np.sqrt(dx**2 + dy**2 + z0_um**2)
    field = z0_um / r * (1 / r - 1j * k) * np.exp(1j * k * (r - z0_um)) / (2 * np.pi * r)
    # Keep only angles the pixels sample without aliasing, with a smooth edge.
    sin_max = 0.9 * WAVELENGTH_UM / (2 * PIXEL_UM)
    rho = np.hypot(dx, dy) / r
    field *= np.clip((sin_max - rho) / (0.2 * sin_max), 0, 1) ** 2
    depths = z0_um + np.arange(-40.0, 40.5, 2.0)
    stack = np.abs(propagate(field, -depths, wavelength_um=WAVELENGTH_UM, pixel_um=PIXEL_UM)) ** 2
    peak = stack[:, int(row0), int(col0)]
    i = int(np.argmax(peak))
    assert 0 < i < depths.size - 1
    offset = 0.5 * (peak[i - 1] - peak[i + 1]) / (peak[i - 1] - 2 * peak[i] + peak[i + 1])
    assert depths[i] + 2.0 * offset == pytest.approx(z0_um, abs=3.0)
    focus = stack[i]
    window = focus[int(row0) - 3 : int(row0) + 4, int(col0) - 3 : int(col0) + 4]
    yy, xx = np.mgrid[-3:4, -3:4]
    assert np.sum(window * yy) / window.sum() == pytest.approx(0.0, abs=0.05)
    assert np.sum(window * xx) / window.sum() == pytest.approx(0.0, abs=0.05)


def test_backpropagation_refocuses_a_simulated_particle_dark_on_bright():
    from napari_lbs._core import ParticleField, simulate_hologram

    field = ParticleField(np.array([100 * PIXEL_UM]), np.array([90 * PIXEL_UM]), np.array([3000.0]), np.array([25.0]), (256, 256), PIXEL_UM)
    hologram = simulate_hologram(field, wavelength_um=WAVELENGTH_UM)
    depths = np.arange(2600.0, 3401.0, 50.0)
    stack = backpropagate(hologram, depths, wavelength_um=WAVELENGTH_UM, pixel_um=PIXEL_UM, background=np.ones_like(hologram))
    assert stack.dtype == np.float32
    window = stack[:, 75:106, 85:116]
    gradient_y, gradient_x = np.gradient(window, axis=(1, 2))
    sharpness = np.sum(gradient_y**2 + gradient_x**2, axis=(1, 2))
    # Sharpest edge within one 50 µm plane of the true depth (the twin image skews the focus curve).
    assert abs(depths[np.argmax(sharpness)] - 3000.0) <= 50.0
    focus = stack[np.argmin(np.abs(depths - 3000.0))]
    assert focus[90, 100] < 0.3  # opaque disc in focus: little light
    assert np.median(focus) == pytest.approx(1.0, abs=0.02)  # background stays at 1


def test_tile_at_the_edge_has_no_wrapped_fringes():
    """A particle 10 px from the left edge at 4.8 mm: the tile simulated alone equals the same
    region cut from a much larger simulation (exact linear convolution) to 1e-3 (corner frequencies band-limited slightly differently); an unpadded
    FFT wraps its fringes onto the right edge at the 1e-2 level."""
    from napari_lbs._core import ParticleField, simulate_hologram

    z, d = 4800.0, 30.0
    tile = ParticleField(np.array([10 * PIXEL_UM]), np.array([128 * PIXEL_UM]), np.array([z]), np.array([d]), (256, 256), PIXEL_UM)
    alone = simulate_hologram(tile, wavelength_um=WAVELENGTH_UM)
    big = ParticleField(np.array([(10 + 512) * PIXEL_UM]), np.array([(128 + 512) * PIXEL_UM]), np.array([z]), np.array([d]), (1280, 1280), PIXEL_UM)
    reference = simulate_hologram(big, wavelength_um=WAVELENGTH_UM)[512:768, 512:768]
    assert np.max(np.abs(alone - reference)) < 1e-3
    coverage = disc_coverage((256, 256), tile.x_um, tile.y_um, tile.diameter_um, pixel_um=PIXEL_UM)
    fx = np.fft.fftfreq(256, PIXEL_UM)
    q = WAVELENGTH_UM**2 * (fx[:, None] ** 2 + fx[None, :] ** 2)
    naive = np.abs(1 - scipy.fft.ifft2(scipy.fft.fft2(coverage) * np.exp(2j * np.pi * z * (np.sqrt(1 - q) - 1) / WAVELENGTH_UM))) ** 2
    assert np.max(np.abs(naive - reference)[:, 200:]) > 1e-2


def test_backpropagate_rejects_bad_input():
    from napari_lbs._core import InputError

    hologram = np.ones((64, 64), np.float32)
    with pytest.raises(InputError, match="hologram: expected a 2-D"):
        backpropagate(np.ones((2, 64, 64)), [2000.0], wavelength_um=0.66, pixel_um=2.2)
    with pytest.raises(InputError, match="NaN"):
        backpropagate(np.full((64, 64), np.nan), [2000.0], wavelength_um=0.66, pixel_um=2.2)
    with pytest.raises(InputError, match="background"):
        backpropagate(hologram, [2000.0], wavelength_um=0.66, pixel_um=2.2, background=np.zeros((64, 64)))
    with pytest.raises(InputError, match="z_um"):
        backpropagate(hologram, [], wavelength_um=0.66, pixel_um=2.2)


def test_stop_request_interrupts_between_batches():
    from napari_lbs._core import Stopped
    import napari_lbs._core.physics._optics as optics

    calls = []
    old = optics._WORKING_BYTES
    optics._WORKING_BYTES = 1  # one plane per batch
    try:
        with pytest.raises(Stopped):
            backpropagate(np.ones((64, 64), np.float32), np.arange(1800.0, 2300.0, 50.0), wavelength_um=0.66, pixel_um=2.2,
                          progress=lambda done, total: calls.append((done, total)), should_stop=lambda: len(calls) >= 3)
    finally:
        optics._WORKING_BYTES = old
    assert calls == [(1, 10), (2, 10), (3, 10)]
