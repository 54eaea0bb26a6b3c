"""OCE calibration: recovery where the truth is known, determinism, stopping, the real hologram."""

import dataclasses
import time

import numpy as np
import pytest

from napari_lbs._core import ExperimentConfig, InputError, load_sample_hologram, random_particle_field, simulate_hologram
from napari_lbs._core.calibration._calibrate import (
    CalibrationSettings,
    HoloParams,
    _SSIM,
    calibrate,
    calibrate_hologram,
    experimental_reference,
    holo_processing,
    score_params,
)

PLANES_UM = np.arange(1800.0, 4801.0, 200.0)
OPTICS = {"planes_um": PLANES_UM, "wavelength_um": 0.66, "pixel_um": 2.2}
TRUTH = HoloParams(N_R=-0.4, N_sigma=0.35, gamma=0.9)


def hologram(seed, size=256, count=12):
    field = random_particle_field((size, size), count=count, diameter_min_um=20, diameter_max_um=30, layers_um=PLANES_UM, pixel_um=2.2, seed=seed)
    return simulate_hologram(field, wavelength_um=0.66)


@pytest.fixture(scope="module")
def pseudo_experiment():
    """I_e made by Holo-processing a *different* random field with known parameters."""
    return holo_processing(hologram(100), TRUTH, seed=7, **OPTICS), [hologram(s) for s in (1, 2, 3)]


def test_fast_ssim_equals_scikit_image():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    a, b = rng.random((64, 80)), rng.random((64, 80))
    expected = structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert _SSIM(a)(b) == pytest.approx(expected, abs=1e-12)


def test_fit_reaches_at_least_the_truths_ssim(pseudo_experiment):
    """The joint fit finds parameters scoring at least as well as the truth; they need not be the
    truth (parameters trade off, see the profile test and docs/calibration.md)."""
    reference, holograms = pseudo_experiment
    steps, live = [], []
    result = calibrate(reference, holograms, settings=CalibrationSettings(generations=25, population=10), progress=lambda d, t: steps.append((d, t)), report=live.append, **OPTICS)
    truth_ssim, plain_ssim = score_params(reference, holograms, [TRUTH, HoloParams(0.0, 0.2, 1.0)], **OPTICS)
    assert result.ssim >= truth_ssim - 0.005
    assert result.ssim > plain_ssim + 0.02
    totals = {total for _, total in steps}
    assert totals == {3 * 25 + 26 * 10 + 5 * 8}  # the set-up's back-propagations, every candidate, the finalists' re-scoring
    assert [done for done, _ in steps] == sorted(done for done, _ in steps) and steps[-1][0] == steps[-1][1]
    assert [h["generation"] for h in result.history] == list(range(1, 26))
    assert live == result.history  # each generation's record reported as it was made (a live curve)
    assert not result.stopped


def test_noise_width_is_not_identifiable_from_the_depth_average(pseudo_experiment):
    """Shown, not hidden: across N_sigma's whole range the SSIM moves by < 0.03, while gamma
    and N_R move it by > 0.03 and peak within one grid step of the truth (0.1 / 0.1)."""
    reference, holograms = pseudo_experiment

    def profile(name, values):
        return score_params(reference, holograms, [dataclasses.replace(TRUTH, **{name: v}) for v in values], **OPTICS)

    sigma = profile("N_sigma", np.linspace(0.2, 0.6, 5))
    assert np.ptp(sigma) < 0.03
    gammas = np.linspace(0.6, 1.4, 9)
    gamma = profile("gamma", gammas)
    assert np.ptp(gamma) > 0.03 and abs(gammas[np.argmax(gamma)] - TRUTH.gamma) <= 0.1 + 1e-9
    levels = np.linspace(-0.7, -0.1, 7)
    level = profile("N_R", levels)
    assert np.ptp(level) > 0.03 and abs(levels[np.argmax(level)] - TRUTH.N_R) <= 0.1 + 1e-9


def test_same_seed_same_parameters():
    reference = holo_processing(hologram(5, 128, 4), TRUTH, seed=1, **OPTICS)
    holograms = [hologram(6, 128, 4)]
    settings = CalibrationSettings(generations=5, population=6, parents=2, fields=1, seed=11)
    a = calibrate(reference, holograms, settings=settings, **OPTICS)
    b = calibrate(reference, holograms, settings=settings, **OPTICS)
    c = calibrate(reference, holograms, settings=dataclasses.replace(settings, seed=12), **OPTICS)
    assert a.params == b.params and a.ssim == b.ssim and a.history == b.history
    assert a.params != c.params


def test_stop_request_returns_promptly_with_the_best_so_far():
    reference = holo_processing(hologram(5, 128, 4), TRUTH, seed=1, **OPTICS)
    live = []
    start = time.perf_counter()
    result = calibrate(reference, [hologram(6, 128, 4)], settings=CalibrationSettings(generations=500, population=6, parents=2, fields=1),
                       report=live.append, should_stop=lambda: len(live) >= 3, **OPTICS)
    assert time.perf_counter() - start < 20
    assert result.stopped and len(result.history) == 3
    assert 0.0 < result.ssim < 1.0 and -1.0 <= result.params.N_R <= 0.0


def stop_after(count: int, steps: list, asked: list):
    """A ``progress`` that asks to stop once ``count`` steps are done (the time of asking in ``asked``), and its ``should_stop``."""
    def progress(done, total):
        steps.append((done, time.perf_counter()))
        if done >= count and not asked:
            asked.append(time.perf_counter())

    return progress, lambda: bool(asked)


def test_stop_is_heard_between_the_candidates_of_a_generation_and_progress_counts_each():
    """A population of 120 takes seconds to score; Stop after 10 of its candidates returns within 2 s with the best of those."""
    from napari_lbs._core.calibration._calibrate import _Fitness

    reference = holo_processing(hologram(5, 128, 4), TRUTH, seed=1, **OPTICS)
    setup = _Fitness.setup_steps(1)
    steps, asked = [], []
    progress, should_stop = stop_after(setup + 10, steps, asked)
    result = calibrate(reference, [hologram(6, 128, 4)], settings=CalibrationSettings(generations=50, population=120, parents=4, fields=1),
                       progress=progress, should_stop=should_stop, **OPTICS)
    ended = time.perf_counter() - asked[0]
    assert ended < 2.0, f"calibration ended {ended:.1f} s after the stop request"
    assert result.stopped and result.history == [] and 0.0 < result.ssim < 1.0
    assert [done for done, _ in steps[setup : setup + 10]] == list(range(setup + 1, setup + 11))  # each candidate of the first population counted


def test_stop_during_the_set_up_raises_stopped_at_once():
    from napari_lbs._core import Stopped

    reference = holo_processing(hologram(5, 128, 4), TRUTH, seed=1, **OPTICS)
    steps, asked = [], []
    progress, should_stop = stop_after(2, steps, asked)
    with pytest.raises(Stopped):
        calibrate(reference, [hologram(6, 128, 4), hologram(7, 128, 4), hologram(8, 128, 4)], settings=CalibrationSettings(generations=50, fields=3),
                  progress=progress, should_stop=should_stop, **OPTICS)
    assert time.perf_counter() - asked[0] < 2.0 and len(steps) == 2


@pytest.mark.parametrize("mode", ["robust", "seed"])
def test_real_hologram_top_left_tile_calibrates(mode):
    result = calibrate_hologram(load_sample_hologram(), ExperimentConfig(), roi=(0, 0), settings=CalibrationSettings(mode=mode, generations=3, population=6, parents=2, fields=2))
    payload = result.to_json()
    assert payload["roi"] == [0, 0, 256]
    assert set(payload["params"]) >= {"N_R", "N_sigma", "gamma"}
    assert 0.3 < payload["ssim"] < 1.0  # the seed reports ~0.7 after a full fit
    if mode == "seed":
        assert all(abs(v * 100 - round(v * 100)) < 1e-6 for v in payload["params"].values())  # 0.01 grid
    reference = result.reference_experimental
    assert reference.shape == (256, 256) and 0.0 <= reference.min() and reference.max() <= 1.0


def test_reference_tile_choice_and_refusals():
    config = ExperimentConfig()
    hologram_image = load_sample_hologram()[:512, :512]
    with pytest.raises(InputError, match="roi: .* crosses the edge"):
        calibrate_hologram(hologram_image, config, roi=(300, 0))
    with pytest.raises(InputError, match="tile.size"):
        calibrate_hologram(hologram_image[:200, :200], config)
    from napari_lbs._core import backpropagate
    from napari_lbs._core.calibration._calibrate import choose_reference_tile

    stack = backpropagate(hologram_image, config.layer_depths_um(), wavelength_um=0.66, pixel_um=2.2)
    (x, y), reason = choose_reference_tile(stack, size=256)
    assert (x, y) in [(0, 0), (256, 0), (0, 256), (256, 256)] and "medoid of 4" in reason


def test_experimental_reference_is_bright_particles_in_unit_range():
    stack = np.ones((3, 32, 32))
    stack[:, 10:14, 10:14] = 0.1  # a dark particle in the raw reconstruction
    image = experimental_reference(stack)
    assert image[12, 12] == pytest.approx(1.0) and image[0, 0] == pytest.approx(0.0)
