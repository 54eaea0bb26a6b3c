"""Microscope setups: sub-wavelength pixels at the sample, the built-in example, refine with no training."""

import importlib.util
import json
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch

from napari_lbs._cli import main
from napari_lbs._core import ExperimentConfig, InputError, load_config, load_model, read_particles
from napari_lbs._core.learning._network import save_model
from napari_lbs._core.physics import backpropagate, padded_shape, propagate, transfer_function
from napari_lbs._core.refine import RefineSettings, particle_hologram

DATA = files("napari_lbs") / "data"
EXAMPLE = {name: Path(str(DATA / f"microscope_example{name}")) for name in (".toml", "_hologram.tif", "_background.tif", "_dark.tif", "_truth.csv")}
SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "make_microscope_example.py"
# 85× objective on a 7.24 µm camera: 0.0851 µm at the sample, below λ/(2n) = 0.248 µm in water
MICROSCOPE = ExperimentConfig.from_dict({"optics": {"wavelength_um": 0.66, "camera_pixel_um": 7.24, "magnification": 85.0, "medium_index": 1.33},
                                         "volume": {"z_min_um": 5.0, "z_max_um": 60.0, "z_step_um": 0.5},
                                         "particles": {"diameter_min_um": 0.5, "diameter_max_um": 3.0, "layer_step_um": 5.0}})


def test_the_angular_spectrum_at_sub_wavelength_pixels_is_cut_at_the_medium_cutoff():
    optics = {"wavelength_um": 0.66, "pixel_um": MICROSCOPE.optics.pixel_um, "medium_index": 1.33}
    kernel = transfer_function((128, 128), 20.0, **optics)
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(128, d=optics["pixel_um"]), np.fft.fftfreq(128, d=optics["pixel_um"]), indexing="ij"))
    cutoff = 1.33 / 0.66
    assert f.max() > 2.0 * cutoff  # the grid samples far beyond the propagating band
    assert np.all(kernel[f > cutoff] == 0)  # evanescent light dropped
    assert np.allclose(np.abs(kernel[f < 0.9 * cutoff]), 1.0)  # every propagating frequency kept
    grid = padded_shape((128, 128), z_max_um=60.0, **optics)
    assert grid[0] <= 4 * 128  # light at grazing angles is dropped by the band limit, not padded for
    # a uniform field stays uniform, and forth-and-back propagation of a smooth field returns it
    assert np.allclose(propagate(np.ones((64, 64), np.complex128), 30.0, **optics), 1.0)
    rows, cols = np.mgrid[:96, :96]
    smooth = 1.0 + 0.2 * np.exp(-((rows - 48.0) ** 2 + (cols - 48.0) ** 2) / 200.0)
    back = propagate(propagate(smooth.astype(np.complex128), 10.0, **optics), -10.0, **optics)
    assert np.abs(back - smooth)[24:72, 24:72].max() < 1e-3


@pytest.mark.parametrize(("diameter_um", "z_um"), [(0.16, 10.0), (10.0, 5.0)])  # size parameter 1; a 10 µm sphere 5 µm from focus
def test_lorenz_mie_holograms_evaluate_at_microscope_scale(diameter_um, z_um):
    table = {"x_um": [3.2], "y_um": [3.2], "z_um": [z_um], "diameter_um": [diameter_um], "index_contrast": [0.26]}
    hologram = particle_hologram((64, 64), table, MICROSCOPE, settings=RefineSettings(medium_index=1.33))
    assert np.all(np.isfinite(hologram)) and np.all(hologram >= 0)
    modulation = np.ptp(hologram)
    assert (1e-4 < modulation < 0.05) if diameter_um < 1 else (modulation > 1.0)  # a tiny sphere barely scatters, a large one focuses light


def test_backprop_takes_a_microscope_config_and_a_background(tmp_path):
    stack = tmp_path / "stack.tif"
    assert main(["backprop", str(EXAMPLE["_hologram.tif"]), "--config", str(EXAMPLE[".toml"]), "--background", str(EXAMPLE["_background.tif"]), "--out", str(stack)]) == 0
    with tifffile.TiffFile(stack) as handle:
        planes, description = handle.asarray(), json.loads(handle.pages[0].description)
    assert planes.shape == (81, 256, 256) and description["config"]["optics"]["magnification"] == 60.0
    truth = read_particles(EXAMPLE["_truth.csv"])
    # the largest sphere's focal spot is brightest near its depth (a transparent sphere is a lens)
    row, col = (int(round(truth[name][3] / 0.1)) for name in ("y_um", "x_um"))
    brightest_um = description["z_um"][int(np.argmax(planes[:, row, col]))]
    assert abs(brightest_um - truth["z_um"][3]) < 6.0


def test_refine_fits_the_built_in_example_with_no_training(tmp_path):
    out = tmp_path / "fit.csv"
    argv = ["refine", str(EXAMPLE["_hologram.tif"]), "--config", str(EXAMPLE[".toml"]), "--background", str(EXAMPLE["_background.tif"]),
            "--dark", str(EXAMPLE["_dark.tif"]), "--max-particles", "1", "--patch-um", "12.8", "--out", str(out)]
    assert main(argv) == 0
    fit, truth = read_particles(out), read_particles(EXAMPLE["_truth.csv"])
    assert fit["x_um"].size == 1 and bool(fit["refined"][0])
    nearest = int(np.argmin(np.hypot(truth["x_um"] - fit["x_um"][0], truth["y_um"] - fit["y_um"][0])))
    assert nearest == 3  # the strongest scatterer: the 3 µm sphere
    assert abs(fit["z_um"][0] - truth["z_um"][nearest]) < 0.3
    assert abs(fit["diameter_um"][0] - truth["diameter_um"][nearest]) < 0.1
    assert abs(fit["index_contrast"][0] - 0.26) < 0.02
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["find"]["detector"] == "find_particles" and record["config"]["optics"]["magnification"] == 60.0
    assert record["dark_file"] == str(EXAMPLE["_dark.tif"]) and record["particles"] == str(out)
    assert main(argv) == 2  # no clobbering without --force


def test_refine_finds_the_spheres_the_strong_ones_hid_in_the_built_in_example(tmp_path, monkeypatch):
    """The detector sees the 3 and 2.2 µm spheres; the look in their residual finds the 1.5 and 0.8 µm ones, and every refit lands on the truth."""
    monkeypatch.setenv("NAPARI_LBS_THREADS", "1")  # one fitting process on one thread: seconds, where spawned workers on a busy machine take tens
    out = tmp_path / "fit.csv"
    assert main(["refine", str(EXAMPLE["_hologram.tif"]), "--config", str(EXAMPLE[".toml"]), "--background", str(EXAMPLE["_background.tif"]),
                 "--dark", str(EXAMPLE["_dark.tif"]), "--patch-um", "12.8", "--out", str(out)]) == 0
    fit, truth = read_particles(out), read_particles(EXAMPLE["_truth.csv"])
    assert fit["x_um"].size == 4 and fit["refined"].all()
    for i in range(4):
        nearest = int(np.argmin(np.hypot(fit["x_um"] - truth["x_um"][i], fit["y_um"] - truth["y_um"][i])))
        assert np.hypot(fit["x_um"][nearest] - truth["x_um"][i], fit["y_um"][nearest] - truth["y_um"][i]) < 0.1
        assert abs(fit["z_um"][nearest] - truth["z_um"][i]) < 0.2
        assert abs(fit["diameter_um"][nearest] - truth["diameter_um"][i]) < 0.05
        assert abs(fit["index_contrast"][nearest] - truth["index_contrast"][i]) < 0.02
    find = json.loads(out.with_suffix(".json").read_text())["find"]
    assert find["detections"] == 2 and find["detection_rounds"] == 3 and find["rounds"][0]["found"] == 2 and find["rounds"][-1]["found"] == 0


def test_a_stop_asked_in_a_look_at_the_residual_ends_the_refinement_at_once():
    import time

    from napari_lbs._core import Stopped, read_hologram
    from napari_lbs._core.pipeline import refine_hologram

    dark = read_hologram(EXAMPLE["_dark.tif"])
    hologram = (read_hologram(EXAMPLE["_hologram.tif"]) - dark) / (read_hologram(EXAMPLE["_background.tif"]) - dark)
    asked = []

    class Listener:
        def __call__(self, done, total):
            pass

        def phase(self, name):
            if name.startswith("look 2"):
                asked.append(time.monotonic())

    with pytest.raises(Stopped):
        refine_hologram(hologram, load_config(EXAMPLE[".toml"]), patch_um=12.8, progress=Listener(), should_stop=lambda: bool(asked))
    assert asked and time.monotonic() - asked[0] < 2.0


def test_the_example_is_what_its_script_makes(tmp_path):
    spec = importlib.util.spec_from_file_location("make_microscope_example", SCRIPT)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    script.make(tmp_path)
    assert load_config(tmp_path / "microscope_example.toml") == load_config(EXAMPLE[".toml"])
    assert load_config(EXAMPLE[".toml"]).optics.pixel_um == pytest.approx(0.1)
    assert read_particles(tmp_path / "microscope_example_truth.csv").keys() == read_particles(EXAMPLE["_truth.csv"]).keys()
    for name in ("_hologram.tif", "_background.tif", "_dark.tif"):
        made, shipped = tifffile.imread(tmp_path / f"microscope_example{name}"), tifffile.imread(EXAMPLE[name])
        assert made.dtype == shipped.dtype == np.uint16 and made.shape == shipped.shape == (256, 256)
        assert np.abs(made.astype(int) - shipped.astype(int)).max() <= 1  # the same seed, the same frame (to a rounding)


def test_the_fit_bins_only_pixels_finer_than_the_fringes_need():
    from napari_lbs._core.pipeline import fringe_binning

    assert fringe_binning(ExperimentConfig(), medium_index=1.33) == 1  # a lensless sensor's 2.2 µm
    assert fringe_binning(MICROSCOPE, medium_index=1.33) == 2  # 0.0851 µm: 0.17 µm still samples n/λ
    assert fringe_binning(MICROSCOPE, medium_index=1.0) == 3


def test_simulate_and_generate_take_a_microscope_config(tmp_path):
    config = tmp_path / "tiny.toml"
    config.write_text(EXAMPLE[".toml"].read_text(encoding="utf-8").replace("size = 256", "size = 32"), encoding="utf-8")
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "sim"), "--size", "48", "--particles", "2", "--seed", "1"]) == 0
    truth = read_particles(tmp_path / "sim" / "particles.csv")
    assert truth["x_um"].size == 2 and np.all((truth["z_um"] >= 5.0) & (truth["z_um"] <= 45.0)) and np.all(truth["diameter_um"] <= 3.0)
    assert np.all(truth["x_um"] < 48 * 0.1)  # positions in µm at the sample's 0.1 µm pitch
    assert main(["generate", "--config", str(config), "--out", str(tmp_path / "data"), "--groups", "2", "--seed", "0"]) == 0
    spec = json.loads((tmp_path / "data" / "dataset.json").read_text())
    assert spec["config"]["optics"]["magnification"] == 60.0 and spec["config"]["volume"]["z_step_um"] == 0.5


def test_refine_leaves_a_saturated_camera_s_clipped_pixels_out_and_says_so(tmp_path):
    from napari_lbs._core.pipeline import RefineRequest, refine

    frame = 1000.0 + 30.0 * np.random.default_rng(3).standard_normal((48, 48))
    lines = []
    for image, name in ((frame, "free"), (np.minimum(frame, np.quantile(frame, 0.98)), "clipped")):  # a clipped camera: a plateau at the maximum
        refine(RefineRequest(image, tmp_path / f"{name}.csv", load_config(EXAMPLE[".toml"])), log=lines.append)
    assert len(lines) == 1 and "pixels at the frame's maximum" in lines[0] and "left out of the fits" in lines[0]
    free, clipped = (json.loads((tmp_path / f"{name}.json").read_text()) for name in ("free", "clipped"))
    assert free["pixels_at_maximum"] == 1 and free["pixels_left_out"] == 0
    assert clipped["pixels_at_maximum"] >= 40 and clipped["pixels_left_out"] == clipped["pixels_at_maximum"]


def test_a_fit_without_a_saturated_focal_spot_s_clipped_pixels_is_unbiased():
    """A 3 µm sphere 12 µm from focus whose focal spot (1.76 times the light) a camera clips at 1.365 (12 bits, the light at 3000 counts)."""
    import pandas as pd

    from napari_lbs._core.refine import refine_particles, unsaturated_pixels

    pixel = MICROSCOPE.optics.pixel_um
    truth = {"x_um": [32 * pixel + 0.03], "y_um": [32 * pixel - 0.02], "z_um": [12.0], "diameter_um": [3.0], "index_contrast": [0.26], "absorption": [0.0]}
    settings = RefineSettings(patch_px=64, depth_window_um=4.0)
    hologram = particle_hologram((64, 64), truth, MICROSCOPE, settings=settings) + 0.01 * np.random.default_rng(0).standard_normal((64, 64))
    clipped = np.minimum(hologram, 4095 / 3000)
    valid = unsaturated_pixels(clipped)
    assert valid is not None and 100 < np.count_nonzero(~valid) < 1000 and unsaturated_pixels(hologram) is None
    start = pd.DataFrame({"x_um": [32 * pixel + 0.1], "y_um": [32 * pixel + 0.1], "z_um": [12.8], "diameter_um": [2.8]})
    biased = refine_particles(clipped, start, MICROSCOPE, settings=settings)
    masked = refine_particles(clipped, start, MICROSCOPE, settings=settings, valid=valid)
    # the model knows no clipping: through the plateau the fit ends 0.5 µm off in depth; without it, within its error
    assert abs(biased["z_um"][0] - 12.0) > 0.1
    assert abs(masked["z_um"][0] - 12.0) < 0.01 and abs(masked["diameter_um"][0] - 3.0) < 0.01 and abs(masked["index_contrast"][0] - 0.26) < 0.002
    for bad, culprit in ((valid.astype(int), "bool array"), (valid[:10], "shape"), (np.zeros_like(valid), "no pixel left")):
        with pytest.raises(InputError, match=f"^valid: .*{culprit}"):
            refine_particles(clipped, start, MICROSCOPE, settings=settings, valid=bad)


def test_a_binned_pixel_is_valid_where_its_whole_block_is():
    from napari_lbs._core.pipeline._binning import binned_valid, fringe_binning

    assert fringe_binning(MICROSCOPE, medium_index=1.33) == 2
    valid = np.ones((6, 7), bool)
    valid[1, 2] = False
    expected = np.ones((3, 3), bool)
    expected[0, 1] = False
    np.testing.assert_array_equal(binned_valid(valid, MICROSCOPE, medium_index=1.33), expected)
    assert binned_valid(None, MICROSCOPE, medium_index=1.33) is None


def test_the_lbs_pipeline_runs_on_a_microscope_config(tmp_path, monkeypatch):
    """simulate → generate → train → predict --refine at 0.1 µm pixels: a table in µm at the sample, the fit binned 2 × 2 and scanning a quarter of the depths."""
    monkeypatch.setenv("NAPARI_LBS_THREADS", "1")
    config = tmp_path / "microscope.toml"
    text = EXAMPLE[".toml"].read_text(encoding="utf-8").replace("size = 256", "size = 32").replace("z_min_um = 5.0", "z_min_um = 10.0")
    text = text.replace("z_max_um = 45.0", "z_max_um = 14.0").replace("per_tile = 4", "per_tile = 2").replace("layer_step_um = 5.0", "layer_step_um = 2.0")
    config.write_text(text, encoding="utf-8")
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "sim"), "--size", "64", "--particles", "2", "--seed", "3"]) == 0
    assert main(["generate", "--config", str(config), "--out", str(tmp_path / "data"), "--groups", "3", "--seed", "0",
                 "--effect", "particle_phase:index_contrast=0.26,transmission=1"]) == 0
    model = tmp_path / "model.pt"
    assert main(["train", str(tmp_path / "data"), "--out", str(model), "--epochs", "1", "--batch-size", "4", "--patch-size", "32",
                 "--validation-groups", "1", "--device", "cpu"]) == 0
    assert load_model(model).meta["config"]["optics"]["magnification"] == 60.0  # the model's provenance
    out = tmp_path / "particles.csv"
    assert main(["predict", str(tmp_path / "sim" / "hologram.tif"), "--model", str(model), "--refine", "--device", "cpu", "--out", str(out)]) == 0
    table, record = read_particles(out), json.loads(out.with_suffix(".json").read_text())
    assert {"x_um", "y_um", "z_um", "diameter_um", "index_contrast", "fit_residual", "refined"} <= set(table)
    assert record["config"]["optics"]["magnification"] == 60.0 and record["config"]["optics"]["pixel_um"] == pytest.approx(0.1)
    assert record["refine"]["binning"] == 2 and record["refine"]["settings"]["depth_window_um"] == pytest.approx(1.0)  # 10–14 µm: a quarter
    # one tiny epoch has not left the prior's 1 % centre probability: raised, the network proposes particles
    eager = load_model(model)
    with torch.no_grad():
        eager.network.head.bias[0] += 4.0
    save_model(tmp_path / "eager.pt", eager.network, eager.meta)
    assert main(["predict", str(tmp_path / "sim" / "hologram.tif"), "--model", str(tmp_path / "eager.pt"), "--threshold", "0.2", "--device", "cpu",
                 "--out", str(tmp_path / "eager.csv")]) == 0
    table = read_particles(tmp_path / "eager.csv")
    assert table["x_um"].size >= 1
    # µm at the sample's 0.1 µm pitch (the 64-pixel frame is 6.4 µm), not at the camera's 6 µm; depths in the volume
    assert np.all((table["x_um"] >= 0) & (table["x_um"] <= 6.4) & (table["y_um"] >= 0) & (table["y_um"] <= 6.4))
    assert np.all((table["z_um"] >= 9.5) & (table["z_um"] <= 14.5))
