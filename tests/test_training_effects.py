"""Effects of the catalog in the training data: parsing, reading a diagnosis report, generate's provenance."""

import json

import numpy as np
import pytest

from napari_lbs._cli import main
from napari_lbs._core import (
    DatasetLayout,
    ExperimentConfig,
    InputError,
    ParticleField,
    backpropagate,
    effects_from_report,
    generate_dataset,
    open_dataset,
    random_particle_field,
    simulate_hologram,
)
from napari_lbs._core.physics._effects import check_effects, effect_hologram, parse_effect

CONFIG = ExperimentConfig.from_dict({"tile": {"size": 64}, "particles": {"per_tile": 3}, "volume": {"z_min_um": 1800.0, "z_max_um": 2000.0, "z_step_um": 50.0}})


def _field(seed=0, count=4):
    return random_particle_field((64, 64), count=count, diameter_min_um=20, diameter_max_um=30, layers_um=(1800.0, 2400.0), pixel_um=2.2, seed=seed)


def _report(verdict="quantization"):
    effects = [
        {"id": "quantization", "params": {"bits": 8.0, "saturation": 2.0, "baseline.gamma": 1.3}},
        {"id": "particle_phase", "params": {"index_contrast": 0.008, "transmission": 0.5}},
    ]
    return {"gap": {"baseline": 0.8}, "effects": effects, "verdict": {"id": verdict, "shrink": 0.9, "residual": 0.1}, "posterior": {}}


def test_parse_effect_reads_the_command_line_form_and_names_the_culprit():
    assert parse_effect("particle_phase:index_contrast=0.26,transmission=0.3") == {"particle_phase": {"index_contrast": 0.26, "transmission": 0.3}}
    assert parse_effect("multiple_scattering") == {"multiple_scattering": {"on": 1.0}}  # a fixed-bound parameter may be left out
    with pytest.raises(InputError, match="unknown effect id 'dust'"):
        parse_effect("dust:amount=1")
    with pytest.raises(InputError, match="missing parameter 'transmission'"):
        parse_effect("particle_phase:index_contrast=0.26")
    with pytest.raises(InputError, match="unknown parameter 'colour'"):
        parse_effect("sensor_blur:colour=1")
    with pytest.raises(InputError, match="expected a finite number"):
        check_effects({"sensor_blur": {"sigma_px": float("nan")}})
    with pytest.raises(InputError, match="NAME=VALUE"):
        parse_effect("sensor_blur:1.0")


def test_effects_from_report_takes_the_verdicts_model_with_its_parameters():
    # one effect: its parameters, an older report's baseline keys dropped
    assert effects_from_report(_report()) == {"quantization": {"bits": 8.0, "saturation": 2.0}}
    # two effects
    assert effects_from_report(_report("quantization+particle_phase"))["particle_phase"] == {"index_contrast": 0.008, "transmission": 0.5}
    # nothing missing, or undecided: nothing added
    assert effects_from_report(_report(verdict=None)) == {}
    with pytest.raises(InputError, match="not a diagnosis report"):
        effects_from_report({"params": {"gamma": 1.0}}, name="calib.json")
    with pytest.raises(InputError, match="records no parameters"):
        effects_from_report(_report("sensor_blur"))


def test_effect_hologram_obeys_the_physics_of_each_effect():
    field = _field()
    opaque = simulate_hologram(field, wavelength_um=0.66)
    rng = np.random.default_rng(0)
    # a sphere that transmits all light with no phase delay is invisible: the hologram is flat
    invisible = effect_hologram(field, {"particle_phase": {"index_contrast": 0.0, "transmission": 1.0}}, wavelength_um=0.66, rng=rng)
    np.testing.assert_allclose(invisible, 1.0, atol=1e-5)
    # transmission 0 is an opaque disc whatever the phase (band-limited to the pixel grid, so not bit for bit the seed's)
    black = effect_hologram(field, {"particle_phase": {"index_contrast": 0.0126, "transmission": 0.0}}, wavelength_um=0.66, rng=rng)
    assert np.corrcoef(black.ravel(), opaque.ravel())[0, 1] > 0.95
    # a thick glass sphere (62 rad, polystyrene in water) focuses light: a bright spot where the opaque disc is dark
    # (the window must hold the fringes out to where they pass the pixel's band: 192² at 2 mm)
    one = ParticleField(np.array([96 * 2.2]), np.array([96 * 2.2]), np.array([2000.0]), np.array([25.0]), (192, 192), 2.2)
    glass = effect_hologram(one, {"particle_phase": {"index_contrast": 0.26, "transmission": 1.0}}, wavelength_um=0.66, rng=rng)
    disc = simulate_hologram(one, wavelength_um=0.66)
    at_focus = [backpropagate(h, [2000.0], wavelength_um=0.66, pixel_um=2.2)[0, 96, 96] for h in (glass, disc)]
    assert at_focus[0] > 1.2 and at_focus[1] < 0.3
    # 4 bits leave at most 16 grey levels; no effects: the seed's hologram exactly
    quantized = effect_hologram(field, {"quantization": {"bits": 4.0, "saturation": 2.0}}, wavelength_um=0.66, rng=rng)
    assert np.unique(quantized).size <= 16
    np.testing.assert_array_equal(effect_hologram(field, {}, wavelength_um=0.66, rng=rng), opaque)


def test_the_camera_s_envelope_and_etalon_fringe_are_their_formulas_on_a_tile_of_the_sensor():
    from napari_lbs._core.physics._effects import sensor_image

    baseline = {"contrast": 1.0, "sigma": 0.0, "gamma": 1.0}
    flat, zeros = np.ones((40, 60), np.float32), np.zeros((40, 60), np.float32)
    rows, cols = np.arange(10, 50), np.arange(100, 160)  # a tile of a 200 x 300 sensor
    envelope = {"illumination": {"depth": 0.3, "waist": 0.4, "x0": 0.1, "y0": -0.05}}
    y, x = (rows / 199.0 - 0.5)[:, None], (cols / 299.0 - 0.5)[None, :]
    expected = 1.0 - 0.3 * (1.0 - np.exp(-((x - 0.1) ** 2 + (y + 0.05) ** 2) / 0.4**2))
    np.testing.assert_allclose(sensor_image(flat, baseline, envelope, noise=zeros, frame_px=(rows, cols, (200, 300))), expected, rtol=1e-6)
    fringe = {"parasitic_fringes": {"amplitude": 0.04, "period_px": 11.3, "angle_rad": 0.7, "phase_rad": 1.2}}
    expected = 1.0 + 0.04 * np.cos(2 * np.pi * (cols[None, :] * np.cos(0.7) + rows[:, None] * np.sin(0.7)) / 11.3 + 1.2)
    np.testing.assert_allclose(sensor_image(flat, baseline, fringe, noise=zeros, frame_px=(rows, cols, (200, 300))), expected, rtol=1e-6)


def test_a_spheres_phase_delay_is_proportional_to_its_diameter():
    from napari_lbs._core.physics._effects import _sphere_fields

    # φ0 = 2π Δn d / λ through the centre: 0.95 rad for 20 µm, 1.43 rad for 30 µm at Δn 0.005
    # (slow phases, so the band limit leaves the centre's value intact)
    for diameter_um in (20.0, 30.0):
        one = ParticleField(np.array([64 * 2.2]), np.array([64 * 2.2]), np.array([2000.0]), np.array([diameter_um]), (128, 128), 2.2)
        centre = 1.0 + _sphere_fields(one, 2000.0, transmission=1.0, index_contrast=0.005, wavelength_um=0.66)[64, 64]
        assert np.angle(centre) == pytest.approx(2 * np.pi * 0.005 * diameter_um / 0.66, abs=0.03)
        assert abs(centre) == pytest.approx(1.0, abs=0.03)


def test_generate_records_the_effects_and_the_data_differs_only_through_them(tmp_path):
    layout = DatasetLayout(context_planes=1)
    plain = generate_dataset(tmp_path / "plain", CONFIG, groups=1, layout=layout, seed=3)
    effects = {"particle_phase": {"index_contrast": 0.0126, "transmission": 0.8}}
    source = {"report": "r.json", "verdict": "particle_phase"}
    generate_dataset(tmp_path / "phased", CONFIG, groups=1, layout=layout, seed=3, effects=effects, effects_source=source)
    spec = json.loads((tmp_path / "phased" / "dataset.json").read_text())
    assert spec["effects"] == effects and spec["effects_source"] == source
    assert "effects" not in json.loads((tmp_path / "plain" / "dataset.json").read_text())
    plain_inputs, plain_labels, _ = plain.read_group(0)
    phased_inputs, phased_labels, _ = open_dataset(tmp_path / "phased").read_group(0)
    np.testing.assert_array_equal(plain_labels, phased_labels)  # same particles
    assert np.abs(plain_inputs.astype(np.float32) - phased_inputs.astype(np.float32)).max() > 0.05  # other holograms
    with pytest.raises(InputError, match="differs in effects"):
        generate_dataset(tmp_path / "phased", CONFIG, groups=1, layout=layout, seed=3)
    # a set stated before an effect gained optional parameters (here the fringe's dust) is the same set
    fringe = {"parasitic_fringes": {"amplitude": 0.05, "period_px": 9.0, "angle_rad": 0.3}}
    generate_dataset(tmp_path / "fringe", CONFIG, groups=1, layout=layout, seed=3, effects=fringe)
    manifest = tmp_path / "fringe" / "dataset.json"
    old = json.loads(manifest.read_text())
    old["effects"] = fringe  # as written before the dust parameters existed
    manifest.write_text(json.dumps(old))
    assert len(generate_dataset(tmp_path / "fringe", CONFIG, groups=2, layout=layout, seed=3, effects=fringe).groups) == 2


def _config_and_report(tmp_path, verdict: str):
    """A small config of 64-pixel tiles and a report naming ``verdict``, written in ``tmp_path``."""
    config = tmp_path / "c.toml"
    config.write_text('[tile]\nsize = 64\n[particles]\nper_tile = 2\nlayer_step_um = 50.0\n[volume]\nz_min_um = 1800.0\nz_max_um = 1900.0\n')
    report = tmp_path / "report.json"
    report.write_text(json.dumps(_report(verdict)))
    return config, report


def test_cli_generate_effects_from_a_report_and_refusals(tmp_path, capsys):
    config, report = _config_and_report(tmp_path, "quantization+particle_phase")
    out = tmp_path / "data"
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(out), "--context-planes", "1", "--effects-from", str(report), "--effect", "sensor_blur:sigma_px=0.5"]) == 0
    spec = json.loads((out / "dataset.json").read_text())
    assert set(spec["effects"]) == {"quantization", "particle_phase", "sensor_blur"}
    assert spec["effects_source"]["verdict"] == "quantization+particle_phase"
    capsys.readouterr()
    not_a_report = tmp_path / "calib.json"
    not_a_report.write_text(json.dumps({"params": {}}))
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(tmp_path / "x"), "--effects-from", str(not_a_report)]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "calib.json" in error[0] and "not a diagnosis report" in error[0]
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(tmp_path / "y"), "--effect", "particle_phase:index_contrast=inf,transmission=1"]) == 2
    assert not (tmp_path / "y").exists()


def test_cli_generate_a_reports_model_replaces_the_calibration_unless_kept(tmp_path, capsys):
    config, report = _config_and_report(tmp_path, "quantization")
    calibration = tmp_path / "calibration.json"
    calibration.write_text(json.dumps({"params": {"N_R": -0.9, "N_sigma": 0.3, "gamma": 0.8}, "ssim": 0.7, "settings": {"mode": "robust"}}))
    common = ["generate", "--config", str(config), "--groups", "1", "--context-planes", "1", "--calibration", str(calibration)]
    specs = {}
    for name, extra in {"calibrated": [], "report": ["--effects-from", str(report)], "kept": ["--effects-from", str(report), "--keep-calibration"]}.items():
        assert main([*common, "--out", str(tmp_path / name), *extra]) == 0
        specs[name] = json.loads((tmp_path / name / "dataset.json").read_text())
        assert specs[name]["calibration"]["params"]["N_R"] == -0.9  # recorded in every case
        assert ("the report's model replaces the Holo-processing" in capsys.readouterr().err) == (name == "report")
    assert specs["calibrated"]["processing"]["params"]["N_R"] == -0.9 and specs["calibrated"]["processing"]["invert_experiment"]
    assert specs["report"]["processing"] == {"params": {"N_R": 0.0, "N_sigma": 0.0, "gamma": 1.0}, "invert_experiment": False, "mode": "robust"}
    assert specs["report"]["effects_source"]["calibration_applied"] is False
    assert specs["kept"]["processing"] == specs["calibrated"]["processing"] and "calibration_applied" not in specs["kept"]["effects_source"]
    inputs = {name: open_dataset(tmp_path / name).read_group(0)[0] for name in specs}
    assert not np.array_equal(inputs["report"], inputs["kept"])
