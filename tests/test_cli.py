import json
import subprocess
import sys

import numpy as np
import pytest
import tifffile
import torch

from napari_lbs._cli import main
from napari_lbs._core import read_particles


def run(*args):
    return subprocess.run([sys.executable, "-m", "napari_lbs._cli", *map(str, args)], capture_output=True, text=True)


def test_config_simulate_backprop_end_to_end(tmp_path):
    config = tmp_path / "c.toml"
    assert main(["config", "--write", str(config)]) == 0
    config.write_text(config.read_text().replace("z_step_um = 50.0", "z_step_um = 500.0"))
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "sim"), "--size", "64", "--particles", "3", "--seed", "5"]) == 0
    hologram = tifffile.imread(tmp_path / "sim" / "hologram.tif")
    assert hologram.dtype == np.float32 and hologram.shape == (64, 64)
    assert len(np.unique(hologram)) > 1000  # unquantised
    truth = read_particles(tmp_path / "sim" / "particles.csv")
    assert truth["x_um"].size == 3
    assert main(["backprop", str(tmp_path / "sim" / "hologram.tif"), "--config", str(config), "--out", str(tmp_path / "stack.tif")]) == 0
    with tifffile.TiffFile(tmp_path / "stack.tif") as handle:
        stack = handle.asarray()
        description = json.loads(handle.pages[0].description)
    assert stack.shape == (7, 64, 64) and stack.dtype == np.float32
    assert description["z_um"] == [1800.0, 2300.0, 2800.0, 3300.0, 3800.0, 4300.0, 4800.0]
    assert description["config"]["volume"]["z_step_um"] == 500.0


@pytest.mark.parametrize(
    ("args", "culprit"),
    [
        (["backprop", "missing.tif", "--config", "{config}", "--out", "{tmp}/s.tif"], "missing.tif"),
        (["backprop", "{tmp}/rgbstack.tif", "--config", "{config}", "--out", "{tmp}/s.tif"], "rgbstack.tif"),
        (["backprop", "{tmp}/h.tif", "--config", "{tmp}/bad.toml", "--out", "{tmp}/s.tif"], "volume.z_max_um"),
        (["backprop", "{tmp}/h.tif", "--config", "{config}", "--out", "{tmp}/s.tif", "--background", "{tmp}/small.tif"], "small.tif"),
        (["diagnose", "{tmp}/h.tif", "--config", "{config}", "--out", "{tmp}/s.tif"], "h.tif: expected at least 128 pixels"),
        (["diagnose", "{tmp}/h.tif", "--config", "{config}", "--out", "{tmp}/s.tif", "--tile", "20"], "--tile 20"),
    ],
)
def test_bad_input_exits_2_with_one_line_naming_the_culprit(tmp_path, args, culprit):
    config = tmp_path / "c.toml"
    main(["config", "--write", str(config)])
    (tmp_path / "bad.toml").write_text("[volume]\nz_min_um = 3000.0\nz_max_um = 2000.0\n")
    fringes = 1.0 + 0.1 * np.random.default_rng(0).random((32, 32), np.float32)
    tifffile.imwrite(tmp_path / "h.tif", fringes)
    tifffile.imwrite(tmp_path / "small.tif", fringes[:16, :16])
    tifffile.imwrite(tmp_path / "rgbstack.tif", np.ones((5, 32, 32), np.float32))
    result = run(*[a.format(config=config, tmp=tmp_path) for a in args])
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and culprit in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "s.tif").exists()


def test_demo_quick_runs_the_whole_pipeline_and_gives_the_same_result_under_load(tmp_path):
    assert main(["demo", "--out", str(tmp_path), "--quick"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    stack = tifffile.imread(summary["zstack"])
    assert stack.shape == (61, 256, 256)
    assert set(summary["calibration"]["params"]) >= {"N_R", "N_sigma", "gamma"}
    assert (tmp_path / "model.pt").is_file() and (tmp_path / "data" / "dataset.json").is_file()
    table = read_particles(summary["particles"])
    assert len(table["x_um"]) == summary["particle_count"]
    assert json.loads((tmp_path / "particles.json").read_text())["model_sha256"] == summary["model_sha256"]
    assert summary["training"]["stop_reason"] is None and summary["training"]["epochs_done"] == summary["training"]["epochs_planned"]
    # the table is refined, the sample's polystyrene kept: every particle the fit kept is in it or set apart
    refined = summary["refine"]
    assert refined["material_index_contrast"] == 0.26
    assert refined["kept_by_fit"] + refined["found_in_residual"] == summary["particle_count"] + refined["other_material"]
    assert {"refine", "residual"} <= set(summary["seconds"]) and json.loads((tmp_path / "particles.json").read_text())["refine"]["material"]["index_contrast"] == 0.26

    # again with another process spinning on a core: a fixed amount of work, so the same model
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        assert main(["demo", "--out", str(tmp_path / "loaded"), "--quick"]) == 0
    finally:
        busy.kill()
        busy.wait()
    assert (tmp_path / "loaded" / "particles.csv").read_bytes() == (tmp_path / "particles.csv").read_bytes()
    weights = [torch.load(folder / "model.pt", weights_only=True)["state_dict"] for folder in (tmp_path, tmp_path / "loaded")]  # the files differ in the data's path
    assert weights[0].keys() == weights[1].keys() and all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    logs = [json.loads((folder / "model.json").read_text()) for folder in (tmp_path, tmp_path / "loaded")]
    assert [e["train_loss"] for e in logs[0]["epochs"]] == [e["train_loss"] for e in logs[1]["epochs"]]


def test_generate_train_predict_evaluate_end_to_end(tmp_path):
    config = tmp_path / "c.toml"
    main(["config", "--write", str(config)])
    text = config.read_text().replace("z_max_um = 4800.0", "z_max_um = 2200.0").replace("z_step_um = 50.0", "z_step_um = 100.0")
    config.write_text(text.replace("size = 256", "size = 32").replace("per_tile = 12", "per_tile = 2"))
    calibration = tmp_path / "cal.json"
    calibration.write_text(json.dumps({"params": {"N_R": -0.5, "N_sigma": 0.2, "gamma": 0.9}, "ssim": 0.7}))
    assert main(["generate", "--config", str(config), "--calibration", str(calibration), "--groups", "3", "--out", str(tmp_path / "data"), "--seed", "1"]) == 0
    spec = json.loads((tmp_path / "data" / "dataset.json").read_text())
    assert spec["complete"] and spec["calibration"]["params"]["N_R"] == -0.5 and spec["processing"]["invert_experiment"]
    assert main(["train", str(tmp_path / "data"), "--out", str(tmp_path / "m.pt"), "--epochs", "1", "--device", "cpu", "--seed", "2"]) == 0
    log = json.loads((tmp_path / "m.json").read_text())
    assert log["settings"]["seed"] == 2 and len(log["epochs"]) == 1 and log["validation_groups"] == [2]
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "sim"), "--size", "64", "--particles", "3"]) == 0
    assert main(["predict", str(tmp_path / "sim" / "hologram.tif"), "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "p.csv"), "--config", str(config)]) == 0
    header = (tmp_path / "p.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["x_um", "y_um", "z_um", "diameter_um"] and "score" in header
    assert json.loads((tmp_path / "p.json").read_text())["model_sha256"] == log["best"]["sha256"]
    result = run("evaluate", tmp_path / "p.csv", tmp_path / "sim" / "particles.csv", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["n_truth"] == 3
    # a config for other optics is refused, naming the key; nothing is written
    config.write_text(config.read_text().replace("wavelength_um = 0.66", "wavelength_um = 0.532"))
    result = run("predict", tmp_path / "sim" / "hologram.tif", "--model", tmp_path / "m.pt", "--out", tmp_path / "q.csv", "--config", config)
    assert result.returncode == 2 and "optics.wavelength_um" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "q.csv").exists()
    result = run("train", tmp_path / "nothing", "--out", tmp_path / "x.pt")
    assert result.returncode == 2 and "nothing" in result.stderr


def test_calibrate_writes_contract_json(tmp_path):
    from napari_lbs._core import load_sample_hologram

    tifffile.imwrite(tmp_path / "h.tif", load_sample_hologram()[:256, :512])
    config = tmp_path / "c.toml"
    main(["config", "--write", str(config)])
    assert main(["calibrate", str(tmp_path / "h.tif"), "--config", str(config), "--out", str(tmp_path / "cal.json"), "--generations", "2", "--population", "6", "--seed", "3"]) == 0
    payload = json.loads((tmp_path / "cal.json").read_text())
    assert set(payload["params"]) >= {"N_R", "N_sigma", "gamma"}
    assert isinstance(payload["ssim"], float) and payload["roi"][2] == 256 and payload["roi"][1] == 0
    assert payload["history"][0].keys() >= {"generation", "best_fitness"} and len(payload["history"]) == 2
    assert payload["seconds"] > 0 and payload["provenance"]["seed"] == 3
    result = run("calibrate", tmp_path / "h.tif", "--config", config, "--out", tmp_path / "c2.json", "--roi", "400", "0")
    assert result.returncode == 2 and "roi" in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_refine_refuses_bad_input_and_replaces_only_its_own_outputs(tmp_path):
    from importlib.resources import files

    config = str(files("napari_lbs") / "data" / "microscope_example.toml")
    noise = np.random.default_rng(0)
    tifffile.imwrite(tmp_path / "h.tif", (1000 + 30 * noise.standard_normal((48, 48))).astype(np.float32))
    tifffile.imwrite(tmp_path / "bg.tif", (1000 + 30 * noise.standard_normal((48, 48))).astype(np.float32))
    tifffile.imwrite(tmp_path / "small.tif", (1000 + 30 * noise.standard_normal((16, 16))).astype(np.float32))
    base = ["refine", tmp_path / "h.tif", "--config", config, "--out", tmp_path / "t.csv"]
    for extra, culprit in ((["--background", tmp_path / "small.tif"], "small.tif"), (["--dark", tmp_path / "small.tif"], "small.tif"),
                           (["--index-contrast", "7"], "--index-contrast"), (["--config", tmp_path / "none.toml"], "none.toml")):
        result = run(*base, *extra)
        assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1 and culprit in result.stderr
        assert not (tmp_path / "t.csv").exists()
    assert main([*map(str, base), "--background", str(tmp_path / "bg.tif")]) == 0  # noise: nothing found, an empty table
    assert read_particles(tmp_path / "t.csv")["x_um"].size == 0
    assert json.loads((tmp_path / "t.json").read_text())["find"]["detections"] == 0
    assert main([*map(str, base)]) == 2  # exists
    assert main([*map(str, base), "--force"]) == 0
    (tmp_path / "other.json").write_text("{}")
    assert main(["refine", str(tmp_path / "h.tif"), "--config", config, "--out", str(tmp_path / "other.csv"), "--force"]) == 2  # never another file's JSON
    assert (tmp_path / "other.json").read_text() == "{}"
