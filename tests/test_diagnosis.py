"""The diagnose step, its command and its report, on the scene-conditioned engine (`diagnose_scene`).

One small frame (two Lorenz–Mie spheres on 256², recorded with 6-bit levels in an 8-bit file)
is diagnosed once for this module through the command line, with the engine's settings made
small (about 30 s on 2 cores); the pooling of frames, the progress and the refusals run on a
stand-in engine (tests/scene_reports.py). The engine's own tests: tests/test_nested_effects.py.
"""

import json
from functools import partial

import numpy as np
import pytest
import tifffile
from scene_reports import StandIn, scene_report

from napari_lbs._cli import main
from napari_lbs._core import InputError, SceneDiagnosis, SceneDiagnosisSettings, Stopped, effects_from_report, write_report
from napari_lbs._core.foundation import available_threads
from napari_lbs._core.physics import EFFECTS
from napari_lbs._core.pipeline import DIAGNOSED_FRAMES, DiagnoseRequest, diagnose, tiles_per_side

# the effect ids report.json always accounts for, tested or not (docs/formats.md, "Diagnosis report")
REPORT_EFFECT_IDS = {"illumination", "shot_noise", "quantization", "sensor_blur", "coherence", "particle_phase", "multiple_scattering", "parasitic_fringes", "spherical_wave"}
SMALL = partial(SceneDiagnosisSettings, particles=4, scene_particles=8)


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    """``napari-lbs diagnose frame.tif --tile 85 --seed 3`` on a small frame of 6-bit levels (the engine's settings made small); its folder.

    The spheres' rings are rendered to 1 cycle per pixel, aliased as a camera records them: the optics test reads the far rings.
    """
    import pandas as pd

    import napari_lbs._core.gap as gap
    from napari_lbs._core import load_config, particle_hologram

    folder = tmp_path_factory.mktemp("diagnosed")
    config = folder / "c.toml"
    config.write_text("[volume]\nz_min_um = 1800.0\nz_max_um = 2600.0\nz_step_um = 50.0\n")
    spheres = pd.DataFrame({"x_um": [150.0, 420.0], "y_um": [160.0, 400.0], "z_um": [2000.0, 2400.0], "diameter_um": [24.0, 26.0], "index_contrast": [0.26, 0.26]})
    light = particle_hologram((256, 256), spheres, load_config(config), reach_cycles_per_px=1.0) + np.random.default_rng(2).normal(0.0, 0.01, (256, 256))
    tifffile.imwrite(folder / "frame.tif", (np.round(light * 40) * 4).astype(np.uint8))  # a 6-bit converter in an 8-bit file
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(gap, "SceneDiagnosisSettings", SMALL)
        code = main(["diagnose", str(folder / "frame.tif"), "--config", str(config), "--out", str(folder / "report"), "--tile", "85", "--seed", "3"])
    assert code == 0
    return folder


def test_diagnose_writes_the_contract_report_its_figures_and_summary(diagnosed):
    from PIL import Image

    text = (diagnosed / "report" / "report.json").read_text()
    report = json.loads(text, parse_constant=lambda name: pytest.fail(f"report.json holds {name}"))
    gap, verdict = report["gap"], report["verdict"]
    assert isinstance(gap["metric"], str) and isinstance(gap["baseline"], float) and gap["tiles"] == 9 and gap["tile_px"] == 85
    effects = report["effects"]
    z = [e["z"] for e in effects if e["z"] is not None]
    assert z == sorted(z, reverse=True) and all(e["z"] is None for e in effects[len(z):])  # best first
    for effect in effects:
        assert isinstance(effect["gap_after"], float) and isinstance(effect["shrink"], float) and isinstance(effect["params"], dict), effect
        assert effect["shrink"] == pytest.approx(1.0 - effect["gap_after"] / gap["baseline"] if gap["baseline"] > 0 else 0.0)
        if effect["id"] in ("illumination", "sensor_blur", "parasitic_fringes", "coherence", "shot_noise") and effect["params"]:
            assert set(effect["params_err"]) == set(effect["params"]) and all(e is None or e >= 0 for e in effect["params_err"].values()), effect
    assert [group["particles"] for group in gap["by_depth"]] == [1, 1] and gap["by_depth"][0]["z_um"] < gap["by_depth"][1]["z_um"]
    assert {e["id"] for e in effects} | set(report["not_tested"]) >= REPORT_EFFECT_IDS
    assert isinstance(verdict["shrink"], float) and isinstance(verdict["residual"], float) and verdict["undecided"] == [] and verdict["catalog_explains"] is True
    # the file's levels: a converter of 6 bits at 1.6 times the mean light; the spheres: transparent, of index contrast 0.26
    assert verdict["id"] == "particle_phase+quantization"
    optics = report["particle_optics"]
    assert optics["model"] == "transparent" and optics["index_contrast"] == 0.26 and optics["power_spectrum"]["transparent_better"] == 9
    assert optics["through_focus"]["spheres"] == 2 and optics["through_focus"]["transparent_better"] == 2
    bits = next(e for e in effects if e["id"] == "quantization")["params"]
    assert abs(bits["bits"] - 6.0) < 0.1 and abs(bits["saturation"] - 1.6) < 0.1
    assert sum(report["posterior"].values()) == pytest.approx(1.0)
    assert report["frames"] == [{"name": str(diagnosed / "frame.tif"), "verdict": "particle_phase+quantization", "catalog_explains": True, "residual": verdict["residual"],
                                 "probability": verdict["probability"]}]
    assert 0.0 <= verdict["probability"] <= 1.0 and any(d["name"] == "particle_phase" and d["outcome"] == 1 for d in report["confidence"])
    assert report["provenance"]["seed"] == 3 and report["provenance"]["source"] == str(diagnosed / "frame.tif") and report["settings"]["grid"] == 3
    summary = (diagnosed / "report" / "report.md").read_text()
    assert "Verdict: **particle_phase+quantization**" in summary and "bits 6" in summary and "## Not tested" in summary
    assert "- Levels: a converter step of 4 counts" in summary and "Photon noise's slope in the finest filter (a second difference along each axis)" in summary
    for name in ("gap_where.png", "gap_effects.png"):
        with Image.open(diagnosed / "report" / name) as image:
            assert image.size[0] > 1000 and image.size[1] > 400


def test_a_report_of_diagnose_feeds_generate_effects_from(diagnosed, tmp_path):
    config = tmp_path / "tiny.toml"
    config.write_text("[volume]\nz_min_um = 1800.0\nz_max_um = 2200.0\nz_step_um = 100.0\n[tile]\nsize = 48\n")
    report = diagnosed / "report" / "report.json"
    assert main(["generate", "--config", str(config), "--groups", "1", "--out", str(tmp_path / "data"), "--effects-from", str(report)]) == 0
    dataset = json.loads((tmp_path / "data" / "dataset.json").read_text())
    assert dataset["effects"] == effects_from_report(json.loads(report.read_text())) and set(dataset["effects"]) == {"particle_phase", "quantization"}
    assert dataset["effects"]["particle_phase"]["index_contrast"] == 0.26  # the optics the frame's spheres were found to have, into the training data
    assert dataset["effects_source"]["verdict"] == "particle_phase+quantization"


def test_a_report_is_replaced_only_when_forced_and_never_written_through_a_link(diagnosed, tmp_path, capsys):
    folder = diagnosed / "report"
    before = {path.name: path.read_bytes() for path in folder.iterdir()}
    assert main(["diagnose", str(diagnosed / "frame.tif"), "--config", str(diagnosed / "c.toml"), "--out", str(folder)]) == 2  # refused before any work
    assert "report.json: exists" in capsys.readouterr().err and {path.name: path.read_bytes() for path in folder.iterdir()} == before
    diagnosis = SceneDiagnosis(json.loads((folder / "report.json").read_text()), np.full((2, 2), 0.01), None, 1.0)
    paths = write_report(diagnosis, tmp_path / "r")
    (tmp_path / "r" / "report.md").write_text("mine")
    with pytest.raises(InputError, match="report.json: exists; add force=True"):
        write_report(diagnosis, tmp_path / "r")
    assert (tmp_path / "r" / "report.md").read_text() == "mine"
    assert write_report(diagnosis, tmp_path / "r", force=True) == paths and (tmp_path / "r" / "report.md").read_text() != "mine"
    (tmp_path / "linked").mkdir()
    (tmp_path / "linked" / "gap_where.png").symlink_to(tmp_path / "r" / "report.md")
    with pytest.raises(InputError, match="symbolic link"):
        write_report(diagnosis, tmp_path / "linked", force=True)
    assert not (tmp_path / "linked" / "report.json").exists()


class Listener:
    """A progress callback with phases, as napari's steps have."""

    def __init__(self):
        self.phases, self.steps = [], []

    def __call__(self, done, total):
        self.steps.append((done, total))

    def phase(self, name):
        self.phases.append(name)


def test_several_frames_are_diagnosed_each_on_one_bar_and_pooled_by_majority(tmp_path, monkeypatch):
    import napari_lbs._core.gap as gap

    illumination = {"depth": 0.2, "x0": 0.0, "y0": 0.0}
    engine = StandIn([("illumination", True, {"illumination": illumination}), ("illumination+quantization", True), ("quantization", False)])
    monkeypatch.setattr(gap, "diagnose_scene", engine)
    frames = np.stack([1.0 + 0.01 * k + 0.1 * np.random.default_rng(k).random((256, 256)) for k in range(5)]).astype(np.float32)
    tifffile.imwrite(tmp_path / "rec.tif", frames, photometric="minisblack")
    listener = Listener()
    result = diagnose(DiagnoseRequest(tmp_path / "rec.tif", tmp_path / "report", tile_px=64), progress=listener)
    assert DIAGNOSED_FRAMES == 3 and [float(call["hologram"].mean()) for call in engine.calls] == pytest.approx([float(frames[k].mean()) for k in (0, 2, 4)])
    assert all(call["settings"].grid == 4 for call in engine.calls)
    # the step's default fits in one process per core, as predict --refine's (the API's default: one)
    assert all(call["settings"].refine.workers == available_threads() for call in engine.calls) and SceneDiagnosisSettings().refine.workers == 1
    # one pool of workers for the frames' fits: its processes start once
    assert engine.calls[0]["pool"] is not None and all(call["pool"] is engine.calls[0]["pool"] for call in engine.calls)
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert [f["name"] for f in report["frames"]] == [f"{tmp_path / 'rec.tif'}[frame {k}]" for k in (0, 2, 4)]
    assert [f["verdict"] for f in report["frames"]] == ["illumination", "illumination+quantization", "quantization"]
    # each effect named by two frames of three; the catalog explains two of them
    assert report["verdict"]["id"] == "illumination+quantization" and report["verdict"]["catalog_explains"] is True
    assert "majority of the 3 frames" in report["verdict"]["reason"] and result.value.report["verdict"] == report["verdict"]
    # one frame of three gives the pooled verdict, at its own 0.9
    assert report["verdict"]["probability"] == pytest.approx(0.9 / 3)
    # each named effect's parameters are the first naming frame's: what generate --effects-from adds
    # (an optional parameter the report leaves out, the envelope's waist, at its neutral value)
    assert effects_from_report(report) == {"illumination": {**illumination, "waist": EFFECTS["illumination"].neutral["waist"]}, "quantization": {"bits": 6.0, "saturation": 1.6}}
    pooled = {e["id"]: e for e in report["effects"]}
    assert sorted(name for name, e in pooled.items() if e["selected"]) == ["illumination", "quantization"]  # as the pooled verdict names them
    assert pooled["illumination"]["params_err"] == dict.fromkeys(illumination, 0.01)  # the naming frame's errors with its parameters
    # one bar: each frame's phases named, its steps within its third of the bar
    assert listener.phases[:2] == ["frame 1 of 3: particles found", "frame 1 of 3: the catalog's effects"] and listener.phases[-1] == "frame 3 of 3: the catalog's effects"
    assert [done / total for done, total in listener.steps[::2]] == pytest.approx([1 / 6, 1 / 6, 3 / 6, 3 / 6, 5 / 6, 5 / 6])
    # a stop in the second frame ends the diagnosis and writes nothing
    with pytest.raises(Stopped):
        diagnose(DiagnoseRequest(tmp_path / "rec.tif", tmp_path / "stopped"), should_stop=lambda: len(engine.calls) > 4)
    assert not (tmp_path / "stopped").exists()


def test_diagnose_scene_fits_in_the_pool_it_is_given_and_leaves_it_open(monkeypatch):
    from napari_lbs._core import ExperimentConfig
    from napari_lbs._core.foundation import WorkerPool
    from napari_lbs._core.gap import _scene_diagnosis, diagnose_scene

    used, closed = [], []
    monkeypatch.setattr(_scene_diagnosis, "_diagnosed", lambda *args: used.append(args[-1]))
    monkeypatch.setattr(WorkerPool, "close", lambda self: closed.append(self))
    frame = 1.0 + 0.1 * np.random.default_rng(0).random((128, 128))
    pool = WorkerPool(2)
    diagnose_scene(frame, ExperimentConfig(), pool=pool)
    diagnose_scene(frame, ExperimentConfig(), pool=pool)
    assert used == [pool, pool] and closed == []
    # without one, each call starts its own and ends it
    diagnose_scene(frame, ExperimentConfig())
    assert used[-1] is not pool and closed == [used[-1]]


def test_one_frame_s_report_is_its_diagnosis_with_one_frame(tmp_path, monkeypatch):
    import napari_lbs._core.gap as gap

    monkeypatch.setattr(gap, "diagnose_scene", StandIn([("sensor_blur", False)]))
    frame = 1.0 + 0.1 * np.random.default_rng(0).random((160, 200))
    result = diagnose(DiagnoseRequest(frame, tmp_path / "report", source="holo", roi=(10, 20)))
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["verdict"] == scene_report("sensor_blur", explains=False, tile_px=40)["verdict"] and report["roi"] == {"x": 10, "y": 20}
    assert report["frames"] == [{"name": "holo", "verdict": "sensor_blur", "catalog_explains": False, "residual": 0.2, "probability": 0.9}]
    assert result.summary.startswith("verdict: sensor_blur; probability 0.90;") and "does not explain" in result.summary
    # the particles' optics left undecided is said beside the verdict: a verdict naming nothing is not a claim that they are opaque
    assert "; particle optics undecided;" in result.summary


@pytest.mark.parametrize(("extra", "shape", "culprit"), [
    ([], (64, 64), "h.tif: expected at least 128 pixels a side"),
    (["--tile", "129"], (256, 256), "--tile 129: a 256x256 (x by y) frame holds 1 tile(s)"),
    (["--tile", "100"], (256, 256), "--tile 100: a 256x256 (x by y) frame holds 2 tile(s) of 100 px in a line; expected at most 85 px (3 tiles)"),
    (["--roi", "300", "10"], (256, 256), "--roi 300 10: outside the 256x256"),
    (["--background", "{tmp}/bg.tif"], (256, 256), "bg.tif: expected the hologram's shape"),
    (["--calibration", "{tmp}/h.tif"], (256, 256), "h.tif"),
])
def test_diagnose_refuses_bad_input_in_one_line_before_any_work(tmp_path, capsys, monkeypatch, extra, shape, culprit):
    import napari_lbs._core.gap as gap

    monkeypatch.setattr(gap, "diagnose_scene", lambda *a, **k: pytest.fail("the diagnosis ran"))
    tifffile.imwrite(tmp_path / "h.tif", (1.0 + 0.1 * np.random.default_rng(0).random(shape)).astype(np.float32))
    tifffile.imwrite(tmp_path / "bg.tif", (1.0 + 0.1 * np.random.default_rng(1).random((128, 128))).astype(np.float32))
    capsys.readouterr()
    (tmp_path / "c.toml").write_text("")  # the defaults
    code = main(["diagnose", str(tmp_path / "h.tif"), "--config", str(tmp_path / "c.toml"), "--out", str(tmp_path / "r"), *[part.format(tmp=tmp_path) for part in extra]])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and culprit in lines[0], lines
    assert not (tmp_path / "r").exists()


def test_tiles_per_side_follows_the_tile_edge_within_3_to_16():
    assert tiles_per_side((400, 384), 128) == 3 and tiles_per_side((1024, 1024), 32) == 16 and tiles_per_side((1024, 1024), 200) == 5
    with pytest.raises(InputError, match="^tile 600: a 1024x1024"):
        tiles_per_side((1024, 1024), 600, flag="tile")


def test_the_report_shows_the_scene_s_numbers(tmp_path):
    report = scene_report("illumination")
    report["scene"] = {"particles": 12, "per_mm2": 2.4, "in_size_range": 10, "below_size_range": 2, "above_size_range": 0, "percentiles": [5, 25, 50, 75, 95],
                       "diameter_um": [21.0, 24.0, 25.1, 25.7, 29.0], "index_contrast": [0.2, 0.25, 0.26, 0.27, 0.3], "z_um": [1900.0, 2800.0, 3600.0, 3900.0, 4200.0],
                       "small_scatterers": {"count": 2, "per_256px_tile": 0.125, "diameter_um": [11.0, 17.5]}}
    write_report(SceneDiagnosis(report, np.full((2, 2), 0.01), None, 1.0), tmp_path / "r")
    summary = (tmp_path / "r" / "report.md").read_text()
    assert "## The scene" in summary and "12 particles fitted (2.4 per mm²" in summary and "10 within the config's sizes, 2 below" in summary
    assert "diameter median 25.1 (quartiles 24–25.7) µm" in summary and "Depth median 3.6 (quartiles 2.8–3.9) mm" in summary
    assert "Small scatterers (below the config's sizes): 2, 0.12 per 256-pixel tile, 11–17.5 µm." in summary


def test_the_report_shows_a_blur_by_direction(tmp_path):
    report = scene_report("sensor_blur")
    report["gap"]["directional_blur"] = {"gain_nats": 19131.0, "z": 4.0, "variance_difference_px2": 9.72, "angle_rad": 0.512}
    write_report(SceneDiagnosis(report, np.full((2, 2), 0.01), None, 1.0), tmp_path / "r")
    summary = (tmp_path / "r" / "report.md").read_text()
    assert "Blur by direction (motion, astigmatism; outside the catalog): held-out gain 19131 nats, sign test z 4.00" in summary
    assert "exceeds the short one's by 9.72 px² at 29° from the x axis" in summary


def test_the_report_shows_the_blur_by_depth_where_a_blur_was_selected(tmp_path):
    report = scene_report("coherence")
    report["blur_by_depth"] = {"depths_um": [2000.0, 2500.0, 3000.0, 3500.0, 4000.0], "sigma_px": [[0.6, 0.75, 0.9, 1.05, 1.2], [0.62, 0.74, 0.88, 1.06, 1.21]],
                               "sensor_sigma_px": 0.0, "theta_mrad": 0.66, "t_sensor": 0.1, "t_source": 21.0, "z_sensor": 0.08, "z_source": 3.72, "dof": 3,
                               "origin": ["coherence"]}
    write_report(SceneDiagnosis(report, np.full((2, 2), 0.01), None, 1.0), tmp_path / "r")
    summary = (tmp_path / "r" / "report.md").read_text()
    assert "## The blur by depth" in summary and "θ 0.66 mrad (t 21.0, z 3.7) on 3 degrees of freedom" in summary and "**coherence**" in summary
    assert "| 3.00 | 0.9 | 0.88 |" in summary
    write_report(SceneDiagnosis(scene_report("illumination"), np.full((2, 2), 0.01), None, 1.0), tmp_path / "s")
    assert "blur by depth" not in (tmp_path / "s" / "report.md").read_text()


def test_the_unexplained_share_is_told_by_the_particles_depth():
    """Four particles, each at its own depth: what is left about the deep ones is their whole structure, about the shallow ones none of it."""
    import pandas as pd

    from napari_lbs._core.gap._heldout import TileSplit
    from napari_lbs._core.gap._unexplained import share_by_depth

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:256, 0:256]
    table = pd.DataFrame({"x_um": [40.0, 200.0, 60.0, 190.0], "y_um": [50.0, 60.0, 200.0, 190.0], "z_um": [1000.0, 2000.0, 3000.0, 4000.0]})
    rings = [0.2 * np.cos(np.hypot(yy - y, xx - x) / 3.0) * np.exp(-np.hypot(yy - y, xx - x) ** 2 / 800.0) for x, y in zip(table["x_um"], table["y_um"], strict=True)]
    noise = rng.normal(0.0, 0.002, (256, 256))
    data = 1.0 + sum(rings) + noise
    left = rings[2] + rings[3] + noise  # the two deep particles' rings are not explained
    groups = share_by_depth((data - 1.0, data - 1.0), (left, left), data, table, TileSplit.of((256, 256), grid=4), 0.002**2, pixel_um=1.0, reach_px=30)
    assert [g["z_um"] for g in groups] == [1000.0, 2000.0, 3000.0, 4000.0] and all(g["particles"] == 1 and g["pixels"] > 1000 for g in groups)
    assert all(g["baseline"] == pytest.approx(1.0, abs=0.05) for g in groups)
    assert [g["after"] for g in groups][:2] == pytest.approx([0.0, 0.0], abs=0.02) and [g["after"] for g in groups][2:] == pytest.approx([1.0, 1.0], abs=0.05)


def test_the_report_shows_each_parameter_with_its_error_and_the_share_left_by_depth(tmp_path):
    report = scene_report("sensor_blur")
    blur = next(e for e in report["effects"] if e["id"] == "sensor_blur")
    blur["params"], blur["params_err"] = {"sigma_px": 1.0213}, {"sigma_px": 0.01234}
    envelope = next(e for e in report["effects"] if e["id"] == "illumination")
    envelope["params"], envelope["params_err"] = {"depth": 0.36, "y0": 0.5}, {"depth": 0.098, "y0": None}  # y0 on its bound
    report["gap"]["by_depth"] = [{"z_um": 2400.0, "particles": 20, "pixels": 5000, "baseline": 0.4, "after": 0.1},
                                 {"z_um": 4100.0, "particles": 20, "pixels": 5200, "baseline": 0.5, "after": 0.35}]
    write_report(SceneDiagnosis(report, np.full((2, 2), 0.01), None, 1.0), tmp_path / "r")
    summary = (tmp_path / "r" / "report.md").read_text()
    assert "sigma_px 1.02 ± 0.012" in summary and "depth 0.36 ± 0.098, y0 0.5 (no error bar)" in summary
    assert "| 2.40 | 20 | 0.4 | 0.1 |" in summary and "| 4.10 | 20 | 0.5 | 0.35 |" in summary
    from PIL import Image

    write_report(SceneDiagnosis(scene_report("sensor_blur"), np.full((2, 2), 0.01), None, 1.0), tmp_path / "without")
    with Image.open(tmp_path / "r" / "gap_where.png") as with_depth, Image.open(tmp_path / "without" / "gap_where.png") as without:
        assert with_depth.size[0] > 1.3 * without.size[0]  # a third panel: what is left by the particles' depth
