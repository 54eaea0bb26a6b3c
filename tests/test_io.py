import hashlib

import numpy as np
import pytest
import tifffile

from napari_lbs._core import InputError, load_sample_hologram, read_hologram, read_particles, read_stack, write_particles, write_stack


def test_real_hologram_reads_as_its_red_channel(real_hologram_bmp):
    messages = []
    hologram = read_hologram(real_hologram_bmp, log=messages.append)
    assert hologram.shape == (1024, 1024) and hologram.dtype == np.float32
    assert hologram.mean() == pytest.approx(161.2, abs=0.1)
    assert "red channel" in messages[0]


# SHA-256 of the pixels (1024x1024x3 uint8, C order) of the seed authors' cropped_hologram.bmp.
SEED_BMP_PIXELS_SHA256 = "7d41a425036a070e9361f73e97b2dcd4527e692fc252df42fa8759289577cffa"


def test_shipped_sample_is_bit_identical_to_the_seed_bmp():
    original = load_sample_hologram(rgb=True)
    assert original.shape == (1024, 1024, 3) and original.dtype == np.uint8
    assert hashlib.sha256(np.ascontiguousarray(original).tobytes()).hexdigest() == SEED_BMP_PIXELS_SHA256
    assert np.array_equal(load_sample_hologram(), original[..., 0].astype(np.float32))


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.zeros((4, 64, 64)), "holds 4 pages"),
        (np.zeros((8, 8)), "at least 16x16"),
        (np.where(np.eye(32) > 0, np.nan, 1.0), "NaN"),
        (np.zeros((32, 32), np.uint8), "every pixel is 0"),
        (np.full((32, 32), 7.5, np.float32), "every pixel is 7.5"),
        (-np.arange(32 * 32, dtype=np.float32).reshape(32, 32), "negative intensities"),
    ],
)
def test_bad_images_are_refused_with_the_culprit(tmp_path, array, message):
    path = tmp_path / "bad.tif"
    tifffile.imwrite(path, array, photometric="minisblack")
    with pytest.raises(InputError, match=message) as info:
        read_hologram(path)
    assert "bad.tif" in str(info.value) and "\n" not in str(info.value)


def test_missing_and_undecodable_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_hologram(tmp_path / "none.tif")
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not a png")
    with pytest.raises(InputError, match="junk.png"):
        read_hologram(junk)


def test_float64_precision_is_kept(tmp_path):
    path = tmp_path / "h.tif"
    tifffile.imwrite(path, 1.0 + 1e-12 * np.arange(32 * 32).reshape(32, 32))
    assert read_hologram(path).dtype == np.float64


def test_stack_and_particle_round_trips(tmp_path):
    stack = np.random.default_rng(0).random((3, 20, 24)).astype(np.float32)
    write_stack(tmp_path / "s.tif", stack, z_um=[1.0, 2.0, 3.5], metadata={"seed": 7})
    back, description = read_stack(tmp_path / "s.tif")
    assert np.array_equal(back, stack) and description["z_um"] == [1.0, 2.0, 3.5] and description["seed"] == 7
    table = {"x_um": np.array([1.5, 2.0]), "y_um": np.array([3.0, 4.0]), "z_um": np.array([1800.0, 2000.0]), "diameter_um": np.array([25.0, 21.0]), "score": np.array([0.9, 0.5])}
    write_particles(tmp_path / "p.csv", table)
    assert (tmp_path / "p.csv").read_text().splitlines()[0] == "x_um,y_um,z_um,diameter_um,score"
    back = read_particles(tmp_path / "p.csv")
    for key, values in table.items():
        assert np.allclose(back[key], values)


def test_failed_write_keeps_the_previous_file(tmp_path):
    target = tmp_path / "s.tif"
    write_stack(target, np.zeros((1, 16, 16), np.float32), z_um=[1.0])
    before = target.read_bytes()
    with pytest.raises(InputError):
        write_stack(target, np.zeros((2, 16, 16), np.float32), z_um=[1.0], force=True)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.tif"]
