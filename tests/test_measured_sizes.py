"""Particle sizes a diagnosis measured, as the training data's size distribution."""

import json

import numpy as np
import pytest

from napari_lbs._cli import main
from napari_lbs._core import ExperimentConfig, InputError, generate_dataset, random_particle_field
from napari_lbs._core.physics import SizeDistribution, sizes_from_report

LEVELS = (0.05, 0.25, 0.5, 0.75, 0.95)
MEASURED_UM = (23.9, 24.9, 25.3, 25.9, 26.5)  # a polystyrene sample's fitted quantiles


def _report(diameters=list(MEASURED_UM), counted=97, percentiles=(5, 25, 50, 75, 95)) -> dict:
    """A diagnosis report naming nothing, whose scene fitted ``counted`` particles within its sizes."""
    scene = {"particles": counted, "in_size_range": counted, "percentiles": list(percentiles), "diameter_um": diameters,
             "small_scatterers": {"count": 0, "per_256px_tile": 0.0, "diameter_um": None}}
    return {"verdict": {"id": None}, "effects": [], "scene": scene}


def test_draws_follow_the_measured_quantiles_within_the_config_s_range():
    sizes = SizeDistribution(LEVELS, MEASURED_UM)
    drawn = sizes.draw(np.random.default_rng(0), 40_000, diameter_min_um=20.0, diameter_max_um=30.0)
    assert drawn.min() >= 20.0 and drawn.max() <= 30.0
    # the inverse transform reproduces each given quantile to its sampling error (~0.02 µm here)
    np.testing.assert_allclose(np.quantile(drawn, LEVELS), MEASURED_UM, atol=0.06)
    # the tails reach out to the range's bounds, linearly: 5 % below 23.9 µm, spread over 20-23.9
    assert np.mean(drawn < 21.95) == pytest.approx(0.025, abs=0.004)


def test_without_sizes_a_field_s_diameters_are_the_seed_s_uniform_draw():
    field = random_particle_field((64, 64), count=7, diameter_min_um=20.0, diameter_max_um=30.0, layers_um=(1800.0,), pixel_um=2.2, seed=3)
    np.testing.assert_array_equal(field.diameter_um, np.random.default_rng(3).uniform(20.0, 30.0, 7))  # data sets made before stay the same
    measured = random_particle_field((64, 64), count=200, diameter_min_um=20.0, diameter_max_um=30.0, layers_um=(1800.0,), pixel_um=2.2, seed=3,
                                     sizes=SizeDistribution(LEVELS, MEASURED_UM))
    assert 24.9 < np.median(measured.diameter_um) < 25.7


def test_a_report_s_scene_gives_its_sizes_or_none_where_it_measured_too_few():
    sizes = sizes_from_report(_report(), diameter_range_um=(20.0, 30.0))
    assert sizes == SizeDistribution(LEVELS, MEASURED_UM)
    assert sizes_from_report(_report(counted=9), diameter_range_um=(20.0, 30.0)) is None  # five quantiles of nine particles
    assert sizes_from_report(_report(diameters=None, counted=0), diameter_range_um=(20.0, 30.0)) is None
    assert sizes_from_report({"verdict": {"id": None}, "effects": []}, diameter_range_um=(20.0, 30.0)) is None  # no scene
    assert sizes_from_report(_report(), diameter_range_um=(10.0, 25.0)) is None  # measured with other sizes than the data's config
    for report, culprit in ((_report(counted="many"), "in_size_range"), (_report(diameters=[25.0, 24.0, 26.0, 27.0, 28.0]), "non-decreasing"),
                            (_report(percentiles=(5, 25, 50, 75, 105)), "levels"), (_report(diameters=[25.0, "x", 26.0, 27.0, 28.0]), "diameter_um"),
                            (_report(diameters=[25.0, 26.0]), "equally long")):
        with pytest.raises(InputError, match=f"^r.json: scene: .*{culprit}") as error:
            sizes_from_report(report, diameter_range_um=(20.0, 30.0), name="r.json")
        assert "\n" not in str(error.value)


def test_a_set_made_with_other_sizes_is_not_extended(tmp_path):
    config = ExperimentConfig.from_dict({"tile": {"size": 32}, "particles": {"per_tile": 2, "layer_step_um": 100.0},
                                         "volume": {"z_min_um": 1800.0, "z_max_um": 1900.0, "z_step_um": 100.0}})
    sizes = SizeDistribution(LEVELS, MEASURED_UM)
    dataset = generate_dataset(tmp_path / "d", config, groups=1, sizes=sizes)
    assert dataset.spec["sizes"] == {"levels": list(LEVELS), "diameters_um": list(MEASURED_UM)}
    with pytest.raises(InputError, match="differs in sizes"):
        generate_dataset(tmp_path / "d", config, groups=2)
    _, _, description = dataset.read_group(0)
    assert all(20.0 <= d <= 30.0 for d in description["particles"]["diameter_um"])


def test_cli_generate_draws_the_report_s_sizes_unless_told_otherwise(tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text('[tile]\nsize = 32\n[particles]\nper_tile = 2\nlayer_step_um = 50.0\n[volume]\nz_min_um = 1800.0\nz_max_um = 1900.0\n')
    report = tmp_path / "report.json"
    report.write_text(json.dumps(_report()))
    common = ["generate", "--config", str(config), "--groups", "1", "--context-planes", "1", "--effects-from", str(report)]
    assert main([*common, "--out", str(tmp_path / "a")]) == 0
    assert json.loads((tmp_path / "a" / "dataset.json").read_text())["sizes"]["diameters_um"] == list(MEASURED_UM)
    assert "measured sizes: median 25.3 um, quartiles 24.9-25.9 um" in capsys.readouterr().err
    assert main([*common, "--out", str(tmp_path / "b"), "--uniform-sizes"]) == 0
    assert "sizes" not in json.loads((tmp_path / "b" / "dataset.json").read_text())
    report.write_text(json.dumps(_report(diameters=[25.0, 24.0, 26.0, 27.0, 28.0])))
    assert main([*common, "--out", str(tmp_path / "c")]) == 2
    assert "report.json: scene: percentiles, diameter_um" in capsys.readouterr().err and not (tmp_path / "c").exists()
