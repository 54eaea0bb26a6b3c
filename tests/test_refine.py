"""Particle refinement: the Lorenz–Mie and disc forward models, and the fit of every detection."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch
from sphere_scenes import FAST, PIXEL_UM, WATER, WAVELENGTH_UM, default_config, guess_table, sphere_scene

from napari_lbs._core.physics._disc import disc_holograms
from napari_lbs._core.physics._lorenz_mie import mie_coefficients, sphere_fields, sphere_holograms, term_count


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def converged_pylorenzmie(monkeypatch):
    """pylorenzmie with its partial-wave sum carried far enough to converge.

    pylorenzmie 3.4.0 starts the downward recurrence of D_n(mx) at n = |mx|; for a
    non-absorbing sphere that leaves errors of order 1 in a_n (measured: d = 16 µm
    polystyrene in water, |Δa_n| up to 0.92). Forty more orders make its coefficients
    agree with the textbook formula (scipy's Bessel functions) to 1e-5.
    """
    theory = pytest.importorskip("pylorenzmie.theory")  # reason-ok: a test extra, installed by CI (.[test]); skipped only where a user left it out
    from pylorenzmie.theory.Instrument import Instrument

    stock = theory.Sphere.wiscombe_yang
    monkeypatch.setattr(theory.Sphere, "wiscombe_yang", staticmethod(lambda x, m: stock(x, m) + 40))
    return theory.LorenzMie, theory.Sphere, Instrument


def _grid(size, pixel_um, centre_px):
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    dx = torch.tensor(((cols - centre_px[0]) * pixel_um).ravel())[None]
    dy = torch.tensor(((rows - centre_px[1]) * pixel_um).ravel())[None]
    return dx, dy


@pytest.mark.parametrize(
    ("diameter_um", "z_um", "contrast", "absorption", "pixel_um", "size"),
    [
        (16.0, 2400.0, 0.26, 0.0, 2.2, 96),  # polystyrene in water, lensless, near the sensor
        (36.0, 6400.0, 0.26, 0.0, 2.2, 96),  # size parameter 228, far
        (25.0, 4000.0, 0.26, 0.02, 2.2, 96),  # absorbing
        (1.0, 15.0, 0.26, 0.0, 0.085, 96),  # through an objective: 1 µm at 15 µm, 0.085 µm pixels
    ],
)
def test_sphere_hologram_matches_pylorenzmie(converged_pylorenzmie, diameter_um, z_um, contrast, absorption, pixel_um, size):
    LorenzMie, Sphere, Instrument = converged_pylorenzmie
    centre = (size / 2 + 0.3, size / 2 - 0.2)
    instrument = Instrument(wavelength=WAVELENGTH_UM, magnification=pixel_um, n_m=WATER)
    sphere = Sphere(a_p=diameter_um / 2, n_p=WATER + contrast, k_p=absorption, x_p=centre[0], y_p=centre[1], z_p=z_um / pixel_um)
    reference = LorenzMie(coordinates=LorenzMie.meshgrid((size, size)), particle=sphere, instrument=instrument).hologram()
    dx, dy = _grid(size, pixel_um, centre)
    ours = sphere_holograms(dx, dy, *(torch.tensor([v]) for v in (z_um, diameter_um, contrast, absorption)), wavelength_um=WAVELENGTH_UM, medium_index=WATER)[0].numpy()
    relative_rms = np.sqrt(np.mean((ours - reference) ** 2)) / np.sqrt(np.mean((reference - 1.0) ** 2))
    assert relative_rms < 1e-3


def test_mie_coefficients_match_the_textbook_formula():
    """a_n, b_n against Bohren & Huffman Eq. 4.53 written with scipy's spherical Bessel functions."""
    from scipy.special import spherical_jn, spherical_yn

    x, m = 2 * np.pi * WATER / WAVELENGTH_UM * 8.0, 1.59 / WATER  # d = 16 µm polystyrene in water
    a, b = mie_coefficients(torch.tensor([x]), torch.tensor([complex(m)]), terms=term_count(x, m))
    for n in (1, 2, 40, 110):
        def psi(z, n=n):
            return z * spherical_jn(n, z)

        def dpsi(z, n=n):
            return spherical_jn(n, z) + z * spherical_jn(n, z, derivative=True)

        h = spherical_jn(n, x) + 1j * spherical_yn(n, x)
        xi, dxi = x * h, h + x * (spherical_jn(n, x, derivative=True) + 1j * spherical_yn(n, x, derivative=True))
        a_exact = (m * psi(m * x) * dpsi(x) - psi(x) * dpsi(m * x)) / (m * psi(m * x) * dxi - xi * dpsi(m * x))
        b_exact = (psi(m * x) * dpsi(x) - m * psi(x) * dpsi(m * x)) / (psi(m * x) * dxi - m * xi * dpsi(m * x))
        assert abs(complex(a[0, n - 1]) - a_exact) < 1e-4
        assert abs(complex(b[0, n - 1]) - b_exact) < 1e-4


def test_mie_coefficients_without_gradient_equal_the_differentiable_ones():
    """The numpy path (no gradient wanted) and the torch path (a gradient wanted) give the same a_n, b_n."""
    x = torch.tensor([30.0, 120.0, 228.0], dtype=torch.float64)
    m = torch.tensor([1.59 / WATER, (1.33 + 0.6 + 0.05j) / WATER, 1.2 + 0.0j], dtype=torch.complex128)
    terms = term_count(228.0 * 1.15, 1.0)
    fast = mie_coefficients(x, m, terms=terms)
    slow = mie_coefficients(x.clone().requires_grad_(True), m, terms=terms)
    assert slow[0].requires_grad and not fast[0].requires_grad
    for ours, theirs in zip(fast, slow, strict=True):
        assert torch.allclose(ours, theirs.detach(), rtol=1e-9, atol=1e-12)


def test_far_field_limit_is_the_amplitude_function():
    """Far away the field is ``cosθ S2(θ) e^{ik(r - z)} / (-ikr)`` along the polarisation (Bohren & Huffman Eq. 4.74)."""
    diameter, contrast, z = 5.0, 0.26, 2.0e7
    k = 2 * np.pi * WATER / WAVELENGTH_UM
    x, m = k * diameter / 2, (WATER + contrast) / WATER
    terms = term_count(x, m)
    a, b = (c[0].numpy() for c in mie_coefficients(torch.tensor([x]), torch.tensor([complex(m)]), terms=terms))
    theta = np.array([0.0, 0.02, 0.05, 0.1])
    rho = z * np.tan(theta)
    # angular functions by their defining recurrence (Bohren & Huffman Eq. 4.47)
    mu = np.cos(theta)
    pi_prev, pi_n, s2 = np.zeros_like(mu), np.ones_like(mu), np.zeros(theta.size, complex)
    for n in range(1, terms + 1):
        tau = n * mu * pi_n - (n + 1) * pi_prev
        s2 += (2 * n + 1) / (n * (n + 1)) * (a[n - 1] * tau + b[n - 1] * pi_n)
        pi_prev, pi_n = pi_n, ((2 * n + 1) * mu * pi_n - (n + 1) * pi_prev) / n
    r = np.hypot(rho, z)
    expected = np.cos(theta) * s2 * np.exp(1j * k * (r - z)) / (-1j * k * r)
    ex, _, _ = sphere_fields(torch.tensor(rho)[None], torch.zeros(1, theta.size, dtype=torch.float64), torch.tensor([z]), torch.tensor([diameter]),
                             torch.tensor([contrast]), torch.tensor([0.0]), wavelength_um=WAVELENGTH_UM, medium_index=WATER)
    assert np.allclose(ex[0].numpy(), expected, rtol=1e-4, atol=1e-4 * abs(expected[0]))


@pytest.mark.parametrize("pixel_um", [None, 2.2])
def test_azimuthal_moments_match_the_hologram_averaged_over_the_azimuth(pixel_um):
    """``⟨I⟩`` and ``⟨I cos2φ⟩`` of the ring model against `sphere_holograms` on 720 azimuths per radius (absorbing, so C and Q matter)."""
    import math

    from napari_lbs._core.physics._lorenz_mie import azimuthal_mean_holograms

    z, d, contrast, kappa = 1800.0, 24.0, 0.26, 0.02
    rho = torch.linspace(0.5, 160.0, 48, dtype=torch.float64)
    phi = (torch.arange(720, dtype=torch.float64) + 0.5) * 2 * math.pi / 720
    dx = (rho[:, None] * torch.cos(phi)).reshape(1, -1)
    dy = (rho[:, None] * torch.sin(phi)).reshape(1, -1)
    plane = sphere_holograms(dx, dy, *(torch.tensor([v]) for v in (z, d, contrast, kappa)), wavelength_um=WAVELENGTH_UM, medium_index=WATER,
                             pixel_um=pixel_um, radial_step_um=torch.tensor([0.05])).reshape(48, 720)
    ring = azimuthal_mean_holograms(torch.tensor([z]), torch.tensor([[d]]), torch.tensor([[contrast]]), torch.tensor([[kappa]]), rho[None],
                                    wavelength_um=WAVELENGTH_UM, medium_index=WATER, pixel_um=pixel_um)[0, 0]
    assert float((ring[:, 0] - plane.mean(dim=1)).abs().max()) < 1e-8
    second = (plane * torch.cos(2 * phi)).mean(dim=1)
    assert float(second.abs().max()) > 1e-5  # the second harmonic is there to be matched
    assert float((ring[:, 1] - second).abs().max()) < 1e-8


def test_ring_moments_through_the_coarse_radial_grid_match_the_direct_sums():
    """Summing A, B, C on 6 samples per lobe and interpolating them to 1-pixel rings changes the ring moments by < 1e-3 of the modulation.

    An 8-bit camera's rounding alone is 1/256 of its range, four times that.
    """
    import math

    from napari_lbs._core.physics._lorenz_mie import mean_intensity, weighted_coefficients, mie_coefficients, term_count

    k = 2 * math.pi * WATER / WAVELENGTH_UM
    diameters = torch.tensor([33.0, 34.0, 35.0], dtype=torch.float64)
    a, b = mie_coefficients(k * diameters / 2, torch.full((3,), (WATER + 0.26 + 0.001j) / WATER, dtype=torch.complex128),
                            terms=term_count(k * 35.0 / 2 * 1.15, 1.0))
    a_eff, b_eff = (c.reshape(1, 1, 3, -1) for c in weighted_coefficients(a, b))
    z = torch.tensor([[2500.0, 2520.0]], dtype=torch.float64)
    rho = ((torch.arange(90, dtype=torch.float64) + 0.5) * PIXEL_UM)[None, None, :].expand(1, 2, -1)
    direct = mean_intensity(a_eff, b_eff, z, rho, k=k, pixel_um=PIXEL_UM, annulus_um=PIXEL_UM)
    coarse = mean_intensity(a_eff, b_eff, z, rho, k=k, pixel_um=PIXEL_UM, annulus_um=PIXEL_UM, lobe_diameter_um=torch.full((1, 2), 35.0))
    modulation = float((direct[..., 0] - 1.0).abs().max())
    assert modulation > 0.1
    assert float((coarse - direct).abs().max()) < 1e-3 * modulation


def test_valley_interval_widens_with_the_rings_unexplained_chi_square():
    """The profile's interval reaches as far as the cost stays within Δχ² = 4 plus the excess χ² of the minimum, in the valley and across."""
    from napari_lbs._core.refine import _valley

    diameters = torch.linspace(29.0, 31.0, 41, dtype=torch.float64)[None]  # 0.05 µm apart
    contrast = torch.stack([torch.full((41,), 0.26 + j * 0.022, dtype=torch.float64) for j in (-1, 0, 1)], dim=-1)[None]
    offset = (diameters[0] - 30.0)[:, None] / 0.1  # half-variances rise as (Δd / 0.1 µm)²
    cost = (offset**2 + torch.tensor([30.0, 0.0, 30.0], dtype=torch.float64))[None]
    for minimum, reach_d, across in ((100.0, 0.15, False), (140.0, 0.65, True)):  # dof 200: excess 0 and 40
        profile = _valley._Profile(diameters, contrast, torch.zeros_like(cost), cost + minimum, torch.ones(1, dtype=torch.float64), torch.tensor([200.0]))
        threshold = _valley.interval_threshold(profile, torch.ones(1, dtype=torch.float64))
        assert float(threshold[0]) == _valley._INTERVAL + max(minimum - 100.0, 0.0)
        spread = _valley.profile_spread(profile, torch.tensor([30.0], dtype=torch.float64), torch.tensor([0.26], dtype=torch.float64), threshold)
        assert abs(2.0 * float(spread[0, 0]) - reach_d) < 0.03
        assert (float(spread[0, 1]) > 0.01) == across  # the neighbouring valleys only within the wider interval


def test_symmetric_centre_is_found_within_a_tenth_of_a_pixel():
    from napari_lbs._core.refine import _levenberg_marquardt, _patches, _rings

    truth = (36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 900.0, 18.0)
    hologram = sphere_scene([truth])
    guess_x, guess_y = np.array([truth[0] + 1.9]), np.array([truth[1] - 1.4])
    patches = _patches.cut_patches(hologram, guess_x, guess_y, np.array([48]), pixel_um=PIXEL_UM, device="cpu")
    residual, _, _ = _levenberg_marquardt.flat_model(patches)
    x, y = _rings.symmetric_centres(residual, patches, guess_x, guess_y, pixel_um=PIXEL_UM)
    assert abs(x[0] - truth[0]) < 0.1 * PIXEL_UM and abs(y[0] - truth[1]) < 0.1 * PIXEL_UM


def test_opaque_disc_matches_the_angular_spectrum_simulator():
    from napari_lbs._core.physics._synthesis import ParticleField, simulate_hologram

    pixel, size, z, diameter = 2.2, 128, 2000.0, 25.0
    centre = (63.3, 64.6)
    field = ParticleField(np.array([centre[0] * pixel]), np.array([centre[1] * pixel]), np.array([z]), np.array([diameter]), (size, size), pixel)
    simulated = simulate_hologram(field, wavelength_um=WAVELENGTH_UM)
    ours = disc_holograms(torch.tensor([centre[0]]), torch.tensor([centre[1]]), torch.tensor([z]), torch.tensor([diameter]), shape=(size, size),
                          wavelength_um=WAVELENGTH_UM, pixel_um=pixel)[0].numpy()
    inner = (slice(24, 104), slice(24, 104))
    assert np.sqrt(np.mean((ours[inner] - simulated[inner]) ** 2)) < 0.01
    assert np.corrcoef(ours[inner].ravel(), simulated[inner].ravel())[0, 1] > 0.995


def test_forward_models_are_differentiable_in_every_parameter():
    params = [torch.tensor([v], dtype=torch.float64, requires_grad=True) for v in (3000.0, 25.0, 0.26, 0.01)]
    dx, dy = _grid(24, 2.2, (12.3, 11.8))
    sphere_holograms(dx, dy, *params, wavelength_um=WAVELENGTH_UM, medium_index=WATER, pixel_um=2.2).sum().backward()
    assert all(torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0 for p in params)
    disc = [torch.tensor([v], dtype=torch.float64, requires_grad=True) for v in (15.2, 16.7, 2000.0, 25.0)]
    disc_holograms(*disc, shape=(32, 32), wavelength_um=WAVELENGTH_UM, pixel_um=2.2).var().backward()
    assert all(torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0 for p in disc)



def test_radial_interpolation_is_differentiable_in_the_profiles_and_the_radii():
    """The sparse Catmull–Rom product passes torch's numerical gradient check in its table and its positions."""
    from napari_lbs._core.physics._interpolation import CatmullRom

    generator = torch.Generator().manual_seed(0)
    table = torch.randn(2, 12, 4, dtype=torch.float64, generator=generator, requires_grad=True)
    position = (torch.rand(2, 30, dtype=torch.float64, generator=generator) * 8 + 1.5).requires_grad_(True)
    assert torch.autograd.gradcheck(CatmullRom.apply, (table, position))


@pytest.mark.parametrize("pixel_um", [None, 2.2])
def test_lateral_derivatives_match_central_differences(pixel_um):
    """The analytic ∂I/∂x, ∂I/∂y (a neighbour's field added) agree with central differences of the hologram to 1e-6 of their scale."""
    from napari_lbs._core.physics._lorenz_mie import fields_from_profiles, holograms_from_fields, lateral_derivatives, radial_profiles

    optics = {"wavelength_um": WAVELENGTH_UM, "medium_index": WATER}
    dx, dy = _grid(40, 2.2, (19.6, 20.3))
    z, spheres = torch.tensor([2600.0, 4100.0], dtype=torch.float64), [torch.tensor(v, dtype=torch.float64) for v in ([24.0, 31.0], [0.26, 0.1], [0.0, 0.02])]
    dx, dy = dx.expand(2, -1), dy.expand(2, -1)
    profiles, step = radial_profiles(z, *spheres, rho_max_um=float(torch.sqrt(dx**2 + dy**2).max()) + 1.0, **optics)
    others = tuple(0.05 * torch.polar(torch.ones_like(dx), 0.3 * dx + 0.1 * dy * (1 + axis)) for axis in range(3))

    def hologram(shift_x, shift_y):
        fields = fields_from_profiles(profiles, step, dx + shift_x, dy + shift_y, z, **optics)
        own = holograms_from_fields(fields, dx + shift_x, dy + shift_y, z, pixel_um=pixel_um, **optics)
        return own + 2.0 * sum((f * o.conj()).real for f, o in zip(fields, others, strict=True))

    along_x, along_y = lateral_derivatives(profiles, step, dx, dy, z, others=others, pixel_um=pixel_um, **optics)
    h = 1e-4
    numeric_x = (hologram(h, 0.0) - hologram(-h, 0.0)) / (2 * h)
    numeric_y = (hologram(0.0, h) - hologram(0.0, -h)) / (2 * h)
    scale = float(numeric_x.abs().max())
    assert scale > 1e-3
    assert float((along_x - numeric_x).abs().max()) < 1e-6 * scale
    assert float((along_y - numeric_y).abs().max()) < 1e-6 * scale


# --- the fit ------------------------------------------------------------------------------------

def test_coarse_patches_are_every_other_row_and_column_of_the_full_ones():
    """Patches cut at the image's edges too: the coarse pixels are the full patch's [::2, ::2], the padding masked."""
    from napari_lbs._core.refine import _patches

    image = np.random.default_rng(1).random((90, 70))
    x_um, y_um, edges = np.array([10.0, 80.0, 150.0]), np.array([5.0, 100.0, 190.0]), np.array([40, 33, 48])
    fine = _patches.cut_patches(image, x_um, y_um, edges, pixel_um=PIXEL_UM, device="cpu")
    coarse, _ = _patches.every_other_pixel(fine)
    for i, (rows, cols) in enumerate(fine.shape):
        block = fine.data[i, : rows * cols].reshape(rows, cols)[::2, ::2]
        assert coarse.shape[i] == tuple(block.shape)
        assert torch.equal(coarse.data[i, : block.numel()], block.reshape(-1))
        assert float(coarse.mask[i].sum()) == block.numel()
        assert torch.equal(coarse.x_um[i, : block.numel()], fine.x_um[i, : rows * cols].reshape(rows, cols)[::2, ::2].reshape(-1))

def test_fit_recovers_depth_size_and_index_from_offset_starts():
    from napari_lbs._core import RefineSettings, refine_particles

    truth = (36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 900.0, 18.0)
    hologram = sphere_scene([truth])
    start = guess_table([(truth[0] + 1.2, truth[1] - 0.9, truth[2] + 60.0, truth[3] + 0.6)])
    start["score"] = 0.7
    out = refine_particles(hologram, start, default_config(), fixed={"absorption": 0.0}, settings=RefineSettings(**FAST))
    assert list(out.columns[:11]) == ["x_um", "y_um", "z_um", "diameter_um", "index_contrast", "absorption", "z_err_um", "diameter_err_um", "index_err",
                                      "fit_residual", "refined"]
    assert "score" in out.columns and len(out) == 1 and bool(out.refined[0])
    assert abs(out.z_um[0] - truth[2]) < 2.0
    assert abs(out.diameter_um[0] - truth[3]) < 0.3
    assert abs(out.index_contrast[0] - 0.26) < 0.01
    assert abs(out.x_um[0] - truth[0]) < 0.2 and abs(out.y_um[0] - truth[1]) < 0.2
    assert out.z_err_um[0] > 0 and out.diameter_err_um[0] > 0 and out.index_err[0] > 0
    assert bool(out.outside_training[0])  # 18 µm: below the config's 20-30 µm


def test_fixed_parameters_stay_put():
    from napari_lbs._core import RefineSettings, refine_particles

    truth = (36.0 * PIXEL_UM, 36.0 * PIXEL_UM, 900.0, 18.0)
    out = refine_particles(sphere_scene([truth]), guess_table([(truth[0], truth[1], truth[2] + 20.0, 18.0)]), default_config(), fixed={"index_contrast": 0.26, "diameter_um": 18.0},
                           settings=RefineSettings(**{**FAST, "rounds": 1}))
    assert out.index_contrast[0] == 0.26 and out.diameter_um[0] == 18.0 and out.index_err[0] == 0.0
    assert abs(out.z_um[0] - truth[2]) < 2.0


@pytest.mark.parametrize("rounds", [1, 2])
def test_two_overlapping_particles_are_both_recovered(rounds):
    """One round (each with the other at its guess): within the reported 2σ; a second (with the other's fit): within 3 µm in depth."""
    from napari_lbs._core import RefineSettings, refine_particles

    truths = [(30.2 * PIXEL_UM, 33.7 * PIXEL_UM, 850.0, 17.0), (44.6 * PIXEL_UM, 39.1 * PIXEL_UM, 1000.0, 19.0)]
    starts = guess_table([(x + 0.8, y - 0.6, z - 40.0, d - 0.5) for x, y, z, d in truths])
    out = refine_particles(sphere_scene(truths, (80, 80)), starts, default_config(), fixed={"absorption": 0.0, "index_contrast": 0.26},
                           settings=RefineSettings(**FAST, rounds=rounds))
    assert len(out) == 2
    for row, (x, y, z, d) in zip(out.itertuples(), truths, strict=True):
        assert abs(row.z_um - z) < (3.0 if rounds == 2 else 2.0 * row.z_err_um) and abs(row.diameter_um - d) < 0.4 and abs(row.x_um - x) < 0.4


def test_worker_processes_give_the_same_table_report_progress_and_stop_at_once():
    """Batches fitted in two spawned processes: the same table bit for bit every run, as in one process and in a pool kept across calls; progress at least every second, a stop within 2 s."""
    import multiprocessing
    import time

    from napari_lbs._core import RefineSettings, Stopped, refine_particles
    from napari_lbs._core.foundation import WorkerPool

    truths = [(30.2 * PIXEL_UM, 33.7 * PIXEL_UM, 850.0, 17.0), (44.6 * PIXEL_UM, 39.1 * PIXEL_UM, 1000.0, 19.0)]
    hologram = sphere_scene(truths, (80, 80))
    starts = guess_table([(x + 0.8, y - 0.6, z - 40.0, d - 0.5) for x, y, z, d in truths])
    settings = {**FAST, "batch": 1, "rounds": 2}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as each worker runs
    try:
        alone = refine_particles(hologram, starts, default_config(), fixed={"absorption": 0.0}, settings=RefineSettings(**settings))
    finally:
        torch.set_num_threads(threads)
    calls = []
    pooled = refine_particles(hologram, starts, default_config(), fixed={"absorption": 0.0}, settings=RefineSettings(**settings, workers=2),
                              progress=lambda done, total: calls.append((time.perf_counter(), done, total)))
    again = refine_particles(hologram, starts, default_config(), fixed={"absorption": 0.0}, settings=RefineSettings(**settings, workers=2))
    # run after run, and against one process on one thread: bit for bit
    pd.testing.assert_frame_equal(pooled, again, check_exact=True)
    pd.testing.assert_frame_equal(pooled, alone, check_exact=True)
    # a pool the caller keeps: its processes start once and fit both calls, the same table again
    with WorkerPool(2) as pool:
        kept = [refine_particles(hologram, starts, default_config(), fixed={"absorption": 0.0}, settings=RefineSettings(**settings), pool=pool)
                for _ in range(2)]
        processes = [set(pool._executor._processes)]
        refine_particles(hologram, starts.iloc[:1], default_config(), fixed={"absorption": 0.0}, settings=RefineSettings(**settings), pool=pool)
        processes.append(set(pool._executor._processes))
    assert len(processes[0]) == 2 and processes[0] == processes[1] and not multiprocessing.active_children()
    for table in kept:
        pd.testing.assert_frame_equal(table, alone, check_exact=True)
    assert len(pooled) == 2
    times = [t for t, _, _ in calls]
    assert calls[-1][1:] == (6, 6) and max(np.diff(times)) < 1.0  # two batches in each of two rounds and the small spheres' retry
    asked = []

    def stop_soon() -> bool:
        asked.append(time.perf_counter())
        return len(asked) > 3  # after the workers started fitting

    with pytest.raises(Stopped):
        refine_particles(hologram, starts, default_config(), settings=RefineSettings(**settings, workers=2), should_stop=stop_soon)
    assert time.perf_counter() - asked[-1] < 2.0
    # every worker gone within the 2 s too (a process ended is reaped by active_children itself)
    while multiprocessing.active_children() and time.perf_counter() < asked[-1] + 2.0:
        time.sleep(0.05)
    assert not multiprocessing.active_children()


def test_the_model_without_the_particle_rounds_the_same_wherever_its_buffers_lie():
    """The illumination's least squares gives the same bits for the same patches, whatever memory they were copied to (LAPACK's does not)."""
    from napari_lbs._core.refine import _levenberg_marquardt, _patches

    image = np.random.default_rng(3).random((200, 200))
    patches = _patches.cut_patches(image, np.arange(16) * 6.0 + 20.0, np.arange(16) * 5.0 + 30.0, np.full(16, 60), pixel_um=PIXEL_UM, device="cpu")
    first = _levenberg_marquardt.flat_model(patches)
    spacers = []
    for size in range(1, 40):
        spacers.append(torch.empty(size, dtype=torch.float64))  # each copy lands at another alignment
        copy = _patches.Patches(*(t.clone() if isinstance(t, torch.Tensor) else t for t in vars(patches).values()))
        for expected, got in zip(first, _levenberg_marquardt.flat_model(copy)):
            assert torch.equal(expected, got)


def test_steps_longer_than_the_heartbeat_report_the_count_again_when_checked():
    """Refinement's batches take seconds in one process: `Steps.check` repeats the count once a heartbeat is due, not more often."""
    import time

    from napari_lbs._core.foundation._progress import Steps

    calls = []
    steps = Steps(3, progress=lambda done, total: calls.append((done, total)), should_stop=None, heartbeat_s=0.05)
    steps.check()
    assert calls == []
    time.sleep(0.06)
    steps.check()
    steps.check()
    assert calls == [(0, 3)]
    steps.advance()
    time.sleep(0.03)
    steps.check()
    assert calls == [(0, 3), (1, 3)]


def test_a_detection_on_an_empty_patch_is_dropped():
    from napari_lbs._core import RefineSettings, refine_particles

    truth = (20.0 * PIXEL_UM, 20.0 * PIXEL_UM, 900.0, 18.0)
    hologram = sphere_scene([truth], (64, 140))
    starts = guess_table([truth, (110.0 * PIXEL_UM, 30.0 * PIXEL_UM, 1000.0, 20.0)])  # the second sees only noise
    out = refine_particles(hologram, starts, default_config(), fixed={"absorption": 0.0}, settings=RefineSettings(**{**FAST, "rounds": 1}))
    assert len(out) == 1 and abs(out.x_um[0] - truth[0]) < 0.5


@pytest.mark.parametrize(("hologram", "culprit"), [(np.zeros((40, 40)), "hologram"), (np.full((40, 40), np.nan), "hologram"), (np.ones(40), "hologram")])
def test_bad_holograms_are_refused_in_one_line(hologram, culprit):
    from napari_lbs._core import InputError, refine_particles

    with pytest.raises(InputError) as error:
        refine_particles(hologram, guess_table([(40.0, 40.0, 900.0, 18.0)]), default_config())
    assert str(error.value).startswith(culprit) and "\n" not in str(error.value)


@pytest.mark.parametrize(("change", "culprit"), [({"z_um": [np.nan]}, "z_um"), ({"diameter_um": [-1.0]}, "diameter_um")])
def test_bad_tables_and_fixed_names_are_refused_in_one_line(change, culprit):
    from napari_lbs._core import InputError, refine_particles

    table = guess_table([(40.0, 40.0, 900.0, 18.0)])
    for name, values in change.items():
        table[name] = values
    with pytest.raises(InputError, match=culprit):
        refine_particles(np.ones((40, 40)), table, default_config())
    with pytest.raises(InputError, match="radius"):
        refine_particles(np.ones((40, 40)), guess_table([(40.0, 40.0, 900.0, 18.0)]), default_config(), fixed={"radius": 1.0})


@pytest.mark.parametrize(("settings", "fixed", "culprit"), [({"index_contrast": 3.0}, None, "refine settings: index_contrast"),
                                                       ({"absorption": -0.1}, None, "refine settings: absorption"),
                                                       ({"index_contrast": float("nan")}, None, "refine settings: index_contrast"),
                                                       ({}, {"index_contrast": -1.2}, "fixed: index_contrast"),
                                                       ({}, {"diameter_um": 0.0}, "fixed: diameter_um")])
def test_starts_and_fixed_values_outside_the_fits_range_are_refused_in_one_line(settings, fixed, culprit):
    from napari_lbs._core import InputError, RefineSettings, refine_particles

    with pytest.raises(InputError) as error:
        refine_particles(np.ones((40, 40)), guess_table([(40.0, 40.0, 900.0, 18.0)]), default_config(), fixed=fixed, settings=RefineSettings(**settings))
    assert str(error.value).startswith(culprit) and "fit's range" in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize("flags", [["--refine"], ["--material", "0.26"]])
def test_predict_refine_writes_the_refined_columns(tmp_path, monkeypatch, flags):
    """``napari-lbs predict --refine``: the network's table refined, the contract's columns after the first four (the network stubbed).

    ``--material`` refines too, starting every fit at that index contrast, and records the
    gate in the provenance (this polystyrene sphere is of the material 0.26).
    """
    import tifffile

    from napari_lbs import _cli
    from napari_lbs._core.learning import _network
    from napari_lbs._core.learning import _prediction
    from napari_lbs._core.foundation._io import read_particles

    truth = (36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 900.0, 18.0)
    tifffile.imwrite(tmp_path / "holo.tif", sphere_scene([truth]).astype(np.float32))
    guesses = {"x_um": np.array([truth[0] + 1.0]), "y_um": np.array([truth[1]]), "z_um": np.array([930.0]), "diameter_um": np.array([18.4]),
               "score": np.array([0.8]), "planes": np.array([3.0])}

    class Model:
        config = default_config()
        meta = {"threshold": 0.5}

    thresholds = []
    monkeypatch.setattr(_network, "load_model", lambda *a, **k: Model())
    monkeypatch.setattr(_prediction, "predict_particles",
                        lambda *a, **k: thresholds.append(k["settings"].threshold) or _prediction.PredictionResult(guesses, {"model_sha256": "stub"}, 0.1))
    from napari_lbs._core.refine import _refine

    made, settings = [], _refine.RefineSettings
    class Recorded(settings):  # a RefineSettings (the fit checks its type) made fast, its options recorded
        def __init__(self, **options):
            made.append(options)
            super().__init__(**{**FAST, **options})

    monkeypatch.setattr(_refine, "RefineSettings", Recorded)
    assert _cli.main(["predict", str(tmp_path / "holo.tif"), "--model", str(tmp_path / "model.pt"), "--out", str(tmp_path / "p.csv"), *flags,
                      "--device", "cpu"]) == 0
    from napari_lbs._core.foundation._threads import available_threads

    material = {"index_contrast": 0.26} if "--material" in flags else {}
    # the fit runs where the prediction did, a process per core, over the refine command's depth window, with the network's
    # validated depth error as its depth prior (this model's file records none) (later: copies the fit makes)
    assert made[0] == {"device": "cpu", "workers": available_threads(), "depth_window_um": 400.0, "depth_prior_um": 0.0, **material}
    # the network proposes down to 0.8 of its threshold (the fit checks them), then again in
    # the refined table's residual, where the stub's same guess finds nothing more
    assert thresholds == [0.4, 0.4]
    header = (tmp_path / "p.csv").read_text().splitlines()[0].split(",")
    assert header[:12] == ["x_um", "y_um", "z_um", "diameter_um", "index_contrast", "absorption", "z_err_um", "diameter_err_um", "index_err", "fit_residual",
                           "refined", "outside_training"]
    assert "score" in header
    table, record = read_particles(tmp_path / "p.csv"), json.loads((tmp_path / "p.json").read_text())["refine"]
    assert len(table["x_um"]) == 1 and abs(table["z_um"][0] - truth[2]) < 3.0 and abs(table["index_contrast"][0] - 0.26) < 0.02
    assert record.get("material", {}).get("other_material") == (0 if material else None)
    assert record["residual"]["proposals"] == 1 and record["residual"]["found"] == 0


def test_predict_material_refines_every_frame_of_a_recording(tmp_path, monkeypatch):
    """A recording's rows are refined on their own frame; the material's gate adds up over the frames (the network stubbed)."""
    import tifffile

    from napari_lbs import _cli
    from napari_lbs._core.learning import _network
    from napari_lbs._core.learning import _prediction
    from napari_lbs._core.refine import _refine
    from napari_lbs._core.recordings import _sequence
    from napari_lbs._core.foundation._io import read_particles

    spheres = [(36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 900.0, 18.0), (34.8 * PIXEL_UM, 37.1 * PIXEL_UM, 880.0, 18.0)]  # the sphere in frame 0, then 1
    tifffile.imwrite(tmp_path / "rec.tif", np.stack([sphere_scene([sphere], seed=i) for i, sphere in enumerate(spheres)]).astype(np.float32))
    guesses = {"x_um": np.array([s[0] + 1.0 for s in spheres]), "y_um": np.array([s[1] for s in spheres]), "z_um": np.array([930.0, 910.0]),
               "diameter_um": np.array([18.4, 18.4]), "score": np.array([0.8, 0.8]), "frame": np.array([0, 1])}

    class Model:
        config = default_config()
        meta = {"threshold": 0.5}

    def sequence(frames, model, config, **options):
        options["work_dir"].mkdir()
        return _sequence.SequenceResult(guesses, {"frames": 2, "scheduler": "stub", "model_sha256": "stub"}, 0.1, 0)

    monkeypatch.setattr(_network, "load_model", lambda *a, **k: Model())
    monkeypatch.setattr(_sequence, "predict_sequence", sequence)
    # the second look, in each frame's residual: the first frame's guess again, explained there already
    first = {name: values[:1] for name, values in guesses.items() if name != "frame"}
    monkeypatch.setattr(_prediction, "predict_particles", lambda *a, **k: _prediction.PredictionResult(first, {"model_sha256": "stub"}, 0.1))
    settings = _refine.RefineSettings
    class Fast(settings):  # a RefineSettings (the fit checks its type) made fast
        def __init__(self, **options):
            super().__init__(**{**FAST, **options})

    monkeypatch.setattr(_refine, "RefineSettings", Fast)
    assert _cli.main(["predict", str(tmp_path / "rec.tif"), "--model", "m.pt", "--out", str(tmp_path / "p.csv"), "--material", "0.26", "--device", "cpu"]) == 0
    table, record = read_particles(tmp_path / "p.csv"), json.loads((tmp_path / "p.json").read_text())["refine"]
    assert table["frame"].tolist() == [0, 1] and np.allclose(table["z_um"], [900.0, 880.0], atol=3.0)
    assert record["detections"] == 2 and record["kept"] == 2 and record["material"]["other_material"] == 0 and record["material"]["index_contrast"] == 0.26
    assert record["residual"]["proposals"] == 2 and record["residual"]["found"] == 0


@pytest.mark.parametrize("offset_um", [300.0, -300.0])
def test_a_depth_300_um_off_is_recovered_by_the_depth_scan(offset_um):
    from napari_lbs._core import RefineSettings, refine_particles

    truth = (36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 1500.0, 22.0)
    start = guess_table([(truth[0] + 1.0, truth[1] - 0.8, truth[2] + offset_um, truth[3] + 0.8)])
    out = refine_particles(sphere_scene([truth]), start, default_config(), fixed={"absorption": 0.0, "index_contrast": 0.26},
                           settings=RefineSettings(**{**FAST, "depth_window_um": 400.0}))
    assert abs(out.z_um[0] - truth[2]) < 2.0 and abs(out.diameter_um[0] - truth[3]) < 0.3


def test_a_depth_shifted_twin_is_merged_into_its_particle():
    from napari_lbs._core import RefineSettings, refine_particles

    truth = (36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 1500.0, 22.0)
    starts = guess_table([(truth[0] + 0.5, truth[1], truth[2] + 10.0, 22.5), (truth[0] - 0.5, truth[1] + 0.4, truth[2] + 300.0, 21.5)])
    out = refine_particles(sphere_scene([truth]), starts, default_config(), fixed={"absorption": 0.0, "index_contrast": 0.26},
                           settings=RefineSettings(**{**FAST, "depth_window_um": 400.0, "rounds": 1}))
    assert len(out) == 1 and abs(out.z_um[0] - truth[2]) < 2.0


def test_a_fit_on_a_bound_of_a_free_parameter_is_not_a_fit():
    """An index on its bound found no minimum inside the model's range; zero absorption (transparent) and fixed parameters on a bound are fine."""
    import torch

    from napari_lbs._core.refine._batches import _on_bound

    low = torch.tensor([[0.0, 0.0, 1.0, 0.05, -0.9, 0.0, -1e9]], dtype=torch.float64)
    high = torch.tensor([[100.0, 100.0, 5000.0, 500.0, 2.5, 5.0, 1e9]], dtype=torch.float64)
    fit = torch.tensor([[50.0, 50.0, 3000.0, 25.0, 0.26, 0.0, 1.0]], dtype=torch.float64)
    free = torch.ones_like(fit, dtype=torch.bool)
    assert not _on_bound(fit, free, low, high).item()  # transparent: absorption 0 is a value, not a bound hit
    for axis, value in ((4, -0.9), (4, 2.5), (2, 5000.0), (3, 0.05), (0, 0.0), (5, 5.0)):
        ended = fit.clone()
        ended[0, axis] = value
        assert _on_bound(ended, free, low, high).item(), axis
        held = free.clone()
        held[0, axis] = False
        assert not _on_bound(ended, held, low, high).item(), axis


def test_a_diameter_beyond_the_inner_size_grid_is_recovered_by_its_outer_part():
    """A guess 6 µm too large (a network's guess for a size it never saw) lies beyond the ±3.6 µm grid: its edge sends the search on to ±8 µm."""
    from napari_lbs._core import RefineSettings, refine_particles

    truth = (36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 900.0, 17.0)
    hologram = sphere_scene([truth], seed=2)
    refined = refine_particles(hologram, guess_table([(truth[0] + 0.5, truth[1], 910.0, 23.0)]), default_config(), fixed={"absorption": 0.0},
                               settings=RefineSettings(**FAST))
    assert len(refined) == 1 and abs(refined.diameter_um[0] - truth[3]) < 0.5 and abs(refined.index_contrast[0] - 0.26) < 0.02


def test_predict_refine_refits_every_particle_once_its_second_look_finds_more(monkeypatch):
    """A find in the residual joins every particle's model: the table is refitted with it (two rounds, from the fits, at the start's index contrast), in the first fit's pool."""
    import pandas as pd

    import napari_lbs._core.refine as refine_wing
    from napari_lbs._core import RefineSettings, load_config
    from napari_lbs._core.foundation import WorkerPool
    from napari_lbs._core.pipeline import _predict

    calls = []

    def fitted(table):
        return pd.DataFrame(table).reset_index(drop=True).assign(index_contrast=0.5, refined=True)

    def refine_particles(image, table, config, *, settings, valid=None, progress=None, should_stop=None, pool=None):
        calls.append((pd.DataFrame(table).reset_index(drop=True), settings.rounds, pool))
        return fitted(table)

    finds = [pd.DataFrame({"x_um": [30.0], "y_um": [40.0], "z_um": [2100.0], "diameter_um": [22.0]})]
    monkeypatch.setattr(refine_wing, "refine_particles", refine_particles)
    monkeypatch.setattr(refine_wing, "residual_particles", lambda *args, **kwargs: fitted(finds[0]) if len(finds[0]) else finds[0])
    particles = {"x_um": np.array([10.0, 90.0]), "y_um": np.array([10.0, 90.0]), "z_um": np.array([2000.0, 2500.0]), "diameter_um": np.array([20.0, 25.0])}
    options = {"material": None, "propose": None, "valid": None, "progress": None, "should_stop": None, "pool": WorkerPool(1)}
    table, record = _predict._refined(np.ones((64, 64)), particles, load_config(None), RefineSettings(index_contrast=0.26), **options)
    assert len(calls) == 2 and len(table["x_um"]) == 3
    refit, rounds, pool = calls[1]
    assert len(refit) == 3 and rounds >= 2 and np.all(refit["index_contrast"] == 0.26)  # the finds in the model; each restarted in its start's valley
    assert pool is not None and calls[0][2] is pool  # both fits in one pool of processes, started once
    assert record["residual"]["found"] == 1 and record["refit"] == {"particles": 3, "kept": 3}
    calls.clear()
    finds[0] = finds[0].iloc[:0]
    table, record = _predict._refined(np.ones((64, 64)), particles, load_config(None), RefineSettings(index_contrast=0.26), **options)
    assert len(calls) == 1 and "refit" not in record and record["residual"]["found"] == 0


def test_a_proposal_below_the_network_s_threshold_stays_only_where_the_fit_refines_it(monkeypatch):
    """Proposals are made below the model's threshold for the fit to judge: unrefined, such a one leaves the table; one above it stays at its guess."""
    import pandas as pd

    import napari_lbs._core.refine as refine_wing
    from napari_lbs._core import RefineSettings, load_config
    from napari_lbs._core.foundation import WorkerPool
    from napari_lbs._core.pipeline import _predict

    refined = np.array([True, True, False, False])
    monkeypatch.setattr(refine_wing, "refine_particles", lambda image, table, config, **kwargs: pd.DataFrame(table).reset_index(drop=True).assign(refined=refined))
    monkeypatch.setattr(refine_wing, "residual_particles", lambda *args, **kwargs: pd.DataFrame({"x_um": [], "y_um": [], "z_um": [], "diameter_um": []}))
    particles = {"x_um": np.array([10.0, 30.0, 50.0, 70.0]), "y_um": np.full(4, 20.0), "z_um": np.full(4, 2000.0), "diameter_um": np.full(4, 22.0),
                 "score": np.array([0.3, 0.15, 0.25, 0.12])}
    options = {"material": None, "propose": None, "valid": None, "progress": None, "should_stop": None, "pool": WorkerPool(1)}
    table, record = _predict._refined(np.ones((64, 64)), particles, load_config(None), RefineSettings(), accept_score=0.2, **options)
    assert table["x_um"].tolist() == [10.0, 30.0, 50.0] and record["unconfirmed"] == 1  # 0.15 refined stays, 0.12 unrefined goes
    table, record = _predict._refined(np.ones((64, 64)), particles, load_config(None), RefineSettings(), **options)
    assert len(table["x_um"]) == 4 and "unconfirmed" not in record
    assert _predict._acceptance_threshold({"threshold": 0.2}, None) == 0.2 and _predict._acceptance_threshold({"threshold": 0.2}, 0.12) == 0.12


def test_the_depth_prior_is_a_laplace_cost_of_the_guesses_median_error():
    from napari_lbs._core import RefineSettings
    from napari_lbs._core.foundation import InputError
    from napari_lbs._core.refine._rings import depth_prior

    z = torch.tensor([[10.0, 10.5, 9.0, 14.0]])
    cost = depth_prior(z, torch.tensor([10.0]), 0.5)
    assert torch.allclose(cost, torch.tensor([[0.0, np.log(2.0), 2 * np.log(2.0), 8 * np.log(2.0)]], dtype=cost.dtype))  # median |Δz| costs ln 2
    assert torch.equal(depth_prior(z, torch.tensor([10.0]), 0.0), torch.zeros_like(z))
    with pytest.raises(InputError, match="depth_prior_um"):
        RefineSettings(depth_prior_um=-1.0)


def test_a_fit_with_a_depth_prior_starts_at_its_guess_too_and_keeps_a_clear_sphere():
    from napari_lbs._core import RefineSettings, refine_particles

    truth = (36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 1500.0, 22.0)
    start = guess_table([(truth[0] + 1.0, truth[1] - 0.8, truth[2] + 20.0, truth[3] + 0.8)])
    out = refine_particles(sphere_scene([truth]), start, default_config(), fixed={"absorption": 0.0, "index_contrast": 0.26},
                           settings=RefineSettings(**{**FAST, "depth_prior_um": 15.0}))
    assert abs(out.z_um[0] - truth[2]) < 2.0 and abs(out.diameter_um[0] - truth[3]) < 0.3


def test_predict_refine_takes_its_depth_prior_from_the_model_s_validated_depth_error():
    from napari_lbs._core import RefineSettings, load_config
    from napari_lbs._core.pipeline import _predict

    assert _predict._network_depth_error_um({"validation": {"median_abs_dz_um": 0.44}}) == 0.44
    assert _predict._network_depth_error_um({"validation": {"median_abs_dz_um": None}}) == 0.0 and _predict._network_depth_error_um({}) == 0.0
    config = load_config(None)
    assert _predict._fit_settings(None, config, device="cpu", material=None, depth_prior_um=0.44).depth_prior_um == 0.44
    given = RefineSettings(depth_prior_um=2.0)
    assert _predict._fit_settings(given, config, device="cpu", material=0.26, depth_prior_um=0.44).depth_prior_um == 2.0  # a caller's settings win


def test_a_small_sphere_s_failed_fit_is_retried_with_its_index_held_and_a_large_one_s_is_not(monkeypatch):
    """Below k a = 10 a hologram shows a sphere's polarisability, not its size and index apart: a fit that ran to a bound is retried with both held at their starts."""
    from napari_lbs._core import RefineSettings, refine_particles
    from napari_lbs._core.refine import _refine

    calls = []

    def run_tasks(tasks, pool, steps):
        calls.append(tasks)
        outputs = []
        for task in tasks:
            count = len(task.index)
            params = task.start.copy()
            params[:, 4] = np.where(task.free[:, 4], 2.5, task.start[:, 4])  # a free index runs to its bound
            outputs.append({"params": params, "errors": 0.01 * task.free, "spread": np.full((count, 2), np.nan), "gain": np.full(count, 1e3),
                            "residual": np.full(count, 0.1), "ok": ~task.free[:, 4]})
            steps.advance(1)
        return outputs

    monkeypatch.setattr(_refine, "run_tasks", run_tasks)
    # 0.8 µm at 660 nm in water: k a = 5.1; 22 µm: k a = 139
    table = guess_table([(5.0, 5.0, 30.0, 0.8), (40.0, 40.0, 30.0, 22.0)])
    out = refine_particles(np.ones((64, 64)), table, default_config(), settings=RefineSettings(**FAST))
    assert len(calls) == 2 and [list(task.index) for task in calls[1]] == [[0]]  # the small sphere alone is retried
    assert not calls[1][0].free[0, 4] and not calls[1][0].free[0, 5] and calls[1][0].free[0, 2]  # index and absorption held, depth free
    small = out[out.diameter_um < 1.0].iloc[0]
    assert bool(small.refined) and small.index_contrast == pytest.approx(0.26) and small.index_err == 0.0
    assert not bool(out[out.diameter_um > 1.0].iloc[0].refined)  # the large one's failed fit stays unrefined at its guess


def test_a_fit_on_another_s_line_of_sight_is_its_twin_at_any_depth():
    # detections a quarter diameter apart laterally stay out of each other's model, so both
    # explain the same fringes: the worse fit is a twin, however far in depth it stopped
    from napari_lbs._core.refine._refine import _duplicates

    params = np.array([[10.0, 10.0, 30.0, 2.9, 0.26, 0.0],   # the sphere
                       [10.03, 10.0, 40.7, 1.8, -0.3, 0.0],  # its twin a depth minimum below (3.7 diameters)
                       [10.0, 13.0, 30.0, 1.0, 0.26, 0.0],   # a neighbour 3 um aside
                       [10.0, 10.1, 20.0, 2.0, 0.26, 0.0]])  # a fit that failed: never anyone's twin
    result = {"params": params, "ok": np.array([True, True, True, False]), "residual": np.array([0.10, 0.20, 0.15, 0.05])}
    assert _duplicates(result).tolist() == [False, True, False, False]
    # the better-fitted one keeps the particle, whichever depth it has
    assert _duplicates({**result, "residual": np.array([0.20, 0.10, 0.15, 0.05])}).tolist() == [True, False, False, False]


def test_a_ring_fit_whose_stencil_leaves_physics_keeps_finite_parameters(monkeypatch):
    """A sphere on the size bound (0.05 µm) puts the secant stencil at a negative size: that point has no hologram, the fit no NaN."""
    from types import SimpleNamespace

    from napari_lbs._core.refine import _rings

    def residuals(rings, z_um, spheres, scale, *, model):
        # a smooth bowl about (20 µm, 0.5 µm, 0.26), with no hologram below a size of zero;
        # as Lorenz–Mie theory's term count, a NaN sphere is refused
        if not torch.isfinite(spheres).all() or not torch.isfinite(z_um).all():
            raise ValueError("cannot convert float NaN to integer")
        out = torch.stack([z_um - 20.0, 10.0 * (spheres[:, 0] - 0.5), spheres[:, 1] - 0.26], dim=1)
        return torch.where((spheres[:, :1] > 0.0), out, torch.full_like(out, float("nan")))

    monkeypatch.setattr(_rings, "_ring_residuals", residuals)
    rings = SimpleNamespace(map=lambda change: rings)
    model = SimpleNamespace(optics={"wavelength_um": WAVELENGTH_UM, "medium_index": WATER})
    start = torch.tensor([[19.6, 0.05, 0.26], [19.6, 0.8, 0.26]], dtype=torch.float64)
    low = torch.tensor([[1.0, 0.05, -0.9]] * 2, dtype=torch.float64)
    high = torch.tensor([[60.0, 500.0, 2.5]] * 2, dtype=torch.float64)
    free = torch.ones(2, 3, dtype=torch.bool)
    fitted, cost = _rings._ring_fit(rings, start, free, torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64), low, high,
                                    model=model, iterations=8, depth_reach_um=1.0)
    assert torch.isfinite(fitted).all()
    # the sphere whose stencil stays physical still goes down its bowl
    assert abs(float(fitted[1, 1]) - 0.5) < 0.05 and abs(float(fitted[1, 0]) - 20.0) < 0.5


def test_a_singular_step_is_rejected_without_evaluating_a_nan_sphere():
    """A patch whose normal equations are not finite keeps its parameters; Lorenz–Mie theory, which refuses NaN spheres, never sees its trial."""
    from types import SimpleNamespace

    from napari_lbs._core.refine import RefineSettings
    from napari_lbs._core.refine._levenberg_marquardt import levenberg_marquardt

    generator = torch.Generator().manual_seed(0)
    design = torch.randn(40, 9, generator=generator, dtype=torch.float64)
    truth = torch.randn(2, 9, generator=generator, dtype=torch.float64)

    class Linear:
        def __init__(self, rows):
            self.rows = rows
            self.patches = SimpleNamespace(data=truth[rows] @ design.T, mask=torch.ones(len(rows), 40, dtype=torch.float64))

        def select(self, which):
            return Linear(self.rows[which])

        def __call__(self, params):
            if not torch.isfinite(params).all():
                raise ValueError("cannot convert float NaN to integer")
            return params @ design.T

        def jacobian(self, params, free):
            jac = design.expand(len(self.rows), -1, -1).clone()
            jac[self.rows == 0] = float("nan")  # the first patch's system is singular
            return self(params), jac

    start = torch.zeros(2, 9, dtype=torch.float64)
    free = torch.ones(2, 9, dtype=torch.bool)
    infinite = torch.full((2, 9), float("inf"), dtype=torch.float64)
    fitted, _ = levenberg_marquardt(Linear(torch.arange(2)), start, free, -infinite, infinite, scale=torch.ones(2, dtype=torch.float64),
                                    settings=RefineSettings(), iterations=20)
    assert torch.equal(fitted[0], start[0])
    assert torch.allclose(fitted[1], truth[1], atol=1e-6)


def test_a_fit_with_no_finite_curvature_is_not_a_fit_and_has_no_error_bars(monkeypatch):
    """Where the final Jacobian holds no finite number (a sphere on the size bound, its secants below zero) the fit is refused, not the batch."""
    from napari_lbs._core import RefineSettings, refine_particles
    from napari_lbs._core.refine import _model

    truth = (36.3 * PIXEL_UM, 35.6 * PIXEL_UM, 900.0, 18.0)
    hologram = sphere_scene([truth])
    start = guess_table([(truth[0] + 1.2, truth[1] - 0.9, truth[2] + 60.0, truth[3] + 0.6)])
    jacobian = _model.Model.jacobian

    def no_curvature(self, params, free, *, envelope=False):
        prediction, jac = jacobian(self, params, free, envelope=envelope)
        return prediction, (torch.full_like(jac, float("nan")) if envelope else jac)

    monkeypatch.setattr(_model.Model, "jacobian", no_curvature)
    out = refine_particles(hologram, start, default_config(), fixed={"absorption": 0.0}, settings=RefineSettings(**FAST))
    assert len(out) == 1 and not bool(out.refined[0])
    assert np.isnan(out.z_err_um[0]) and np.isnan(out.diameter_err_um[0])
