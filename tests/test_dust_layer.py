"""Dust on a window outside the volume, found as a layer of grains in what the frame's model leaves and among the scene's particles (`dust_layer`); report.md's sections of the tests run after the selection."""

import dataclasses

import numpy as np
import pytest

from napari_lbs._core import load_config
from napari_lbs._core.gap._dust_layer import LAYER_TILES, dust_layer, dust_search_ranges_um, in_window, outside_volume
from napari_lbs._core.gap._heldout import TileSplit
from napari_lbs._core.refine import RefineSettings

SIZE = 384


def _dusty_window(distance_um: float, *, grains: int, seed: int, noise: float = 0.01) -> np.ndarray:
    """Light behind opaque discs ``distance_um`` before the sensor, with read noise (unobstructed 1).

    Written here (Fresnel's paraxial transfer function on a grid twice the frame's, so that
    grains outside the frame send their rings in), apart from the Lorenz–Mie fits that
    find the grains.
    """
    config = load_config()
    pixel, wavelength = config.optics.pixel_um, config.optics.wavelength_um
    rng = np.random.default_rng(seed)
    grid = 2 * SIZE
    yy, xx = np.mgrid[0:grid, 0:grid]
    opaque = np.zeros((grid, grid))
    for _ in range(grains):
        radius_px = rng.uniform(6.0, 25.0) / 2 / pixel
        cy, cx = rng.uniform(0.3 * grid, 0.7 * grid, size=2)
        opaque[(yy - cy) ** 2 + (xx - cx) ** 2 <= radius_px**2] = 1.0
    f = np.fft.fftfreq(grid, pixel)
    kernel = np.exp(-1j * np.pi * wavelength * distance_um * (f[:, None] ** 2 + f[None, :] ** 2))
    light = np.abs(1.0 - np.fft.ifft2(np.fft.fft2(opaque) * kernel)) ** 2
    frame = light[SIZE // 2 : SIZE // 2 + SIZE, SIZE // 2 : SIZE // 2 + SIZE]
    return frame + noise * rng.standard_normal(frame.shape)


def _settings() -> RefineSettings:
    return RefineSettings(min_gain=0.0, workers=1)


def test_a_dusty_window_is_named_at_its_distance_with_its_rings_zone():
    config = load_config()
    distance_um = 12000.0
    found = dust_layer(_dusty_window(distance_um, grains=14, seed=3), config, TileSplit.of((SIZE, SIZE)), settings=_settings())
    assert found["searched"] and found["named"]
    assert found["in_layer"] >= LAYER_TILES
    assert found["depth_um"] == pytest.approx(distance_um, rel=0.05)
    zone_px = np.sqrt(config.optics.wavelength_um * distance_um) / config.optics.pixel_um
    assert found["params"]["dust_zone_px"] == pytest.approx(zone_px, rel=0.03)
    assert abs(found["params"]["dust_zone_px"] - zone_px) <= 3.0 * found["params_err"]["dust_zone_px"] + 0.01 * zone_px
    assert found["z"] == pytest.approx(np.sqrt(np.count_nonzero(found["tiles"])))


def test_a_frame_of_noise_holds_no_dust():
    noise = 1.0 + 0.01 * np.random.default_rng(5).standard_normal((SIZE, SIZE))
    found = dust_layer(noise, load_config(), TileSplit.of((SIZE, SIZE)), settings=_settings())
    assert found["searched"] and not found["named"]
    assert found["in_layer"] == 0 and found["z"] == 0.0


def test_a_window_within_the_volume_s_depths_is_not_named():
    """A plane of grains at the volume's own depths is the sample's business: the window search looks outside it."""
    config = load_config()
    middle_um = 0.5 * (config.volume.z_min_um + config.volume.z_max_um)
    found = dust_layer(_dusty_window(middle_um, grains=14, seed=3), config, TileSplit.of((SIZE, SIZE)), settings=_settings())
    assert all(not (near <= middle_um <= far) for near, far in dust_search_ranges_um(config))
    assert not found["named"]


def test_the_scene_s_particles_fitted_outside_the_volume_in_one_plane_are_a_window_s_grains():
    """Grains near the volume focus within the finder's depths and their fits take them out: the scene's such particles make a layer without a search."""
    import pandas as pd

    config = load_config()
    split = TileSplit.of((SIZE, SIZE))
    pixel = config.optics.pixel_um
    near_um = 0.6 * config.volume.z_min_um  # in front of the volume, between it and the sensor
    # four grains in one plane, each on its own tile, among six of the sample's particles
    corners = [(0.1, 0.1), (0.1, 0.9), (0.9, 0.1), (0.9, 0.9)]
    grains = pd.DataFrame({"x_um": [c * SIZE * pixel for c, _ in corners], "y_um": [r * SIZE * pixel for _, r in corners],
                           "z_um": near_um * np.array([1.0, 1.01, 0.99, 1.02]), "diameter_um": 20.0, "index_contrast": 0.3, "absorption": 0.5})
    sample = pd.DataFrame({"x_um": np.linspace(50, 700, 6), "y_um": np.linspace(80, 600, 6), "z_um": np.linspace(config.volume.z_min_um, config.volume.z_max_um, 6),
                           "diameter_um": 25.0, "index_contrast": 0.26, "absorption": 0.0})
    scene = pd.concat([sample.iloc[:3], grains, sample.iloc[3:]], ignore_index=True)
    assert outside_volume(scene, config).tolist() == [False] * 3 + [True] * 4 + [False] * 3
    found = dust_layer(np.ones((SIZE, SIZE)), config, split, settings=_settings(), scene=scene, search=False)
    assert found["named"] and not found["searched"]
    assert in_window(scene, found, config).tolist() == [False] * 3 + [True] * 4 + [False] * 3
    assert found["depth_um"] == pytest.approx(near_um, rel=0.02) and found["in_layer"] == 4
    assert found["table"]["in_scene"].all()
    # three of them on one tile are not a window
    crowded = grains.assign(x_um=[10.0, 30.0, 50.0, 500.0], y_um=[10.0, 30.0, 50.0, 500.0])
    found = dust_layer(np.ones((SIZE, SIZE)), config, split, settings=_settings(), scene=crowded, search=False)
    assert not found["named"] and found["in_layer"] == 4


def test_a_microscope_s_rings_leave_no_depth_outside_the_volume_to_search():
    config = load_config()
    microscope = dataclasses.replace(config, optics=dataclasses.replace(config.optics, pixel_um=0.1))
    assert dust_search_ranges_um(microscope) == ()
    found = dust_layer(np.ones((SIZE, SIZE)), microscope, TileSplit.of((SIZE, SIZE)), settings=_settings())
    assert not found["searched"] and not found["named"]


def test_report_md_says_where_the_dusty_window_is_and_whether_a_spectrum_took_the_blur_s_place(tmp_path):
    import pandas as pd
    from scene_reports import scene_report

    from napari_lbs._core import SceneDiagnosis, write_report

    report = scene_report("parasitic_fringes", explains=False)
    next(e for e in report["effects"] if e["id"] == "parasitic_fringes")["dust_z"] = 2.0
    report["dust_layer"] = {"searched": True, "named": True, "z": 2.0, "grains": 6, "in_layer": 5, "depth_um": 12345.0, "tiles_with_grains": 4,
                            "params": {"dust_per_mpx": 20.0, "dust_zone_px": 39.4, "dust_grain_px": 6.5}, "layer_grains": {}}
    table = pd.DataFrame({"x_um": [10.0], "y_um": [10.0], "z_um": [2000.0], "diameter_um": [25.0]})
    write_report(SceneDiagnosis(report, np.zeros((2, 2)), table), tmp_path / "r")
    text = (tmp_path / "r" / "report.md").read_text()
    assert "5 of 6 significant grains lie in one plane 12.35 mm away, on 4 tiles" in text and "**named**" in text
    assert "first Fresnel zone 39.4 px" in text
    assert "| parasitic_fringes | yes (a window's dust: z 2.00 from its grains' tiles) |" in text
    report["spectrum_width"] = {"replaces": ["sensor_blur"], "gain_nats": 7934.0, "z": 4.0, "bandwidth_nm": 17.2, "bandwidth_nm_err": 0.5, "named": True}
    write_report(SceneDiagnosis(report, np.zeros((2, 2)), table), tmp_path / "r", force=True)
    assert "In place of sensor_blur: held-out gain 7934 nats, z 4.0, full width 17.2 nm; **coherence as a spectrum's width takes its place**" in (
        tmp_path / "r" / "report.md").read_text()
    del report["dust_layer"], report["spectrum_width"]
    write_report(SceneDiagnosis(report, np.zeros((2, 2)), table), tmp_path / "r", force=True)
    assert "Dust on a window" not in (tmp_path / "r" / "report.md").read_text()


def test_a_named_window_is_divided_out_and_the_frame_fitted_and_judged_again(monkeypatch):
    """Where searched grains name a window, the frame is fitted and judged again divided by their hologram (floored), and the report names the dust."""
    import pandas as pd

    import napari_lbs._core.gap._scene_diagnosis as scene_diagnosis
    from napari_lbs._core import ExperimentConfig, particle_hologram
    from napari_lbs._core.gap import SceneDiagnosisSettings, diagnose_scene

    config = ExperimentConfig.from_dict({"volume": {"z_min_um": 1800.0, "z_max_um": 2600.0, "z_step_um": 50.0}})
    spheres = pd.DataFrame({"x_um": [150.0, 420.0], "y_um": [160.0, 400.0], "z_um": [2000.0, 2400.0], "diameter_um": [24.0, 26.0], "index_contrast": [0.26, 0.26]})
    grain = pd.DataFrame({"x_um": [300.0], "y_um": [250.0], "z_um": [12000.0], "diameter_um": [40.0], "index_contrast": [0.3], "absorption": [1.0], "in_scene": [False]})
    frame = particle_hologram((256, 256), spheres, config) + np.random.default_rng(2).normal(0.0, 0.01, (256, 256))
    settings = SceneDiagnosisSettings(particles=4, scene_particles=8, index_grid=(0.26,), grid=2, level_z=2.0, structure_level=0.0)
    window = {"searched": True, "named": True, "z": 2.0, "tiles": np.array([1.0, 1.0, 1.0, 1.0]), "grains": 1, "in_layer": 1, "depth_um": 12000.0,
              "params": {"dust_per_mpx": 15.0, "dust_zone_px": 40.0, "dust_grain_px": 9.0}, "params_err": {"dust_per_mpx": 15.0, "dust_zone_px": 0.1, "dust_grain_px": 0.5},
              "table": grain}
    monkeypatch.setattr(scene_diagnosis, "dust_layer", lambda *args, **kwargs: window)
    seen = []
    judged = scene_diagnosis._judged
    monkeypatch.setattr(scene_diagnosis, "_judged", lambda data, *args, **kwargs: (seen.append(data.copy()), judged(data, *args, **kwargs))[1])
    report = diagnose_scene(frame, config, settings=settings).report
    assert len(seen) == 2
    light = frame / frame.mean()
    cleared = light / np.maximum(particle_hologram(frame.shape, grain, config, settings=settings.refine), 0.2)
    np.testing.assert_allclose(seen[1], cleared / cleared.mean(), rtol=1e-6)
    assert report["dust_layer"]["named"] and "parasitic_fringes" in report["verdict"]["id"].split("+")
    assert report["scene"]["particles"] == 2
    # the scene alone on the recorded frame, beside the frame divided by the window
    recorded = report["gap"]["baseline_recorded_frame"]
    assert isinstance(recorded, float) and 0.0 <= recorded <= 1.0 and recorded != report["gap"]["baseline"]
