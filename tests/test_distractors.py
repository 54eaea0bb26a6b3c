"""Unlabelled distractors in the training data: impurities and neighbours outside the window."""

import json

import numpy as np
import pytest

from napari_lbs._cli import main
from napari_lbs._core import (
    DatasetLayout,
    Distractors,
    ExperimentConfig,
    InputError,
    ParticleField,
    generate_dataset,
    open_dataset,
    random_particle_field,
    simulate_hologram,
)
from napari_lbs._core.physics._synthesis import distractor_scene

CONFIG = ExperimentConfig.from_dict({"tile": {"size": 64}, "particles": {"per_tile": 3}, "volume": {"z_min_um": 1800.0, "z_max_um": 2000.0, "z_step_um": 50.0}})
OPTICS = {"wavelength_um": 0.66, "medium_index": 1.0}


def _field(count=5, seed=0):
    return random_particle_field((64, 64), count=count, diameter_min_um=20, diameter_max_um=30, layers_um=(1800.0, 2000.0), continuous=True, pixel_um=2.2, seed=seed)


def _scene(field, distractors, rng):
    return distractor_scene(field, distractors, tile_px=64, depth_range_um=(1800.0, 2000.0), diameter_range_um=(20.0, 30.0), rng=rng)


def test_an_inactive_distractor_set_changes_nothing_and_draws_nothing():
    field, rng = _field(), np.random.default_rng(1)
    state = rng.bit_generator.state
    assert _scene(field, Distractors(), rng) is field
    assert rng.bit_generator.state == state  # data sets made before distractors existed stay the same


def test_neighbours_fill_the_margin_and_impurities_the_widened_window():
    field, margin = _field(count=8), 32
    scene = _scene(field, Distractors(impurities_per_tile=4, impurity_diameter_min_um=5.0, impurity_diameter_max_um=9.0, neighbours_margin_px=margin), np.random.default_rng(2))
    assert scene.shape == (128, 128)
    ratio = 128**2 / 64**2
    neighbours, impurities = round(8 * (ratio - 1)), round(4 * ratio)
    assert len(scene) == 8 + neighbours + impurities
    shift = margin * 2.2
    np.testing.assert_allclose(scene.x_um[:8], field.x_um + shift)  # the labelled particles first, in the window
    np.testing.assert_allclose(scene.y_um[:8], field.y_um + shift)
    nx, ny = scene.x_um[8 : 8 + neighbours], scene.y_um[8 : 8 + neighbours]
    inside = (nx >= shift) & (nx <= shift + 63 * 2.2) & (ny >= shift) & (ny <= shift + 63 * 2.2)
    assert not inside.any()
    assert np.all((scene.diameter_um[8 : 8 + neighbours] >= 20) & (scene.diameter_um[8 : 8 + neighbours] <= 30))
    d = scene.diameter_um[8 + neighbours :]
    assert np.all((d >= 5.0) & (d <= 9.0))
    assert np.all((scene.z_um >= 1800.0) & (scene.z_um <= 2000.0))
    assert np.all((scene.x_um >= 0) & (scene.x_um <= 127 * 2.2))
    with pytest.raises(InputError, match="impurity_diameter_min_um"):
        Distractors(impurity_diameter_min_um=10.0, impurity_diameter_max_um=5.0)


def test_a_widened_scenes_window_holds_its_particles_in_place_and_its_neighbours_fringes():
    margin = 24
    one = ParticleField(np.array([30 * 2.2]), np.array([20 * 2.2]), np.array([1900.0]), np.array([25.0]), (64, 64), 2.2)
    scene = _scene(one, Distractors(neighbours_margin_px=margin), np.random.default_rng(0))
    # the labelled particle alone (the scene lists it first), simulated on the widened window
    window = simulate_hologram(ParticleField(scene.x_um[:1], scene.y_um[:1], scene.z_um[:1], scene.diameter_um[:1], scene.shape, 2.2), **OPTICS)[margin:-margin, margin:-margin]
    # the sphere's pattern is centred on its pixel (row 20, column 30) of the window
    np.testing.assert_allclose(window[20, 30 - 12 : 30], window[20, 31 : 30 + 13][::-1], atol=1e-4)
    np.testing.assert_allclose(window[20 - 12 : 20, 30], window[21 : 20 + 13, 30][::-1], atol=1e-4)
    assert np.abs(window[10:31, 20:41] - 1).max() > 0.2
    # a neighbour 15 um outside the window puts its fringes into it
    outside = ParticleField(np.array([margin * 2.2 - 15.0]), np.array([(margin + 32) * 2.2]), np.array([1900.0]), np.array([25.0]), (112, 112), 2.2)
    fringes = simulate_hologram(outside, **OPTICS)[margin:-margin, margin:-margin]
    assert np.abs(fringes[:, :10] - 1).max() > 0.2 and np.abs(fringes[:, -10:] - 1).max() < 0.05


def test_generate_keeps_the_labels_and_records_the_distractors(tmp_path):
    layout = DatasetLayout(context_planes=1)
    distractors = Distractors(impurities_per_tile=3, neighbours_margin_px=16)
    plain = generate_dataset(tmp_path / "plain", CONFIG, groups=1, layout=layout, seed=3)
    generate_dataset(tmp_path / "busy", CONFIG, groups=1, layout=layout, seed=3, distractors=distractors)
    spec = json.loads((tmp_path / "busy" / "dataset.json").read_text())
    assert spec["distractors"] == distractors.to_dict()
    assert "distractors" not in json.loads((tmp_path / "plain" / "dataset.json").read_text())
    plain_inputs, plain_labels, plain_description = plain.read_group(0)
    busy_inputs, busy_labels, busy_description = open_dataset(tmp_path / "busy").read_group(0)
    np.testing.assert_array_equal(plain_labels, busy_labels)  # the same particles, and only they, labelled
    assert plain_description["particles"] == busy_description["particles"]
    assert np.abs(plain_inputs.astype(np.float32) - busy_inputs.astype(np.float32)).max() > 0.05  # the distractors are in the light
    with pytest.raises(InputError, match="differs in distractors"):
        generate_dataset(tmp_path / "busy", CONFIG, groups=1, layout=layout, seed=3)
    with pytest.raises(InputError, match="impurity_diameter_max_um"):
        generate_dataset(tmp_path / "big", CONFIG, groups=1, layout=layout, distractors=Distractors(impurities_per_tile=1, impurity_diameter_max_um=25.0))


def test_cli_generate_with_distractors_and_a_refusal(tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text('[tile]\nsize = 64\n[particles]\nper_tile = 2\nlayer_step_um = 50.0\n[volume]\nz_min_um = 1800.0\nz_max_um = 1900.0\n')
    out = tmp_path / "data"
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(out), "--context-planes", "1", "--impurities", "2", "--neighbours-margin-px", "8"]) == 0
    assert json.loads((out / "dataset.json").read_text())["distractors"]["impurities_per_tile"] == 2
    assert "unlabelled distractors" in capsys.readouterr().err
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(tmp_path / "x"), "--impurities", "2", "--impurity-diameter-um", "10", "22"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "--impurity-diameter-um" in error[0]
    assert not (tmp_path / "x").exists()
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(tmp_path / "z"), "--neighbours-margin-px", "8", "--impurity-diameter-um", "10", "5"]) == 2
    assert "--impurity-diameter-um" in capsys.readouterr().err
    # without impurities their diameters shape nothing, so they are no part of the set's identity
    assert Distractors(neighbours_margin_px=8).to_dict() == Distractors(neighbours_margin_px=8, impurity_diameter_min_um=1.0).to_dict() == {"impurities_per_tile": 0, "neighbours_margin_px": 8}


def _scene_report(per_256px_tile: float, sizes) -> dict:
    """A diagnosis report naming nothing, whose scene measured small scatterers."""
    return {"verdict": {"id": None}, "effects": [], "scene": {"small_scatterers": {"count": 3, "per_256px_tile": per_256px_tile, "diameter_um": sizes}}}


def test_the_small_scatterers_a_report_measured_become_impurities_scaled_to_the_tile():
    from napari_lbs._core.physics import distractors_from_report

    measured = distractors_from_report(_scene_report(1.6, [11.2, 19.5]), tile_px=256, diameter_min_um=20.0)
    assert measured == Distractors(impurities_per_tile=2, impurity_diameter_min_um=11.2, impurity_diameter_max_um=19.5)
    assert distractors_from_report(_scene_report(1.6, [11.2, 19.5]), tile_px=512, diameter_min_um=20.0).impurities_per_tile == 6
    # a size at the particles' own lower bound is kept just below it, as the generator needs
    assert distractors_from_report(_scene_report(2.0, [12.0, 20.0]), tile_px=256, diameter_min_um=20.0).impurity_diameter_max_um == pytest.approx(19.6)
    assert distractors_from_report(_scene_report(0.4, [11.2, 19.5]), tile_px=256, diameter_min_um=20.0) == Distractors()  # under half a scatterer a tile
    assert distractors_from_report(_scene_report(0.0, None), tile_px=256, diameter_min_um=20.0) == Distractors()
    assert distractors_from_report({"verdict": {"id": None}, "effects": []}, tile_px=256, diameter_min_um=20.0) == Distractors()  # no scene: an older report
    for broken, culprit in (({"small_scatterers": {}}, "missing"), ({"small_scatterers": {"per_256px_tile": -1.0, "diameter_um": [1.0, 2.0]}}, "per_256px_tile"),
                            ({"small_scatterers": {"per_256px_tile": 2.0, "diameter_um": [5.0, "x"]}}, "diameter_um"),
                            ({"small_scatterers": {"per_256px_tile": 2.0, "diameter_um": [9.0, 5.0]}}, "diameter_um")):
        with pytest.raises(InputError, match=f"^r.json: scene: small_scatterers: .*{culprit}"):
            distractors_from_report({"scene": broken}, tile_px=256, diameter_min_um=20.0, name="r.json")


def test_cli_generate_takes_the_report_s_small_scatterers_unless_told_otherwise(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text('[tile]\nsize = 64\n[particles]\nper_tile = 2\nlayer_step_um = 50.0\n[volume]\nz_min_um = 1800.0\nz_max_um = 1900.0\n')
    report = tmp_path / "report.json"
    report.write_text(json.dumps(_scene_report(32.0, [6.0, 12.0])))  # 2 per 64-pixel tile
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(tmp_path / "a"), "--context-planes", "1", "--effects-from", str(report)]) == 0
    spec = json.loads((tmp_path / "a" / "dataset.json").read_text())
    assert spec["distractors"] == {"impurities_per_tile": 2, "impurity_diameter_min_um": 6.0, "impurity_diameter_max_um": 12.0, "neighbours_margin_px": 0}
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(tmp_path / "b"), "--context-planes", "1", "--effects-from", str(report), "--impurities", "0"]) == 0
    assert "distractors" not in json.loads((tmp_path / "b" / "dataset.json").read_text())


def _particles_report(particles: int, median_diameter_um: float, median_z_um: float) -> dict:
    report = _scene_report(0.0, None)
    report["scene"].update(particles=particles, in_size_range=particles, percentiles=[5, 25, 50, 75, 95],
                           diameter_um=[f * median_diameter_um for f in (0.8, 0.9, 1.0, 1.05, 1.1)],
                           z_um=[2000.0, 3000.0, median_z_um, 4000.0, 4500.0])
    return report


def test_the_neighbours_margin_is_two_airy_radii_of_the_scenes_median_particle():
    from napari_lbs._core.physics import distractors_from_report

    optics = {"wavelength_um": 0.66, "pixel_um": 2.2}
    # 2 x 1.22 x 0.66 um x 3500 um / 25 um = 225.4 um = 102.5 px
    assert distractors_from_report(_particles_report(40, 25.0, 3500.0), tile_px=256, diameter_min_um=20.0, **optics).neighbours_margin_px == 103
    assert distractors_from_report(_particles_report(40, 25.0, 3500.0), tile_px=256, diameter_min_um=20.0, medium_index=1.33, **optics).neighbours_margin_px == 78
    assert distractors_from_report(_particles_report(40, 5.0, 3500.0), tile_px=256, diameter_min_um=20.0, **optics).neighbours_margin_px == 128  # half a tile at most
    assert distractors_from_report(_particles_report(9, 25.0, 3500.0), tile_px=256, diameter_min_um=20.0, **optics).neighbours_margin_px == 0  # too few fitted
    assert distractors_from_report(_particles_report(40, 25.0, 3500.0), tile_px=256, diameter_min_um=20.0).neighbours_margin_px == 0  # no optics given
    with pytest.raises(InputError, match="r.json: scene: the median"):
        distractors_from_report(_particles_report(40, float("nan"), 3500.0), tile_px=256, diameter_min_um=20.0, name="r.json", **optics)


def test_cli_generate_takes_the_reports_neighbours_margin_unless_told_otherwise(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text('[tile]\nsize = 64\n[particles]\nper_tile = 2\nlayer_step_um = 50.0\n[volume]\nz_min_um = 1800.0\nz_max_um = 1900.0\n')
    report = tmp_path / "report.json"
    report.write_text(json.dumps(_particles_report(40, 100.0, 1850.0)))  # 2 x 1.22 x 0.66 x 1850 / 100 um = 29.8 um: 14 px of 2.2 um
    common = ["generate", "--config", str(config), "--groups", "1", "--context-planes", "1", "--effects-from", str(report)]
    assert main([*common, "--out", str(tmp_path / "a")]) == 0
    assert json.loads((tmp_path / "a" / "dataset.json").read_text())["distractors"]["neighbours_margin_px"] == 14
    assert main([*common, "--out", str(tmp_path / "b"), "--neighbours-margin-px", "0"]) == 0
    assert "distractors" not in json.loads((tmp_path / "b" / "dataset.json").read_text())
