import pytest

from napari_lbs._core import ConfigError, ExperimentConfig, load_config, write_config


def test_defaults_are_the_contracts():
    config = ExperimentConfig()
    assert config.to_dict() == {
        "optics": {"wavelength_um": 0.66, "pixel_um": 2.2, "medium_index": 1.0},
        "volume": {"z_min_um": 1800.0, "z_max_um": 4800.0, "z_step_um": 50.0},
        "particles": {"diameter_min_um": 20.0, "diameter_max_um": 30.0, "per_tile": 12, "layer_step_um": 200.0},
        "tile": {"size": 256},
    }
    assert len(config.volume.planes_um()) == 61 and config.volume.planes_um()[-1] == 4800.0
    assert len(config.layer_depths_um()) == 16


def test_write_then_load_round_trips(tmp_path):
    path = write_config(tmp_path / "c.toml")
    assert load_config(path) == ExperimentConfig()
    assert not list(tmp_path.glob(".*part*"))  # no temporary left behind


@pytest.mark.parametrize(
    ("text", "culprit"),
    [
        ("[optics]\npixel_um = -2.2\n", "optics.pixel_um"),
        ("[volume]\nz_min_um = 4800.0\nz_max_um = 1800.0\n", "volume.z_max_um"),
        ("[volume]\nz_step_um = 5000.0\n", "volume.z_step_um"),
        ("[optics]\nwavelenght_um = 0.5\n", "optics.wavelenght_um"),
        ("[lens]\nf = 1\n", "lens"),
        ("[tile]\nsize = 12.5\n", "tile.size"),
        ("[particles]\ndiameter_max_um = 10.0\n", "particles.diameter_max_um"),
        ("[optics]\nwavelength_um = \"red\"\n", "optics.wavelength_um"),
        ("[optics\n", "not valid TOML"),
    ],
)
def test_impossible_values_are_rejected_naming_the_key(tmp_path, text, culprit):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=culprit.replace(".", r"\.")):
        load_config(path)


def test_partial_file_takes_defaults_for_the_rest(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[optics]\nwavelength_um = 0.532\n")
    config = load_config(path)
    assert config.optics.wavelength_um == 0.532 and config.volume.z_max_um == 4800.0


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        load_config(tmp_path / "nope.toml")
