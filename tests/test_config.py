import pytest

from napari_lbs._core import ConfigError, ExperimentConfig, load_config, write_config


def test_defaults_are_the_contracts():
    config = ExperimentConfig()
    assert config.to_dict() == {
        "optics": {"wavelength_um": 0.66, "pixel_um": 2.2, "medium_index": 1.0, "magnification": 1.0},
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
        ("[optics]\npixel_um = 0.0\n", "optics.pixel_um"),
        ("[optics]\npixel_um = nan\n", "optics.pixel_um"),
        ("[optics]\nmagnification = 0.0\n", "optics.magnification"),
        ("[optics]\nmagnification = -40.0\n", "optics.magnification"),
        ("[optics]\nmagnification = inf\n", "optics.magnification"),
        ("[optics]\ncamera_pixel_um = -5.0\nmagnification = 60.0\n", "optics.camera_pixel_um"),
        ("[optics]\ncamera_pixel_um = 5.0\nmagnification = 60.0\npixel_um = 0.1\n", "optics.camera_pixel_um"),
        ("[volume]\nz_min_um = 5.0\nz_max_um = 5.0\n", "volume.z_max_um"),
        ("[volume]\nz_min_um = 0.0\nz_max_um = 60.0\n", "volume.z_min_um"),
        ("[volume]\nz_min_um = 5.0\nz_max_um = 60.0\nz_step_um = 0.5\n", "particles.layer_step_um"),
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


MICROSCOPE = """[optics]
wavelength_um = 0.66
camera_pixel_um = 7.24
magnification = 85.0
medium_index = 1.33

[volume]
z_min_um = 5.0
z_max_um = 60.0
z_step_um = 0.5

[particles]
diameter_min_um = 0.5
diameter_max_um = 3.0
layer_step_um = 5.0
"""


def test_a_microscope_takes_sub_wavelength_pixels_at_the_sample(tmp_path):
    path = tmp_path / "microscope.toml"
    path.write_text(MICROSCOPE)
    config = load_config(path)
    assert config.optics.pixel_um == pytest.approx(7.24 / 85.0, rel=1e-12)  # below λ/(2n) = 0.248 µm
    assert config.optics.magnification == 85.0 and config.optics.camera_pixel_um == pytest.approx(7.24)
    planes = config.volume.planes_um()
    assert len(planes) == 111 and planes[0] == 5.0 and planes[-1] == pytest.approx(60.0)
    assert len(config.layer_depths_um()) == 12
    written = write_config(tmp_path / "again.toml", config)
    assert load_config(written) == config  # the pitch at the sample and the magnification are what is stored
    assert "camera pitch 7.24 µm" in written.read_text(encoding="utf-8")


def test_the_same_pitch_given_both_ways_is_one_config(tmp_path):
    path = tmp_path / "both.toml"
    path.write_text("[optics]\ncamera_pixel_um = 6.5\nmagnification = 40.0\npixel_um = 0.1625\n")
    assert load_config(path).optics.pixel_um == pytest.approx(0.1625)


def test_non_finite_ends_are_refused_naming_the_key():
    from napari_lbs._core.foundation._config import ParticlesConfig, VolumeConfig

    with pytest.raises(ConfigError, match=r"volume\.z_max_um"):
        VolumeConfig(z_max_um=float("inf"))
    with pytest.raises(ConfigError, match=r"particles\.diameter_max_um"):
        ParticlesConfig(diameter_max_um=float("inf"))
