"""Catalog effects as nested models of a frame (`select_effects`) and the held-out likelihood they are judged by."""

import numpy as np
import pytest

from napari_lbs._core.gap._heldout import TileSplit, model_probabilities, tile_spectra, whittle_loglik
from napari_lbs._core.gap._levels import levels_test
from napari_lbs._core.gap._nested import fit_frame, select_effects
from napari_lbs._core.gap._scene_image import Scene
from napari_lbs._core.physics import gaussian_blur, sensor_image

SIZE = 256


def _scene(seed: int = 0) -> np.ndarray:
    """A frame of ring patterns (a stand-in for particles' holograms: fringes at 0.05-0.3 cycles per pixel), unobstructed light 1."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    scene = np.ones((SIZE, SIZE))
    for _ in range(12):
        cy, cx, scale = rng.uniform(0, SIZE), rng.uniform(0, SIZE), rng.uniform(40.0, 120.0)
        r2 = (yy - cy) ** 2 + (xx - cx) ** 2
        scene += 0.3 * np.cos(r2 / scale) * np.exp(-r2 / (2 * 40.0**2))
    return scene


def _frame(effects: dict, *, seed: int = 1, read_noise: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    scene = _scene()
    noise = np.random.default_rng(seed).standard_normal((SIZE, SIZE)).astype(np.float32)
    image = sensor_image(scene.astype(np.float32), {"contrast": 0.9, "sigma": read_noise, "gamma": 1.0}, effects, noise=noise).astype(np.float64)
    return image / image.mean(), scene


@pytest.mark.parametrize(("effects", "expected"), [
    ({}, ()),
    ({"illumination": {"depth": 0.35, "x0": 0.2, "y0": -0.1}}, ("illumination",)),
    ({"sensor_blur": {"sigma_px": 1.2}}, ("sensor_blur",)),
])
def test_the_effect_present_is_selected_and_nothing_else(effects, expected):
    data, scene = _frame(effects)
    selection = select_effects(data, scene, TileSplit.of(data.shape))
    assert selection.chosen == expected
    if expected == ("sensor_blur",):
        fitted = [fit["sensor_blur.sigma_px"] for fit in selection.fits["sensor_blur"].params]
        assert all(abs(value - 1.2) < 0.15 for value in fitted)


def _depth_scene() -> Scene:
    """Two depth groups of ring patterns: shallow ones (1 mm) and deep ones (5 mm), on 2 µm pixels."""
    groups = np.stack([_scene(seed) - 1.0 for seed in (0, 5)]).astype(np.float32)
    return Scene(1.0 + groups.sum(axis=0), (1000.0, 5000.0), groups, 2.0)


@pytest.mark.parametrize(("effect", "expected"), [("coherence", ("coherence",)), ("sensor_blur", ("sensor_blur",))])
def test_a_source_size_blurs_by_depth_and_a_sensor_blurs_every_depth_alike(effect, expected):
    """Coherence (σ = θ·z: 0.8 px shallow, 4 px deep) and sensor blur (1.5 px everywhere) are told apart by depth."""
    scene = _depth_scene()
    blurred = scene.coherent_blur(1.6) if effect == "coherence" else scene.image
    effects = {"sensor_blur": {"sigma_px": 1.5}} if effect == "sensor_blur" else {}
    noise = np.random.default_rng(3).standard_normal((SIZE, SIZE)).astype(np.float32)
    image = sensor_image(blurred.astype(np.float32), {"contrast": 1.0, "sigma": 0.01, "gamma": 1.0}, effects, noise=noise).astype(np.float64)
    data = image / image.mean()
    selection = select_effects(data, scene, TileSplit.of(data.shape))
    assert selection.chosen == expected
    if effect == "coherence":
        assert all(abs(fit["coherence.theta_mrad"] - 1.6) < 0.2 for fit in selection.fits["coherence"].params)


def test_an_array_scene_has_no_depth_dependent_candidate():
    data, scene = _frame({})
    selection = select_effects(data, scene, TileSplit.of(data.shape))
    assert "coherence" not in selection.steps[0]["gains"]


@pytest.mark.parametrize(("step", "selected"), [(1, False), (8, True)])
def test_the_converter_step_is_read_from_the_levels_used(step, selected):
    """8-bit counts on a grid of 8 (a 5-bit converter) name quantization with its bits; every level used names nothing."""
    rng = np.random.default_rng(0)
    counts = (np.clip(np.round((150 + rng.normal(0, 2.0, (128, 128))) / step), 0, 255 // step) * step).astype(np.uint8)
    result = levels_test(counts, np.zeros(counts.shape), floor_variance=(2.0 / 150) ** 2)
    assert result["step_counts"] == step and result["selected"] is selected
    if selected:
        assert abs(result["params"]["bits"] - np.log2(255 / 8 + 1)) < 1e-9
    assert not levels_test(counts.astype(np.float64) + 0.5, np.zeros(counts.shape), floor_variance=1e-4)["integer"]


@pytest.mark.parametrize(("level", "selected"), [(150.0, False), (215.0, True)])
def test_saturation_is_named_when_the_light_it_cuts_is_a_share_of_the_noise(level, selected):
    """Fringes of ±35 % about a mean of 150 counts touch 255 at their crests only (no name); about 215 counts, every crest is cut."""
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:256, 0:256]
    light = 1.0 + 0.35 * np.cos(2 * np.pi * np.hypot(yy - 128, xx - 128) ** 2 / 4000.0) + rng.normal(0.0, 0.1, (256, 256))
    recorded = light * level + rng.normal(0.0, 2.0, light.shape)
    counts = np.clip(np.round(recorded), 0, 255).astype(np.uint8)
    mean = counts.mean()
    result = levels_test(counts, light * level / mean - counts / mean, floor_variance=(2.0 / mean) ** 2)
    assert result["step_counts"] == 1 and result["saturated_share"] > 0 and result["selected"] is selected
    assert (result["saturation_noise_share"] >= 0.1) is selected


def test_a_wrong_effect_gains_nothing_held_out():
    """On a frame with no etalon, the fringe model's held-out gain is at most zero within its error."""
    data, scene = _frame({})
    split = TileSplit.of(data.shape)
    base, fringes = fit_frame(data, scene, split, ()), fit_frame(data, scene, split, ("parasitic_fringes",))
    gain = fringes.loglik - base.loglik
    assert gain.sum() <= 2.0 * gain.std(ddof=1) * np.sqrt(gain.size)


def test_a_tile_the_scene_misfits_is_one_vote_in_the_held_out_test():
    """14 of 16 tiles gaining 200 nats and two losing 1 300 each (a misfit particle's tiles) pass the sign test at z 3; their sum over its tile-to-tile error would not."""
    from napari_lbs._core.gap._nested import gain_and_z

    gains = np.array([200.0] * 14 + [-1300.0] * 2)
    total, z = gain_and_z(gains, np.zeros_like(gains))
    assert total == pytest.approx(200.0) and z == pytest.approx(3.0)
    assert total / (gains.std(ddof=1) * np.sqrt(gains.size)) < 0.2
    assert gain_and_z(-gains, np.zeros_like(gains))[1] == pytest.approx(-3.0) and gain_and_z(np.zeros(16), np.zeros(16)) == (0.0, 0.0)


def test_whittle_likelihood_prefers_the_residual_that_is_noise():
    """A residual of white noise scores higher than the same noise plus a structure the model left."""
    split = TileSplit.of((SIZE, SIZE))
    rng = np.random.default_rng(4)
    white = rng.standard_normal((SIZE, SIZE))
    structured = white + 2.0 * np.sin(np.arange(SIZE) / 3.0)[None, :]
    clean = whittle_loglik((tile_spectra(white, split), tile_spectra(white, split)), split)
    left = whittle_loglik((tile_spectra(structured, split), tile_spectra(structured, split)), split)
    assert clean.sum() > left.sum()
    probabilities = model_probabilities({"clean": clean, "left": left})
    assert probabilities["clean"] > 0.99 and sum(probabilities.values()) == pytest.approx(1.0)


def _gains_of_taking_out(structure, misfit_of_r2) -> np.ndarray:
    """Each tile's held-out gain of a model that takes ``structure(yy, xx)`` out of every tile, one tile also holding ``misfit_of_r2(r²)`` about its centre."""
    split = TileSplit.of((SIZE, SIZE))
    noise = 0.01 * np.random.default_rng(5).standard_normal((SIZE, SIZE))
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    window = split.windows()[1]
    cy, cx = (window[0].start + window[0].stop) / 2, (window[1].start + window[1].stop) / 2
    misfit = np.zeros((SIZE, SIZE))
    misfit[window] = misfit_of_r2((yy - cy) ** 2 + (xx - cx) ** 2)[window]
    left, taken = noise + misfit + structure(yy, xx), noise + misfit
    return whittle_loglik((tile_spectra(taken, split),) * 2, split) - whittle_loglik((tile_spectra(left, split),) * 2, split)


def test_a_tile_of_misfit_is_judged_at_its_own_level():
    """A model that takes a fringe out of every tile gains in every tile, the one holding a particle's misfit too.

    Judged at the level of a spectrum shared by every tile, the misfit's tile loses: the
    fringe had raised the spectrum its structure was judged against.
    """
    fringe = lambda yy, xx: 0.05 * np.cos(2 * np.pi * (xx * np.cos(0.5) + yy * np.sin(0.5)) / 8.0 + 0.4)
    rings = lambda r2: 0.3 * np.cos(r2 / 60.0) * np.exp(-r2 / (2 * 30.0**2))  # a sphere's chirped rings: power at every radius
    assert np.all(_gains_of_taking_out(fringe, rings) > 0)


def test_an_envelope_taken_out_gains_in_a_tile_of_low_frequency_misfit_too():
    """A model that takes a smooth illumination envelope out of every tile gains in every tile, the one holding a broad misfit too.

    Judged at one level per tile, the misfit's tile lost about 3 000 nats: the envelope had
    raised the lowest frequencies its misfit was judged against. Each radial bin of a tile at
    its own level judges each band against itself.
    """
    envelope = lambda yy, xx: 0.03 * np.exp(-((xx - 0.7 * SIZE) ** 2 + (yy - 0.4 * SIZE) ** 2) / (2 * (0.6 * SIZE) ** 2))
    blob = lambda r2: 0.05 * np.exp(-r2 / (2 * 12.0**2))  # the broad blob a misfit particle's mean leaves
    assert np.all(_gains_of_taking_out(envelope, blob) > 0)


def test_a_straight_fringe_between_the_frequency_bins_is_fitted_with_its_phase():
    """An etalon's fringe of 11.3 px at 0.6 rad, 1.2 rad at the first pixel (written here, not by the catalog): recovered and selected."""
    data, scene = _frame({})
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    data = data * (1.0 + 0.04 * np.cos(2 * np.pi * (xx * np.cos(0.6) + yy * np.sin(0.6)) / 11.3 + 1.2))
    split = TileSplit.of(data.shape)
    fit = fit_frame(data, scene, split, ("parasitic_fringes",))
    for params in fit.params:
        assert params["parasitic_fringes.period_px"] == pytest.approx(11.3, abs=0.01)
        assert params["parasitic_fringes.angle_rad"] == pytest.approx(0.6, abs=0.01)
        assert np.cos(params["parasitic_fringes.phase_rad"] - 1.2) > np.cos(0.2)
        assert params["parasitic_fringes.amplitude"] == pytest.approx(0.04 / 0.9, rel=0.25)  # the fringe multiplies the light, the scene's contrast 0.9
    assert select_effects(data, scene, split).chosen == ("parasitic_fringes",)


def test_the_same_frame_gives_the_same_selection():
    data, scene = _frame({"illumination": {"depth": 0.3, "x0": 0.0, "y0": 0.0}})
    first, second = (select_effects(data, scene, TileSplit.of(data.shape)) for _ in range(2))
    assert first.chosen == second.chosen and first.fits[first.chosen[0]].params == second.fits[second.chosen[0]].params


@pytest.mark.parametrize("log10_photons", [None, 2.0])
def test_photon_noise_is_found_from_the_bright_and_dark_fringes_and_its_level_measured(log10_photons):
    from napari_lbs._core.gap._nested import shot_noise_test

    effects = {"shot_noise": {"log10_photons": log10_photons}} if log10_photons else {}
    data, scene = _frame(effects, read_noise=0.01)
    split = TileSplit.of(data.shape)
    result = shot_noise_test(fit_frame(data, scene, split, ()), split)
    if log10_photons is None:
        assert result["z"] < 3.0
    else:
        assert result["z"] >= 3.0 and abs(result["log10_photons"] - log10_photons) < 0.3
        assert result["white"] and all(0.5 < ratio < 2.0 for ratio in result["fine_ratios"])


def test_a_residual_that_grows_with_the_light_but_is_not_white_is_no_photon_noise():
    """Noise blurred over 2 px (what misfit fringes leave, not photons) and scaled with the light: the slope is there, the whiteness is not."""
    from napari_lbs._core.gap._nested import FrameFit, shot_noise_test
    from napari_lbs._core.physics import gaussian_blur

    data, scene = _frame({}, read_noise=0.002)
    split = TileSplit.of(data.shape)
    fit = fit_frame(data, scene, split, ())
    rng = np.random.default_rng(4)
    structured = [gaussian_blur(rng.standard_normal(data.shape), 2.0) * 0.2 * mean for mean in fit.means]
    grown = FrameFit(fit.effects, fit.params, fit.loglik, tuple(r + s for r, s in zip(fit.residuals, structured, strict=True)), fit.means)
    result = shot_noise_test(grown, split)
    assert result["z"] >= 3.0 and not result["white"] and all(ratio < 0.5 for ratio in result["fine_ratios"])


@pytest.mark.parametrize("log10_photons", [None, 2.0])
def test_photon_noise_beside_red_leftovers_reads_white_in_the_finest_filter(log10_photons):
    """Leftovers blurred over 1.5 px and scaled with the light (a window's rings from grains
    outside the field, misfit rings): alone they are no photon noise; beside photon noise they
    raise the band's slope three-fold (a band pass read it as not white) and leave the finest
    filter's, so the noise is named and measured."""
    from napari_lbs._core.gap._nested import FrameFit, shot_noise_test
    from napari_lbs._core.physics import gaussian_blur

    effects = {"shot_noise": {"log10_photons": log10_photons}} if log10_photons else {}
    data, scene = _frame(effects, read_noise=0.01 if log10_photons else 0.002)
    split = TileSplit.of(data.shape)
    fit = fit_frame(data, scene, split, ())
    rng = np.random.default_rng(4)
    leftovers = [gaussian_blur(rng.standard_normal(data.shape), 1.5) * 0.3 * mean for mean in fit.means]
    result = shot_noise_test(FrameFit(fit.effects, fit.params, fit.loglik, tuple(r + s for r, s in zip(fit.residuals, leftovers, strict=True)), fit.means), split)
    assert result["z"] >= 3.0
    if log10_photons is None:
        assert not result["white"] and all(ratio < 0.5 for ratio in result["fine_ratios"])
    else:
        assert all(ratio > 2.0 for ratio in result["band_ratios"]), result["band_ratios"]
        assert result["white"] and all(0.67 < ratio < 1.5 for ratio in result["fine_ratios"]) and abs(result["log10_photons"] - log10_photons) < 0.3


@pytest.mark.parametrize("log10_photons", [2.0, None])
def test_the_whiteness_redrawn_on_the_tiles_weighted_alike_is_the_test_s_own(log10_photons):
    """`whiteness_draws` refits the slopes from each tile's normal equations: weighted alike it
    gives the test's verdict, and photon noise clearly white (or a slope clearly not) keeps it
    in nearly every draw."""
    from napari_lbs._core.gap._nested import FrameFit, shot_noise_test, whiteness_draws
    from napari_lbs._core.physics import gaussian_blur

    effects = {"shot_noise": {"log10_photons": log10_photons}} if log10_photons else {}
    data, scene = _frame(effects, read_noise=0.01 if log10_photons else 0.002)
    split = TileSplit.of(data.shape)
    fit = fit_frame(data, scene, split, ())
    if log10_photons is None:  # noise blurred over 2 px and scaled with the light: not white
        rng = np.random.default_rng(4)
        structured = [gaussian_blur(rng.standard_normal(data.shape), 2.0) * 0.2 * mean for mean in fit.means]
        fit = FrameFit(fit.effects, fit.params, fit.loglik, tuple(r + s for r, s in zip(fit.residuals, structured, strict=True)), fit.means)
    result = shot_noise_test(fit, split)
    assert result["white"] == (log10_photons is not None)
    assert whiteness_draws(result["whiteness"], np.full((1, 16), 1 / 16))[0] == result["white"]
    draws = whiteness_draws(result["whiteness"], np.random.default_rng(0).dirichlet(np.ones(16), size=500))
    assert draws.shape == (500,) and np.mean(draws == result["white"]) > 0.9


@pytest.mark.parametrize("log10_photons", [None, 2.0])
def test_far_rings_the_scene_does_not_render_are_a_nuisance_of_the_photon_noise_test(log10_photons):
    """Fine rings left in the residual whose power grows with the light about them (transparent
    spheres' far rings beyond the fitted scene's reach): beside their rendered power
    (`far_ring_power`) they are not taken for photon noise, and photon noise beside them is
    still found and measured."""
    from napari_lbs._core.gap._nested import FrameFit, far_ring_power, shot_noise_test
    from napari_lbs._core.physics import gaussian_blur

    effects = {"shot_noise": {"log10_photons": log10_photons}} if log10_photons else {}
    data, scene = _frame(effects, read_noise=0.01 if log10_photons else 0.002)
    split = TileSplit.of(data.shape)
    fit = fit_frame(data, scene, split, ())
    rng = np.random.default_rng(6)
    rings = gaussian_blur(rng.standard_normal(data.shape), 0.6) * 0.05  # fine rings, their amplitude the light's
    residuals = tuple(r + rings * mean for r, mean in zip(fit.residuals, fit.means, strict=True))
    grown = FrameFit(fit.effects, fit.params, fit.loglik, residuals, fit.means)
    rendered = 1.0 + rings * fit.means[0]
    without, beside = shot_noise_test(grown, split), shot_noise_test(grown, split, nuisance=far_ring_power(rendered))
    if log10_photons is None:
        assert without["z"] >= 3.0 and beside["z"] < 3.0, (without["z"], beside["z"])
    else:
        assert beside["z"] >= 3.0 and beside["white"] and abs(beside["log10_photons"] - log10_photons) < 0.3, beside


def test_photon_noise_under_an_envelope_fitted_imperfectly_is_read_white_within_neighbourhoods():
    """Photon noise under an envelope, and the fringes the envelope's fit multiplies by an error that grows toward the dark side.

    That misfit's power lies in the band and falls with the smooth light: read on the whole
    light it pulled the band's slope down (ratios 0.1–0.5 on these frames, median 0.34); within
    neighbourhoods, the smooth light a nuisance, the ratios stay about photon noise's 1.
    Single frames' band ratios scatter (0.3–1.3); the finest filter, where the misfit holds
    least, reads 0.88–1.35 on these eight noise draws, and every one is named.
    """
    from napari_lbs._core.gap._nested import FrameFit, shot_noise_test
    from napari_lbs._core.physics import gaussian_blur

    ratios, named = [], 0
    for seed in range(1, 9):
        data, scene = _frame({"illumination": {"depth": 0.45, "x0": 0.3, "y0": -0.2}, "shot_noise": {"log10_photons": 2.0}}, read_noise=0.01, seed=seed)
        split = TileSplit.of(data.shape)
        fit = fit_frame(data, scene, split, ("illumination",))
        smooth = [gaussian_blur(mean, 8.0) for mean in fit.means]
        misfit = [(mean - s) * 0.4 * (s.max() - s) for mean, s in zip(fit.means, smooth, strict=True)]
        grown = FrameFit(fit.effects, fit.params, fit.loglik, tuple(r + m for r, m in zip(fit.residuals, misfit, strict=True)), fit.means)
        result = shot_noise_test(grown, split)
        ratios += result["fine_ratios"]
        named += result["z"] >= 3.0 and result["white"]
    assert 0.8 < np.median(ratios) < 1.25 and named >= 7  # read on the whole light in a band pass: median 0.3, one frame of eight named


def test_a_frame_of_spheres_is_diagnosed_end_to_end_with_the_report_fields():
    """`diagnose_scene` on a small Lorenz–Mie frame: particles found and fitted, every field of report.json, strict JSON, the same twice."""
    import json

    import pandas as pd

    from napari_lbs._core import ExperimentConfig, particle_hologram
    from napari_lbs._core.gap import SceneDiagnosisSettings, diagnose_scene

    config = ExperimentConfig.from_dict({"volume": {"z_min_um": 1800.0, "z_max_um": 2600.0, "z_step_um": 50.0}})
    spheres = pd.DataFrame({"x_um": [150.0, 420.0], "y_um": [160.0, 400.0], "z_um": [2000.0, 2400.0], "diameter_um": [24.0, 26.0], "index_contrast": [0.26, 0.26]})
    frame = particle_hologram((256, 256), spheres, config) + np.random.default_rng(2).normal(0.0, 0.01, (256, 256))
    settings = SceneDiagnosisSettings(particles=4, scene_particles=8, index_grid=(0.26,), grid=2, level_z=2.0)
    first, second = (diagnose_scene(frame, config, settings=settings) for _ in range(2))
    report = json.loads(first.to_json())
    assert {"gap", "effects", "verdict", "posterior"} <= set(report)
    assert {"id", "shrink", "residual", "undecided", "catalog_explains", "probability"} <= set(report["verdict"])
    assert 0.0 <= report["verdict"]["probability"] <= 1.0 and {"name", "outcome", "holds"} <= set(report["confidence"][0])
    assert report["verdict"]["probability"] <= min(d["holds"] for d in report["confidence"])
    assert {e["id"] for e in report["effects"]} == {"illumination", "sensor_blur", "parasitic_fringes", "coherence", "particle_phase", "shot_noise", "quantization"}
    levels = next(e for e in report["effects"] if e["id"] == "quantization")["levels"]
    assert levels["integer"] is False  # a float frame holds no converter levels to read
    assert report["particle_optics"]["particles"] == 2 and abs(report["particle_optics"]["diameter_median_um"] - 25.0) < 2.0
    assert report["scene"]["particles"] == 2 and report["scene"]["in_size_range"] == 2 and report["scene"]["small_scatterers"]["count"] == 0
    assert abs(report["scene"]["diameter_um"][2] - 25.0) < 2.0 and abs(report["scene"]["z_um"][2] - 2200.0) < 100.0
    directional = report["gap"]["directional_blur"]
    assert set(directional) == {"gain_nats", "z", "variance_difference_px2", "angle_rad"} and 0.0 <= directional["angle_rad"] < np.pi
    assert directional["variance_difference_px2"] < 0.05  # no blur in the frame, none by direction
    assert first.to_json() == second.to_json()


def test_the_scene_population_counts_the_sample_and_the_small_scatterers_beside_it():
    """Counts against the config's sizes, the density over the frame, the percentiles of the sample's sizes, the small ones per 256-pixel tile."""
    import pandas as pd

    from napari_lbs._core import ExperimentConfig
    from napari_lbs._core.gap._population import scene_population

    config = ExperimentConfig()  # 20-30 um particles, 2.2 um pixels
    table = pd.DataFrame({"x_um": np.zeros(7), "y_um": np.zeros(7), "z_um": [2000.0, 2500.0, 3000.0, 3500.0, 4000.0, 2200.0, 2600.0],
                          "diameter_um": [22.0, 24.0, 25.0, 26.0, 28.0, 8.0, 40.0], "index_contrast": [0.25, 0.26, 0.26, 0.27, 0.28, 0.4, 0.1]})
    population = scene_population(table, config, (512, 512))
    assert (population["particles"], population["in_size_range"], population["below_size_range"], population["above_size_range"]) == (7, 5, 1, 1)
    assert population["per_mm2"] == pytest.approx(7 / (512 * 512 * 0.0022**2))
    assert population["diameter_um"][2] == 25.0 and population["diameter_um"][1] == 24.0 and population["index_contrast"][2] == 0.26
    assert population["small_scatterers"] == {"count": 1, "per_256px_tile": 0.25, "diameter_um": [8.0, 8.0]}
    empty = scene_population(table.iloc[:0], config, (512, 512))
    assert empty["particles"] == 0 and empty["diameter_um"] is None and empty["small_scatterers"]["diameter_um"] is None


def test_the_unexplained_share_is_nothing_for_white_noise_and_a_quarter_for_half_the_frame_s_fringe():
    """A white residual leaves none of the frame's structure unexplained (a floor bin by bin would call half of it structure); half the fringe's amplitude leaves a quarter of its power."""
    from napari_lbs._core.gap._heldout import tile_spectra
    from napari_lbs._core.gap._unexplained import unexplained_share

    split = TileSplit.of((SIZE, SIZE), grid=4)
    rng = np.random.default_rng(0)
    white = (rng.normal(0.0, 0.01, (SIZE, SIZE)), rng.normal(0.0, 0.01, (SIZE, SIZE)))
    fringe = 0.05 * np.sin(np.arange(SIZE) / 7.0)[None, :]
    frame = tile_spectra(fringe + rng.normal(0.0, 0.01, (SIZE, SIZE)), split)
    share, _, tiles, floor = unexplained_share(white, split, frame)
    assert share < 0.01 and tiles.max() < 0.03 and abs(floor - 1e-4) < 1e-5
    share, _, tiles, _ = unexplained_share(tuple(w + 0.5 * fringe for w in white), split, frame)
    assert abs(share - 0.25) < 0.03 and np.ptp(tiles) < 0.05


def test_a_column_pattern_is_found_and_white_noise_or_a_smooth_envelope_hold_none():
    """Offsets per column (a camera's column amplifiers) stand far above white noise in the column means; an envelope and white noise do not."""
    from napari_lbs._core.gap._unexplained import line_pattern

    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    plain = tuple(rng.normal(0.0, 0.01, (SIZE, SIZE)) + 0.05 * ((xx - 0.4) ** 2 + (yy - 0.6) ** 2) for _ in range(2))
    ratios = line_pattern(plain)
    assert max(ratios.values()) < 2.0
    columns = rng.normal(0.0, 0.005, SIZE)[None, :]
    ratios = line_pattern(tuple(r + columns for r in plain))
    assert ratios["columns"] > 20.0 and ratios["rows"] < 2.0


@pytest.mark.parametrize("sigma_rows, sigma_cols, angle", [(0.6, 2.0, 0.0), (2.0, 0.6, np.pi / 2), (1.8, 1.8, None)])
def test_a_blur_by_direction_is_found_with_its_axis_and_a_round_one_is_not(sigma_rows, sigma_cols, angle):
    """A frame blurred more along one axis than the model (motion) gains held out in every tile, its long axis measured; a round blur the model underrates is no blur by direction."""
    from scipy import ndimage

    from napari_lbs._core.gap._directional import directional_blur_test

    rng = np.random.default_rng(3)
    texture = 1.0 + 0.3 * ndimage.gaussian_filter(rng.standard_normal((SIZE, SIZE)), 2.0) / 0.14  # fringes of a few pixels
    model = ndimage.gaussian_filter(texture, 1.2)  # the fitted round blur
    data = ndimage.gaussian_filter(texture, (sigma_rows, sigma_cols)) + rng.normal(0.0, 0.01, (SIZE, SIZE))
    split = TileSplit.of((SIZE, SIZE), grid=4)
    residual = data - model
    baseline = whittle_loglik((tile_spectra(residual, split),) * 2, split)
    found = directional_blur_test((residual, residual), (model, model), split, baseline)
    if angle is None:
        assert found["z"] < 3.0 and found["variance_difference_px2"] < 0.2
        return
    assert found["z"] >= 3.0 and found["gain_nats"] > 0
    assert abs(np.angle(np.exp(2j * (found["angle_rad"] - angle)))) / 2 < 0.05  # the long axis, as an axis
    assert 0.5 * abs(sigma_cols**2 - sigma_rows**2) < found["variance_difference_px2"] < 2.0 * abs(sigma_cols**2 - sigma_rows**2)


def test_a_scene_diagnosis_names_its_phases_reports_every_second_and_stops_at_once():
    """Every phase is named, the effects' selection reports at least every second, and a stop asked in it ends the diagnosis within 2 s."""
    import time

    import pandas as pd

    from napari_lbs._core import ExperimentConfig, Stopped, particle_hologram
    from napari_lbs._core.gap import SceneDiagnosisSettings, diagnose_scene

    config = ExperimentConfig.from_dict({"volume": {"z_min_um": 1800.0, "z_max_um": 2600.0, "z_step_um": 50.0}})
    spheres = pd.DataFrame({"x_um": [150.0, 420.0], "y_um": [160.0, 400.0], "z_um": [2000.0, 2400.0], "diameter_um": [24.0, 26.0], "index_contrast": [0.26, 0.26]})
    frame = particle_hologram((256, 256), spheres, config) + np.random.default_rng(2).normal(0.0, 0.01, (256, 256))
    settings = SceneDiagnosisSettings(particles=4, scene_particles=8, index_grid=(0.26,), grid=2, level_z=2.0)

    class Listener:
        def __init__(self):
            self.phases, self.times, self.phase_at = [], [time.monotonic()], {}

        def __call__(self, done, total):
            self.times.append(time.monotonic())

        def phase(self, name):
            self.phases.append(name)
            self.times.append(time.monotonic())
            self.phase_at[name.split(" around")[0]] = len(self.times) - 1

    listener = Listener()
    diagnose_scene(frame, config, settings=settings, progress=listener)
    assert any("found" in p for p in listener.phases) and any("optics" in p for p in listener.phases) and any("effects" in p for p in listener.phases)
    # the effects' selection is this engine's own loop (the particle fits report through `refine_particles`, tested there)
    selection = listener.times[listener.phase_at["the catalog's effects"]:]
    assert np.diff(selection).max() < 1.0

    asked = []

    def stop() -> bool:
        if not asked and any("effects" in p for p in listener.phases[-1:]):
            asked.append(time.monotonic())
        return bool(asked)

    listener = Listener()
    with pytest.raises(Stopped):
        diagnose_scene(frame, config, settings=settings, progress=listener, should_stop=stop)
    assert asked and time.monotonic() - asked[0] < 2.0


def test_the_two_colours_fitted_side_by_side_are_those_fitted_one_after_the_other(monkeypatch):
    """With two threads each colour's fit runs on its own; the numbers are those of one thread, and a stop in either ends both."""
    import time

    from napari_lbs._core import Stopped
    from napari_lbs._core.gap import _nested

    data, scene = _frame({"illumination": {"depth": 0.3, "waist": 0.5, "x0": 0.1, "y0": 0.0}, "sensor_blur": {"sigma_px": 0.9}})
    split = TileSplit.of(data.shape)
    monkeypatch.setattr(_nested, "process_threads", lambda: 2)
    side_by_side = fit_frame(data, scene, split, ("illumination", "sensor_blur"))
    monkeypatch.setattr(_nested, "process_threads", lambda: 1)
    serial = fit_frame(data, scene, split, ("illumination", "sensor_blur"))
    assert side_by_side.params == serial.params
    np.testing.assert_array_equal(side_by_side.loglik, serial.loglik)

    monkeypatch.setattr(_nested, "process_threads", lambda: 2)
    ended = []

    def on_colour(colour, heard):
        if colour == 0:
            raise Stopped("asked")
        for _ in range(400):  # the other colour hears the stop within one evaluation
            try:
                heard()
            except Stopped:
                ended.append(colour)
                raise
            time.sleep(0.005)
        return colour

    with pytest.raises(Stopped):
        _nested.both_colours(on_colour, None)
    assert ended == [1]


@pytest.mark.parametrize(("changes", "culprit"), [
    ({"grid": 1}, "grid must be an integer 2-16"),
    ({"grid": 2}, "level_z must be at most grid=2"),
    ({"level_z": float("nan")}, "level_z must be a finite number"),
    ({"index_grid": (0.0,)}, "index_grid must hold index contrasts"),
])
def test_scene_diagnosis_settings_refuse_what_cannot_decide(changes, culprit):
    """A checkerboard of 2 × 2 tiles cannot reach the sign test's z of 3: refused in one line, as are other settings out of range."""
    from napari_lbs._core import InputError
    from napari_lbs._core.gap import SceneDiagnosisSettings

    with pytest.raises(InputError, match=culprit):
        SceneDiagnosisSettings(**changes)


def _spheres_of(index_contrast: float, absorption: float, *, count: int, photons: float | None = None):
    """``count`` spheres of 20–30 µm at 1.9–3.5 mm rendered to 1 cycle per pixel with the given optics, a little read noise or photon noise."""
    import pandas as pd

    from napari_lbs._core import ExperimentConfig, particle_hologram

    config = ExperimentConfig()
    rng = np.random.default_rng(5)
    places = pd.DataFrame({"x_um": rng.uniform(60, 500, count), "y_um": rng.uniform(60, 500, count), "z_um": rng.uniform(1900, 3500, count),
                           "diameter_um": rng.uniform(20, 30, count)})
    frame = particle_hologram((SIZE, SIZE), places.assign(index_contrast=index_contrast, absorption=absorption), config, reach_cycles_per_px=1.0)
    frame = frame + rng.normal(0.0, 0.01, frame.shape) if photons is None else rng.poisson(np.maximum(frame, 0.0) * photons) / photons
    return frame, places, config


@pytest.mark.parametrize(("index_contrast", "absorption", "expected"), [(0.12, 0.0, "transparent"), (0.26, 0.0, "transparent"), (0.2, 0.5, "opaque")])
def test_transparent_spheres_are_told_from_opaque_ones_by_their_fine_rings_spectrum(index_contrast, absorption, expected):
    """Spheres rendered to 1 cycle per pixel with a little noise: the spectrum names their optics and the index contrast of the grid's nearest model, from the places and sizes alone."""
    from napari_lbs._core.gap._optics_power import optics_power_test
    from napari_lbs._core.gap._particle_models import particle_models

    frame, places, config = _spheres_of(index_contrast, absorption, count=8)
    result = optics_power_test(frame, particle_models(frame.shape, places, config, index_grid=(0.12, 0.26, 0.40)), TileSplit.of(frame.shape))
    assert result["model"] == expected, result
    if expected == "transparent":
        assert result["index_contrast"] == index_contrast and abs(result["slope"][f"{index_contrast:g}"] - 1.0) < 0.2
    else:
        assert result["z"] <= -3.0 and abs(result["slope"]["opaque"] - 1.0) < 0.2


@pytest.mark.parametrize(("index_contrast", "absorption", "expected"), [(0.12, 0.0, "transparent"), (0.26, 0.0, "transparent"), (0.2, 0.5, "opaque")])
def test_through_focus_each_sphere_votes_for_the_optics_that_light_its_axis_under_strong_photon_noise(index_contrast, absorption, expected):
    """Twelve spheres under 40 photons a pixel (where the fine rings' spectrum leaves opaque spheres undecided): back-propagated, each sphere's axis is bright behind a ball lens and dark behind an
    opaque sphere, and each votes for its own optics; the nearest transparent model is the grid's nearest contrast."""
    from napari_lbs._core.gap._particle_models import particle_models
    from napari_lbs._core.gap._through_focus import through_focus_test

    frame, places, config = _spheres_of(index_contrast, absorption, count=12, photons=40.0)
    split = TileSplit.of(frame.shape)
    result = through_focus_test(frame, particle_models(frame.shape, places, config, index_grid=(0.12, 0.26, 0.40)), places, config, split)
    assert result["model"] == expected and result["spheres"] == 12, result
    assert result["sphere_tiles"].tolist() == split.labels()[(places["y_um"] / 2.2).round().astype(int), (places["x_um"] / 2.2).round().astype(int)].tolist()
    if expected == "transparent":
        assert result["transparent_better"] == 12 and result["index_contrast"] == index_contrast
    else:
        assert result["transparent_worse"] == 12


def _six_depths() -> Scene:
    """Six depth groups of ring patterns from 1 to 5 mm, on 2 µm pixels (the scene diagnosis renders six)."""
    groups = np.stack([_scene(seed) - 1.0 for seed in (0, 5, 7, 11, 13, 17)]).astype(np.float32)
    return Scene(1.0 + groups.sum(axis=0), (1000.0, 1800.0, 2600.0, 3400.0, 4200.0, 5000.0), groups, 2.0)


def _disc_blur(group: np.ndarray, radius_px: float) -> np.ndarray:
    """``group`` convolved with a uniform disc of ``radius_px``: a source of uniform brightness, not the catalog's Gaussian."""
    extent = int(np.ceil(radius_px))
    yy, xx = np.mgrid[-extent : extent + 1, -extent : extent + 1]
    kernel = (np.hypot(yy, xx) <= radius_px).astype(np.float64)
    from scipy import ndimage

    return ndimage.convolve(group.astype(np.float64), kernel / kernel.sum(), mode="wrap")


@pytest.mark.parametrize("source", ["gaussian", "disc", "sensor"])
def test_the_blur_is_named_by_how_it_grows_with_depth(source):
    """A source's blur grows with depth, a sensor's does not; a disc-shaped source, whose kernel the
    catalog's Gaussian does not have, is still a source alone, with no sensor blur beside it."""
    from napari_lbs._core.gap._blur_depth import attribute_blur, blur_by_depth

    scene = _six_depths()
    if source == "sensor":
        blurred = scene.image
        effects = {"sensor_blur": {"sigma_px": 1.2}}
    elif source == "gaussian":
        blurred, effects = scene.coherent_blur(1.2), {}
    else:
        # a disc of radius 2σ has the rms width of a Gaussian of σ along each axis
        blurred = 1.0 + sum(_disc_blur(g, 2 * 1.2e-3 * z / 2.0) for g, z in zip(scene.groups, scene.depths_um, strict=True))
        effects = {}
    noise = np.random.default_rng(3).standard_normal((SIZE, SIZE)).astype(np.float32)
    image = sensor_image(np.asarray(blurred, np.float32), {"contrast": 1.0, "sigma": 0.01, "gamma": 1.0}, effects, noise=noise).astype(np.float64)
    data = image / image.mean()
    split = TileSplit.of(data.shape)
    selection = select_effects(data, scene, split)
    attributed, profile = attribute_blur(data, scene, split, selection)
    expected = ("sensor_blur",) if source == "sensor" else ("coherence",)
    assert attributed.chosen == expected and profile["origin"] == list(expected)
    assert "+".join(expected) in attributed.fits and not [u for u in attributed.undecided if {u["selected"], u["rival"]} == {"coherence", "sensor_blur"}]
    if source == "sensor":
        assert abs(profile["sensor_sigma_px"] - 1.2) < 0.15 and profile["t_source"] < 3
    else:
        # the disc's pixelated kernel has the Gaussian's rms width but not its transfer function: its size is not the test
        assert profile["t_sensor"] < 3 and (source == "disc" or abs(profile["theta_mrad"] - 1.2) < 0.1)
    with pytest.raises(ValueError, match="at least 4 depth groups"):
        blur_by_depth(data, _depth_scene(), split, selection.fits["baseline"].params, ())


def test_what_the_fits_leave_about_one_depth_group_is_not_read_as_a_source():
    """A sensor's blur, and the deepest group's fringes softened a little more on both colours (a
    group's particles fitted slightly off): the group, not the colour, is the replicate, so
    one group's excess does not make a source's share; read with the colours as replicates,
    its slope's t statistic was 3.6 and the frame was read as a sensor's blur and a source's."""
    from napari_lbs._core.gap._blur_depth import attribute_blur

    scene = _six_depths()
    groups = list(scene.groups)
    groups[-1] = gaussian_blur(groups[-1], 0.45)
    noise = np.random.default_rng(3).standard_normal((SIZE, SIZE)).astype(np.float32)
    truth = (1.0 + np.sum(groups, axis=0)).astype(np.float32)
    image = sensor_image(truth, {"contrast": 1.0, "sigma": 0.01, "gamma": 1.0}, {"sensor_blur": {"sigma_px": 0.7}}, noise=noise).astype(np.float64)
    data = image / image.mean()
    split = TileSplit.of(data.shape)
    attributed, profile = attribute_blur(data, scene, split, select_effects(data, scene, split))
    assert attributed.chosen == ("sensor_blur",) and profile["origin"] == ["sensor_blur"]
    assert profile["dof"] == 4 and profile["z_source"] < 3 <= profile["z_sensor"]
    assert abs(profile["sensor_sigma_px"] - 0.7) < 0.1


def test_a_selection_without_a_blur_is_left_as_it_is():
    from napari_lbs._core.gap._blur_depth import attribute_blur

    data, _ = _frame({"illumination": {"depth": 0.35, "x0": 0.2, "y0": -0.1}})
    scene = _six_depths()
    selection = select_effects(data, _scene(), TileSplit.of(data.shape))
    assert attribute_blur(data, scene, TileSplit.of(data.shape), selection) == (selection, None)


def test_a_vignetting_wider_than_the_default_beam_is_fitted_with_its_waist():
    """cos⁴ vignetting about an off-centre axis (40 % lost at the farthest corner): the envelope's waist is fitted, and it is selected."""
    scene = _scene()
    yy, xx = (np.mgrid[0:SIZE, 0:SIZE] / (SIZE - 1.0))
    distance = np.hypot(xx - 0.45, yy - 0.55)
    focal = distance.max() / np.sqrt((1 - 0.4) ** -0.5 - 1)
    noise = np.random.default_rng(2).standard_normal((SIZE, SIZE)).astype(np.float32)
    image = sensor_image((scene / (1 + (distance / focal) ** 2) ** 2).astype(np.float32), {"contrast": 0.9, "sigma": 0.02, "gamma": 1.0}, {}, noise=noise).astype(np.float64)
    selection = select_effects(image / image.mean(), scene, TileSplit.of(image.shape))
    assert selection.chosen == ("illumination",)
    assert all(fit["illumination.waist"] > 0.5 for fit in selection.fits["illumination"].params)


def test_an_etalon_written_by_hand_is_recovered_within_its_error_bars():
    """A fringe of 4 % and 11.3 px at 0.6 rad, 1.2 rad at the first pixel (not the catalog's code): every parameter within 3 errors."""
    data, scene = _frame({})
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    data = data * (1.0 + 0.04 * np.cos(2 * np.pi * (xx * np.cos(0.6) + yy * np.sin(0.6)) / 11.3 + 1.2))
    fit = fit_frame(data, scene, TileSplit.of(data.shape), ("parasitic_fringes",))
    for name, truth in (("amplitude", 0.04), ("period_px", 11.3), ("angle_rad", 0.6), ("phase_rad", 1.2)):
        value, error = fit.estimate(f"parasitic_fringes.{name}")
        assert 0 < error < 0.05 * abs(truth)
        assert abs(value - truth) <= 3 * error, name


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize(("effects", "truth"), [
    ({"sensor_blur": {"sigma_px": 1.2}}, {"sensor_blur.sigma_px": 1.2}),
    ({"illumination": {"depth": 0.35, "x0": 0.2, "y0": -0.1}}, {"illumination.depth": 0.35, "illumination.x0": 0.2, "illumination.y0": -0.1}),
])
def test_a_catalog_effect_is_recovered_within_its_error_bars(effects, truth, seed):
    data, scene = _frame(effects, seed=seed)
    fit = fit_frame(data, scene, TileSplit.of(data.shape), tuple(effects))
    for name, value in truth.items():
        estimate, error = fit.estimate(name)
        assert abs(estimate - value) <= 3 * error, (name, estimate, error)


def test_the_halves_disagreeing_widen_the_error_of_their_mean():
    """Two colours' fits are two measurements: the mean's error is their errors' half quadrature sum, or half their difference if larger."""
    from napari_lbs._core.gap._nested import FrameFit

    def fit(first, second, errors):
        return FrameFit(("sensor_blur",), ({"sensor_blur.sigma_px": first}, {"sensor_blur.sigma_px": second}), np.zeros(16), (None, None), (None, None),
                        tuple({"sensor_blur.sigma_px": e} for e in errors))

    assert fit(1.0, 1.02, (0.03, 0.04)).estimate("sensor_blur.sigma_px") == pytest.approx((1.01, 0.025))
    assert fit(1.0, 1.2, (0.03, 0.04)).estimate("sensor_blur.sigma_px") == pytest.approx((1.1, 0.1))
    assert np.isnan(fit(1.0, 1.2, (np.nan, 0.04)).estimate("sensor_blur.sigma_px")[1])  # on a bound in one half


def test_a_named_effect_reports_the_named_model_s_numbers_and_another_its_own():
    """The report's parameters: an effect the verdict names, as fitted together with the other named ones; an effect it does not name, fitted alone."""
    from napari_lbs._core.gap._nested import FrameFit, Selection
    from napari_lbs._core.gap._scene_diagnosis import _estimates

    def fit(values):
        return FrameFit(tuple({name.split(".")[0] for name in values}), (values, values), np.zeros(16), (None, None), (None, None),
                        (dict.fromkeys(values, 0.01), dict.fromkeys(values, 0.01)))

    fits = {"illumination": fit({"gain": 1.0, "illumination.depth": 0.36}), "sensor_blur": fit({"gain": 1.0, "sensor_blur.sigma_px": 1.019}),
            "coherence": fit({"gain": 1.0, "coherence.theta_mrad": 0.61}),
            "illumination+sensor_blur": fit({"gain": 1.0, "illumination.depth": 0.31, "sensor_blur.sigma_px": 1.021})}
    selection = Selection(("illumination", "sensor_blur"), fits, [], {}, {})
    error = 0.5 * np.hypot(0.01, 0.01)  # each colour's 0.01, the colours agreeing
    assert _estimates("illumination", selection) == {"depth": pytest.approx((0.31, error))}
    assert _estimates("sensor_blur", selection) == {"sigma_px": pytest.approx((1.021, error))}
    assert _estimates("coherence", selection) == {"theta_mrad": pytest.approx((0.61, error))} and _estimates("parasitic_fringes", selection) == {}


def test_photon_noise_blurred_by_the_camera_is_read_through_the_fitted_blur():
    """Photons then a charge-sharing blur of σ 1 px: the band ratio is blurred noise's (about 12), not white noise's.

    The photons are measured per unit of the recorded pixel's variance, the catalog's white
    noise of the same variance: 100 photons blurred by a kernel of Σg² = 1 / (4π) are 1 257.
    """
    from napari_lbs._core.gap._nested import shot_noise_test
    from napari_lbs._core.physics import gaussian_blur

    scene = _scene()
    light = sensor_image(scene.astype(np.float32), {"contrast": 0.9, "sigma": 0.0, "gamma": 1.0}, {}, noise=np.zeros((SIZE, SIZE), np.float32)).astype(np.float64)
    rng = np.random.default_rng(5)
    recorded = gaussian_blur(rng.poisson(light / light.mean() * 100.0) / 100.0, 1.0) + rng.normal(0.0, 0.002, light.shape)
    data = recorded / recorded.mean()
    split = TileSplit.of(data.shape)
    fit = fit_frame(data, scene, split, ("sensor_blur",))
    result = shot_noise_test(fit, split)
    assert result["z"] > 2.0 and result["white"] and result["noise_blur_px"] > 0.8  # blurred noise holds fewer independent samples: z 2.5–3.5 over seeds
    assert all(6.0 < ratio < 24.0 for ratio in result["band_ratios"]) and abs(result["log10_photons"] - np.log10(100.0 * 4 * np.pi)) < 0.3


def _flat_spectrum(scene: Scene, width_nm: float, wavelength_um: float = 0.66) -> np.ndarray:
    """Each depth group's rings summed over 7 wavelengths of a flat spectrum ``width_nm`` wide: at λ' a
    group at depth z shows the rings it shows at λ from z λ'/λ, the real part of Fresnel's kernel
    for the difference (written here, apart from `Scene.spectral_blur`'s Gaussian law)."""
    f2 = np.fft.fftfreq(SIZE, scene.pixel_um)[:, None] ** 2 + np.fft.fftfreq(SIZE, scene.pixel_um)[None, :] ** 2
    image = np.ones((SIZE, SIZE))
    for group, depth in zip(scene.groups, scene.depths_um, strict=True):
        spectrum = np.fft.fft2(group)
        for offset_um in np.linspace(-0.5, 0.5, 7) * width_nm * 1e-3:
            image += np.fft.ifft2(spectrum * np.cos(np.pi * wavelength_um * depth * (offset_um / wavelength_um) * f2)).real / 7
    return image


@pytest.mark.parametrize("source", ["spectrum", "sensor", "source"])
def test_a_spectrum_s_width_takes_the_named_blur_s_place_only_where_the_frame_holds_one(source):
    """A flat spectrum washes deep groups' fine rings out (f⁴ · z²): read as coherence with its width; a
    sensor's blur and a source's size keep their names."""
    from napari_lbs._core.gap._blur_depth import attribute_blur, spectrum_width_test

    scene = _six_depths()
    effects = {}
    if source == "spectrum":
        blurred = _flat_spectrum(scene, 30.0)
    elif source == "sensor":
        blurred, effects = scene.image, {"sensor_blur": {"sigma_px": 1.2}}
    else:
        blurred = scene.coherent_blur(1.2)
    noise = np.random.default_rng(3).standard_normal((SIZE, SIZE)).astype(np.float32)
    image = sensor_image(np.asarray(blurred, np.float32), {"contrast": 1.0, "sigma": 0.01, "gamma": 1.0}, effects, noise=noise).astype(np.float64)
    data = image / image.mean()
    split = TileSplit.of(data.shape)
    selection, _ = attribute_blur(data, scene, split, select_effects(data, scene, split))
    swapped, test = spectrum_width_test(data, scene, split, selection)
    assert test is not None and test["replaces"] == [e for e in selection.chosen if e in ("coherence", "sensor_blur")]
    if source == "spectrum":
        assert test["named"] and swapped.chosen == ("coherence",)
        assert "coherence.bandwidth_nm" in swapped.fits["coherence"].params[0] and 15.0 <= test["bandwidth_nm"] <= 36.0
        # photon noise judged again on the swapped model, where no sensor blur blurs the camera's noise
        assert swapped.shot_noise is not selection.shot_noise and swapped.shot_noise["noise_blur_px"] == 0.0
    else:
        assert not test["named"] and swapped is selection and test["z"] < 0
