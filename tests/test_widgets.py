"""Dock widgets in a real viewer (pytest-qt under xvfb-run): each loaded through the manifest,
run on tiny data to completion, stopped mid-run, and refused invalid input."""

import json
import os

import numpy as np
import pytest

from napari_lbs._core import ExperimentConfig, random_particle_field, simulate_hologram, write_particles
from napari_lbs._core.foundation._config import config_to_toml

TIMEOUT_MS = 180_000


@pytest.fixture(autouse=True)
def isolated_settings(tmp_path_factory):
    from qtpy.QtCore import QSettings

    QSettings.setPath(QSettings.Format.NativeFormat, QSettings.Scope.UserScope, str(tmp_path_factory.mktemp("qsettings")))


@pytest.fixture(autouse=True)
def offered_pixel_size(monkeypatch):
    """An image added in code is in pixels: a step with an empty config asks its pixel size, answered here with the one offered."""
    from qtpy.QtWidgets import QInputDialog

    monkeypatch.setattr(QInputDialog, "getDouble", lambda parent, title, label, value, *args, **kwargs: (value, True))


def tiny_config_file(path, size=48):
    config = ExperimentConfig.from_dict({
        "volume": {"z_min_um": 1800.0, "z_max_um": 2200.0, "z_step_um": 100.0},
        "particles": {"per_tile": 3, "layer_step_um": 200.0},
        "tile": {"size": size},
    })
    path.write_text(config_to_toml(config))
    return path, config


def dock(viewer, name):
    _, widget = viewer.window.add_plugin_dock_widget("napari-lbs", name)
    return widget


def run_to_end(qtbot, widget):
    assert widget._run.enabled, widget._status.value
    widget._run.clicked.emit()
    qtbot.waitUntil(lambda: widget._worker is not None or widget._run.enabled, timeout=5000)
    qtbot.waitUntil(lambda: widget._worker is None, timeout=TIMEOUT_MS)
    assert widget._progress_bar is None and widget._run.enabled and not widget._stop.enabled


def simulated(config, shape=(96, 96), count=6, seed=1):
    field = random_particle_field(shape, count=count, diameter_min_um=20, diameter_max_um=30, layers_um=config.layer_depths_um(), pixel_um=2.2, seed=seed)
    return simulate_hologram(field, wavelength_um=0.66), field


def test_backprop_widget_makes_a_micrometre_z_stack_and_refuses_a_3d_layer(make_napari_viewer, qtbot, tmp_path):
    viewer = make_napari_viewer()
    config_path, config = tiny_config_file(tmp_path / "c.toml")
    hologram, _ = simulated(config)
    viewer.add_image(np.zeros((3, 32, 32), np.float32), name="stack")
    widget = dock(viewer, "1 Back-propagation")
    widget.hologram.value = viewer.layers["stack"]
    assert not widget._run.enabled and "2-D" in widget._status.value
    viewer.add_image(hologram, name="holo")
    widget.hologram.value = viewer.layers["holo"]
    widget.config.value = tmp_path / "missing.toml"
    assert not widget._run.enabled and "not found" in widget._status.value
    widget.config.value = config_path
    run_to_end(qtbot, widget)
    layer = viewer.layers["holo z-stack"]
    assert layer.data.shape == (5, 96, 96)
    assert tuple(layer.scale) == pytest.approx((100.0, 2.2, 2.2)) and layer.translate[0] == pytest.approx(1800.0)
    assert layer.metadata["z_um"] == [1800.0, 1900.0, 2000.0, 2100.0, 2200.0]


def test_calibration_widget_fits_on_the_roi_writes_json_and_stops(make_napari_viewer, qtbot, tmp_path, monkeypatch):
    from napari_lbs._core import load_sample_hologram

    viewer = make_napari_viewer()
    viewer.add_image(load_sample_hologram()[:256, :320], name="real")
    widget = dock(viewer, "2 Calibration")
    widget.hologram.value = viewer.layers["real"]
    widget.add_roi.clicked.emit()
    roi = viewer.layers["reference ROI"]
    roi.data = [np.array([[10.4, 40.2], [200, 300]])]  # dragged by hand: snapped to one 256² tile
    assert np.allclose(np.asarray(roi.data[0]).min(axis=0), [10, 40]) and np.allclose(np.ptp(np.asarray(roi.data[0]), axis=0), [256, 256])
    roi.data = [np.array([[0, 50], [256, 306]])]
    widget.generations.value, widget.population.value = 2, 4
    widget.output.value = tmp_path / "cal.json"
    run_to_end(qtbot, widget)
    payload = json.loads((tmp_path / "cal.json").read_text())
    assert payload["roi"] == [50, 0, 256] and len(payload["history"]) == 2
    assert viewer.layers["I_e (experiment)"].data.shape == (256, 256) and "I_s (synthetic)" in viewer.layers
    # a long run, stopped in its set-up: nothing to keep, within 2 s
    import time

    widget.generations.value, widget.population.value = 500, 24
    widget.output.value = tmp_path / "cal2.json"
    widget._run.clicked.emit()
    qtbot.waitUntil(lambda: widget._bar.value > 0, timeout=60_000)  # the set-up's progress is shown
    clicked = time.perf_counter()
    widget._stop.clicked.emit()
    qtbot.waitUntil(lambda: widget._worker is None, timeout=TIMEOUT_MS)
    assert time.perf_counter() - clicked < 2.0 and "nothing was written" in widget._status.value and not (tmp_path / "cal2.json").exists()
    # stopped in its second generation (24 candidates, seconds of work): the best so far kept within 2 s, widget ready again
    widget._run.clicked.emit()
    qtbot.waitUntil(lambda: len(widget._live_history) == 1, timeout=TIMEOUT_MS)
    qtbot.wait(300)
    clicked = time.perf_counter()
    widget._stop.clicked.emit()
    qtbot.waitUntil(lambda: widget._worker is None, timeout=TIMEOUT_MS)
    assert time.perf_counter() - clicked < 2.0
    assert widget._run.enabled and widget._progress_bar is None
    assert json.loads((tmp_path / "cal2.json").read_text())["stopped"] is True
    assert "(stopped)" in widget._status.value
    # an existing file is replaced only once the user says so
    from qtpy.QtWidgets import QMessageBox

    asked = []
    monkeypatch.setattr(QMessageBox, "warning", lambda *args: asked.append(args[2]) or QMessageBox.StandardButton.Cancel)
    before = (tmp_path / "cal2.json").read_bytes()
    widget._run.clicked.emit()
    qtbot.waitUntil(lambda: widget._worker is None, timeout=TIMEOUT_MS)
    assert "cal2.json exists and will be replaced" in asked[0] and "not run" in widget._status.value
    assert (tmp_path / "cal2.json").read_bytes() == before


def test_generate_takes_a_diagnosis_report_s_effects_and_small_scatterers(make_napari_viewer, qtbot, tmp_path):
    viewer = make_napari_viewer()
    config_path, _ = tiny_config_file(tmp_path / "c.toml")
    generate = dock(viewer, "3 Synthetic data")
    generate.config.value = config_path
    generate.output.value = tmp_path / "data"
    broken = tmp_path / "calibration.json"
    broken.write_text(json.dumps({"params": {}}))
    generate.report.value = broken
    assert not generate._run.enabled and "not a diagnosis report" in generate._status.value
    report = tmp_path / "report.json"
    effects = [{"id": "quantization", "params": {"bits": 8.0, "saturation": 2.0}}]
    small = {"count": 40, "per_256px_tile": 2.5, "diameter_um": [6.0, 17.0]}
    report.write_text(json.dumps({"verdict": {"id": "quantization"}, "effects": effects, "scene": {"small_scatterers": small}}))
    generate.report.value = report
    # 2.5 a 256-pixel tile is 0.09 a 48-pixel one: none; the sizes follow the report where the field holds its count
    assert generate._run.enabled, generate._status.value
    assert generate.impurities.value == 0
    small["per_256px_tile"] = 64.0  # 2.25 a 48-pixel tile
    report.write_text(json.dumps({"verdict": {"id": "quantization"}, "effects": effects, "scene": {"small_scatterers": small}}))
    generate.report.value = tmp_path / "none.json"
    generate.report.value = report
    assert generate.impurities.value == 2
    request = generate.prepare()
    assert request.effects == {"quantization": {"bits": 8.0, "saturation": 2.0}} and request.effects_source["verdict"] == "quantization"
    assert (request.distractors.impurities_per_tile, request.distractors.impurity_diameter_min_um, request.distractors.impurity_diameter_max_um) == (2, 6.0, 17.0)
    again = dock(viewer, "3 Synthetic data")  # napari started again: the remembered report's sizes go with the remembered count
    assert again.impurities.value == 2 and again.prepare().distractors.impurity_diameter_max_um == 17.0
    generate.impurities.value = 3  # the user's own count: the default sizes
    assert generate.prepare().distractors.impurity_diameter_max_um == 14.0
    assert generate.prepare().sizes is None  # the report's scene sized no particles
    # the particles' sizes its scene fitted (within the config's 20-30 µm) are drawn, unless the box says otherwise
    scene = {"small_scatterers": small, "in_size_range": 40, "percentiles": [5, 25, 50, 75, 95], "diameter_um": [23.0, 24.0, 25.0, 26.0, 27.0]}
    report.write_text(json.dumps({"verdict": {"id": "quantization"}, "effects": effects, "scene": scene}))
    assert generate.prepare().sizes.diameters_um == (23.0, 24.0, 25.0, 26.0, 27.0)
    generate.measured_sizes.value = False
    assert generate.prepare().sizes is None


def test_generate_train_predict_widgets_from_data_to_points(make_napari_viewer, qtbot, tmp_path, monkeypatch):
    viewer = make_napari_viewer()
    config_path, config = tiny_config_file(tmp_path / "c.toml")
    generate = dock(viewer, "3 Synthetic data")
    generate.config.value = config_path
    generate.groups.value = 4
    generate.output.value = tmp_path / "data"
    generate.effects.value = "particle_phase:index_contrast=abc"
    assert not generate._run.enabled and "particle_phase.index_contrast" in generate._status.value
    # the demo's recipe: transparent spheres, with unlabelled impurities and neighbours
    generate.effects.value = "particle_phase:index_contrast=0.26,transmission=1"
    generate.impurities.value = 2
    generate.neighbours_margin.value = 16
    run_to_end(qtbot, generate)
    spec = json.loads((tmp_path / "data" / "dataset.json").read_text())
    assert spec["complete"] and spec["effects"]["particle_phase"]["index_contrast"] == 0.26
    assert spec["distractors"]["impurities_per_tile"] == 2 and spec["distractors"]["neighbours_margin_px"] == 16
    # the stack layout: the reconstruction grid plus 8 context planes beyond each end
    assert viewer.layers["training input (group 0)"].data.shape == (len(config.volume.planes_um()) + 16, 48, 48)

    train = dock(viewer, "4 Training")
    train.data.value = tmp_path / "nothing"
    assert not train._run.enabled and "not a napari-lbs data set" in train._status.value
    train.data.value = tmp_path / "data"
    train.output.value = tmp_path / "m.pt"
    train.epochs.value = 1
    train.device.value = "cpu"
    run_to_end(qtbot, train)
    assert (tmp_path / "m.pt").is_file() and train._plot.batches and train._plot.epochs

    hologram, field = simulated(config)
    viewer.add_image(hologram, name="holo")
    write_particles(tmp_path / "truth.csv", field.table())
    predict = dock(viewer, "5 Prediction")
    predict.hologram.value = viewer.layers["holo"]
    predict.model.value = tmp_path / "m.pt"
    predict.reference.value = tmp_path / "truth.csv"
    predict.device.value = "cpu"
    run_to_end(qtbot, predict)
    points = viewer.layers["holo particles"]
    assert set(points.features.columns) >= {"diameter_um", "z_um", "score"}
    assert points.metadata["provenance"]["model_sha256"] and points.metadata["metrics"]["n_truth"] == 6
    # refined: the fit's columns become features to colour by, the provenance says how
    predict.refine.value = True
    run_to_end(qtbot, predict)
    refined = viewer.layers[-1]
    assert refined is not points and {"index_contrast", "z_err_um", "refined"} <= set(refined.features.columns)
    fit = refined.metadata["provenance"]["refine"]
    assert fit["detections"] >= fit["kept"] and fit["kept"] + fit["residual"]["found"] == len(refined.data)
    assert refined.metadata["provenance"]["threshold"] == 0.8 * refined.metadata["provenance"]["model_threshold"]
    predict.colour_by.value = "index_contrast"
    assert refined.border_color.shape == (len(refined.data), 4)
    # the size-index scatter: the refined particles, or (this small model's detections all dropped by the fit) a line saying so
    assert len(predict._plot.axes.containers) == 1 if len(refined.data) else "no particle" in predict._plot.axes.texts[0].get_text()
    # the sample's material: the gate is recorded and drawn; a bad value or one without refine is refused in one line
    predict.material.value = "0.26"
    run_to_end(qtbot, predict)
    gate = viewer.layers[-1].metadata["provenance"]["refine"]["material"]
    assert gate["index_contrast"] == 0.26 and gate["other_material"] == len(gate["other_particles"]["x_um"])
    predict.material.value = "polystyrene"
    assert not predict._run.enabled and "material" in predict._status.value
    predict.material.value = "0.26"
    predict.refine.value = False
    assert not predict._run.enabled and "tick refine" in predict._status.value
    predict.material.value = ""
    # a model for other optics is a warning to confirm; declined, nothing runs and the widget stays usable
    from qtpy.QtWidgets import QMessageBox

    monkeypatch.setattr(QMessageBox, "warning", lambda *args: QMessageBox.StandardButton.Cancel)
    other = config.to_dict()
    other["optics"]["wavelength_um"] = 0.532
    (tmp_path / "other.toml").write_text(config_to_toml(ExperimentConfig.from_dict(other)))
    predict.config.value = tmp_path / "other.toml"
    run_to_end(qtbot, predict)
    assert "not run" in predict._status.value and "optics.wavelength_um" in predict._status.value


def test_training_widget_stop_keeps_a_model(make_napari_viewer, qtbot, tmp_path):
    import time

    from napari_lbs._core import generate_dataset

    _, config = tiny_config_file(tmp_path / "c.toml")
    generate_dataset(tmp_path / "data", config, groups=3, seed=0)
    viewer = make_napari_viewer()
    train = dock(viewer, "4 Training")
    train.data.value = tmp_path / "data"
    train.output.value = tmp_path / "m.pt"
    train.epochs.value = 500
    train.device.value = "cpu"
    train._run.clicked.emit()
    qtbot.waitUntil(lambda: len(train._plot.epochs) >= 1, timeout=TIMEOUT_MS)  # a validated model to keep
    qtbot.wait(300)  # into the next epoch's batches
    clicked = time.perf_counter()
    train._stop.clicked.emit()
    qtbot.waitUntil(lambda: train._worker is None, timeout=TIMEOUT_MS)
    ended = time.perf_counter() - clicked
    assert ended < 2.0, f"training ended {ended:.1f} s after Stop"  # 500 epochs were asked for
    assert train._run.enabled and (tmp_path / "m.pt").is_file() and train.result.stopped


def test_synthetic_sample_and_particle_csv_reader_writer_round_trip(make_napari_viewer, tmp_path):
    viewer = make_napari_viewer()
    layers = viewer.open_sample("napari-lbs", "synthetic_hologram")
    image, truth = layers
    assert image.data.shape == (512, 512) and truth.data.shape == (48, 3)
    assert tuple(image.scale) == (2.2, 2.2) and image.metadata["provenance"]["seed"] == 2024
    path = tmp_path / "truth.csv"
    truth.save(str(path), plugin="napari-lbs")
    reread = viewer.open(str(path), plugin="napari-lbs")[0]
    np.testing.assert_allclose(reread.data, truth.data, rtol=0, atol=1e-5)
    np.testing.assert_allclose(reread.features["diameter_um"], truth.features["diameter_um"], rtol=1e-6)


def test_the_reader_knows_a_particle_table_saved_by_excel_and_hands_other_csvs_on(tmp_path):
    from napari_lbs._io_plugin import _read_with_napari, get_reader, read_particle_csv

    excel = tmp_path / "excel.csv"  # Excel's "CSV UTF-8": a byte-order mark, and quoted names
    excel.write_bytes('\ufeff"x_um","y_um","z_um","diameter_um"\r\n1,2,1800,20\r\n'.encode())
    assert get_reader(str(excel)) is read_particle_csv
    other = tmp_path / "other.csv"
    other.write_text("index,axis-0,axis-1\n0,1,2\n")
    assert get_reader(str(other)) is _read_with_napari and get_reader(str(tmp_path / "a.tif")) is None


def test_diagnosis_widget_diagnoses_a_stack_s_frames_shows_the_verdict_and_maps_the_gap_and_stops(make_napari_viewer, qtbot, tmp_path, monkeypatch):
    import time

    from scene_reports import StandIn

    import napari_lbs._core.gap as gap

    engine = StandIn([("illumination", True), ("illumination+sensor_blur", True), ("sensor_blur", False)])
    monkeypatch.setattr(gap, "diagnose_scene", engine)
    viewer = make_napari_viewer()
    config_path, config = tiny_config_file(tmp_path / "c.toml")
    frames = np.stack([simulated(config, shape=(256, 256), count=16, seed=seed)[0] for seed in (1, 2, 3, 4)])
    viewer.add_image(frames, name="recording", scale=(1.0, 2.2, 2.2))
    widget = dock(viewer, "6 Gap diagnosis")
    widget.hologram.value = viewer.layers["recording"]
    widget.config.value = config_path
    widget.tile.value = 200
    assert not widget._run.enabled and "tile 200: a 256x256 (x by y) frame holds 1 tile(s)" in widget._status.value
    widget.tile.value = 64
    widget.output.value = tmp_path / "report"
    phases = []
    widget._relay.progress.connect(lambda done, total, at, phase: phases.append(phase))
    run_to_end(qtbot, widget)
    # three of the four frames, evenly spaced, each diagnosed on 4 x 4 tiles; the verdict: what most of them name
    assert len(engine.calls) == 3 and all(call["settings"].grid == 4 for call in engine.calls)
    written = json.loads((tmp_path / "report" / "report.json").read_text())
    assert [f["name"] for f in written["frames"]] == ["recording[frame 0]", "recording[frame 2]", "recording[frame 3]"]
    assert written["verdict"]["id"] == "illumination+sensor_blur" and written["provenance"]["source"] == "recording"
    assert "frame 3 of 3: the catalog's effects" in phases and "verdict: illumination+sensor_blur" in widget._status.value
    assert widget._verdict.value.startswith("verdict: illumination+sensor_blur (probability 0.30); named in a majority of the 3 frames")
    # the named effects' parameters with their errors, each from a frame that named it (sensor_blur: the third)
    assert widget._verdict.value.endswith("\nfitted: illumination (depth 0.3 ± 0.01, x0 0.1 ± 0.01, y0 -0.1 ± 0.01); sensor_blur (sigma_px 0.8 ± 0.01)")
    assert len(widget._plot.axes.patches) == len(written["effects"])  # each effect's z
    layer = viewer.layers["gap: unexplained share of the structure"]
    assert layer.data.shape == (4, 4) and tuple(layer.scale) == pytest.approx((140.8, 140.8)) and tuple(layer.translate) == pytest.approx((69.3, 69.3))
    assert layer.colorbar.visible
    # Stop ends a run within the diagnosis, nothing written
    monkeypatch.setattr(gap, "diagnose_scene", StandIn(wait_for_stop=True))
    widget.output.value = tmp_path / "stopped"
    widget._run.clicked.emit()
    qtbot.waitUntil(lambda: widget._stop.enabled, timeout=5000)
    clicked = time.perf_counter()
    widget._stop.clicked.emit()
    qtbot.waitUntil(lambda: widget._worker is None, timeout=10_000)
    assert time.perf_counter() - clicked < 2.0 and "stopped" in widget._status.value and not (tmp_path / "stopped").exists()


def test_batch_widget_turns_a_recording_into_points_over_time_and_tracks_and_stops(make_napari_viewer, qtbot, tmp_path, detector, tiny_config):
    import tifffile

    from napari_lbs._core import simulate_sequence

    recording = simulate_sequence(tiny_config, frames=4, flow="uniform", size=128, count=6, speed_um=6.0, seed=2)
    tifffile.imwrite(tmp_path / "run.tif", recording.frames, photometric="minisblack")
    viewer = make_napari_viewer()
    workflow = dock(viewer, "LBS workflow")
    widget = workflow.batch
    assert workflow.tabs.tabText(6) == "7 Batch" and widget.background.value == "auto"  # as the command line: no median that holds slow particles
    workflow.training.produced.emit(detector.path)  # Training's model is Batch's model too
    assert widget.model.value == detector.path
    widget.frames.value = tmp_path / "gone.tif"
    assert not widget._run.enabled and "not found" in widget._status.value
    widget.frames.line_edit.value = str(tmp_path / "*.png")
    assert not widget._run.enabled and "no file matches" in widget._status.value
    (tmp_path / "empty").mkdir()
    widget.frames.value = tmp_path / "empty"  # a folder without images: refused when run, the widget stays usable
    run_to_end(qtbot, widget)
    assert "error" in widget._status.value and "holds no images" in widget._status.value

    widget.frames.value = tmp_path / "run.tif"
    widget.device.value = "cpu"
    widget.search_range.value, widget.memory.value = 10.0, 1  # the eager model finds hundreds a frame: a short range
    run_to_end(qtbot, widget)
    points, tracks = viewer.layers["run.tif particles"], viewer.layers["run.tif tracks"]
    assert points.ndim == 4 and points.axis_labels[0] == "frame" and viewer.dims.axis_labels[0] == "frame"
    assert set(points.data[:, 0]) == {0, 1, 2, 3} and viewer.dims.nsteps[0] == 4  # one time step per frame
    assert all(str(unit) == "micrometer" for layer in (points, tracks) for unit in layer.units[1:])
    world = points.data[:, 1:] * points.scale[1:] + points.translate[1:]
    np.testing.assert_allclose(world[:, 0], points.features["z_um"])  # (z, y, x) in µm on the plane grid
    assert tuple(points.scale) == pytest.approx((1.0, 100.0, 2.2, 2.2)) and tuple(tracks.scale) == tuple(points.scale)
    assert len(np.unique(tracks.data[:, 0])) == len(np.unique(points.features["track"])) and len(tracks.data) == len(points.data)
    assert points.metadata["provenance"]["model_sha256"] == detector.sha256 and points.metadata["provenance"]["background"] == "auto"
    assert tracks.metadata["linking"] == {"search_range_um": 10.0, "axial_search_range_um": None, "memory": 1}
    assert "4 frames" in widget._status.value and "tracks" in widget._status.value
    assert widget._timing.value.startswith("tracks 4/4") and widget._bar.value == widget._bar.max  # its last phase, linking frame by frame, named

    layers = len(viewer.layers)
    widget._run.clicked.emit()
    widget._stop.clicked.emit()
    qtbot.waitUntil(lambda: widget._worker is None, timeout=TIMEOUT_MS)
    assert widget._run.enabled and "stopped" in widget._status.value and len(viewer.layers) == layers


def test_batch_widget_refuses_workers_with_a_scheduler_and_resumes_a_stopped_run(make_napari_viewer, qtbot, tmp_path, detector, tiny_config):
    import tifffile
    from pandas.testing import assert_frame_equal

    from napari_lbs._core import simulate_sequence

    # two rounds of the frames the local scheduler runs at once and one more, so a stop in the second leaves some to resume
    frames = 2 * (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1) + 1
    recording = simulate_sequence(tiny_config, frames=frames, flow="uniform", size=128, count=4, speed_um=6.0, seed=3)
    tifffile.imwrite(tmp_path / "run.tif", recording.frames, photometric="minisblack")
    viewer = make_napari_viewer()
    widget = dock(viewer, "7 Batch")
    widget.frames.value, widget.model.value, widget.device.value, widget.search_range.value = tmp_path / "run.tif", detector.path, "cpu", 10.0
    widget.workers.value, widget.scheduler.value = 2, "tcp://head:8786"
    assert not widget._run.enabled and "either a number of local workers or a scheduler address, not both" in widget._status.value
    widget.workers.value, widget.scheduler.value = 0, "head:8786"
    assert not widget._run.enabled and "scheme://host:port" in widget._status.value
    widget.scheduler.value = "tcp://head:8786"
    assert widget._run.enabled, widget._status.value
    widget.scheduler.value = ""
    run_to_end(qtbot, widget)  # in one go, in memory
    once = viewer.layers["run.tif particles"]
    assert {key: once.metadata[key] for key in ("workers", "scheduler", "work_dir")} == {"workers": None, "scheduler": None, "work_dir": None}
    expected, features = once.data.copy(), once.features.copy()
    viewer.layers.clear()

    widget.work_dir.value = tmp_path / "work"
    widget._run.clicked.emit()
    qtbot.waitUntil(lambda: widget._bar.value >= 1, timeout=TIMEOUT_MS)
    widget._stop.clicked.emit()  # the frames in flight stop between planes, the finished ones stay in the work folder, the others are not predicted
    qtbot.waitUntil(lambda: widget._worker is None, timeout=TIMEOUT_MS)
    kept = {path.name: path.stat().st_mtime_ns for path in (tmp_path / "work").glob("frame_*.npz")}
    assert 0 < len(kept) < frames and len(viewer.layers) == 0
    assert f"stopped after {len(kept)} of {frames} frames" in widget._status.value and "run again to resume" in widget._status.value
    run_to_end(qtbot, widget)
    points = viewer.layers["run.tif particles"]
    assert points.metadata["work_dir"] == str(tmp_path / "work") and points.metadata["provenance"]["resumed_frames"] == len(kept)
    assert f"{len(kept)} frames resumed" in widget._status.value
    assert {name: (tmp_path / "work" / name).stat().st_mtime_ns for name in kept} == kept  # the finished frames were not predicted again
    np.testing.assert_array_equal(points.data, expected)
    assert_frame_equal(points.features, features)

    # on a dask.distributed scheduler given by its tcp address (a worker thread of this process: it starts in a
    # second, where worker processes would import torch for many): the same table
    from dask.distributed import LocalCluster

    viewer.layers.clear()
    widget.work_dir.value = tmp_path / "on-cluster"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://", dashboard_address=None) as cluster:
        widget.scheduler.value = cluster.scheduler_address
        assert widget._run.enabled, widget._status.value
        run_to_end(qtbot, widget)
    points = viewer.layers["run.tif particles"]
    assert points.metadata["scheduler"] == cluster.scheduler_address
    assert points.metadata["provenance"]["scheduler"] == f"dask.distributed at {cluster.scheduler_address}"
    assert f"dask.distributed at {cluster.scheduler_address}" in widget._status.value
    np.testing.assert_array_equal(points.data, expected)
    assert_frame_equal(points.features, features)


def test_size_index_plot_shows_the_particles_the_other_materials_and_the_band(qtbot):
    from napari_lbs._widgets._plots import SizeIndexPlot

    plot = SizeIndexPlot()
    assert "refine" in plot.axes.texts[0].get_text()  # nothing refined yet: says how to get the plot
    particles = {"diameter_um": [24.0, 25.5, 26.0], "index_contrast": [0.25, 0.26, 0.27], "index_err": [0.02, 0.9, np.nan]}
    others = {"diameter_um": [13.0], "index_contrast": [0.42], "index_err": [0.04]}
    plot.show(particles, others=others, material={"index_contrast": 0.26, "tolerance": 0.08})
    assert len(plot.axes.containers) == 2 and [t.get_text() for t in plot.axes.get_legend().get_texts()] == ["3 particles", "1 of another material"]
    (band,) = plot.axes.patches
    assert np.allclose(band.get_path().get_extents(band.get_transform()).transformed(plot.axes.transData.inverted()).intervaly, [0.18, 0.34])
    assert 0.0 < plot.axes.get_ylim()[0] < 0.18 and 0.42 < plot.axes.get_ylim()[1] < 0.6  # the values set the scale, not the widest error bar (±0.9)
    plot.show(particles)  # no material declared: no band
    assert not plot.axes.patches and len(plot.axes.containers) == 1
