"""The plugin as a lab user meets it, in a real 1280×800 napari window (pytest-qt under xvfb-run):
every step fits a narrow dock, a user's own files and the results share one space, a model
from another setup is caught before Run, progress tells the truth, Stop answers quickly."""

import numpy as np
import pytest

STEPS = ("1 Back-propagation", "2 Calibration", "3 Synthetic data", "4 Training", "5 Prediction", "6 Gap diagnosis", "7 Batch")
DOCK_PX = 300


@pytest.fixture(autouse=True)
def isolated_settings(tmp_path_factory):
    from qtpy.QtCore import QSettings

    QSettings.setPath(QSettings.Format.NativeFormat, QSettings.Scope.UserScope, str(tmp_path_factory.mktemp("qsettings")))


def laptop_viewer(make_napari_viewer):
    viewer = make_napari_viewer(show=True)
    viewer.window._qt_window.resize(1280, 800)
    return viewer


def in_view(widget, dock) -> bool:
    """Whether ``widget`` lies wholly inside ``dock`` (not cut off at its right or bottom edge)."""
    corner = widget.mapTo(dock, widget.rect().bottomRight())
    return widget.isVisible() and 0 <= corner.x() < dock.width() and 0 <= corner.y() < dock.height()


@pytest.mark.parametrize("name", STEPS)
def test_each_step_alone_fits_a_300_px_dock_with_run_stop_and_every_button_in_view(make_napari_viewer, qtbot, name):
    from magicgui.widgets import FileEdit
    from qtpy.QtCore import Qt

    viewer = laptop_viewer(make_napari_viewer)
    dock, step = viewer.window.add_plugin_dock_widget("napari-lbs", name)
    viewer.window._qt_window.resizeDocks([dock], [DOCK_PX], Qt.Orientation.Horizontal)
    qtbot.wait(200)
    assert step.native.minimumSizeHint().width() <= DOCK_PX
    assert dock.width() <= DOCK_PX + 10, dock.width()
    assert in_view(step._run.native, dock) and in_view(step._stop.native, dock)
    for field in step._fields:
        if isinstance(field, FileEdit):  # "Select file" beside its path, not beyond the dock's edge
            corner = field.choose_btn.native.mapTo(dock, field.choose_btn.native.rect().bottomRight())
            assert corner.x() < dock.width(), (field.name, corner.x(), dock.width())


def test_the_workflow_dock_keeps_stop_in_view_while_training_reports_a_long_eta(make_napari_viewer, qtbot):
    viewer = laptop_viewer(make_napari_viewer)
    dock, workflow = viewer.window.add_plugin_dock_widget("napari-lbs", "LBS workflow")
    step = workflow.training
    workflow.tabs.setCurrentWidget(step.root_native_widget)
    step._timing.value = "120/4000 batches, 1:05:23 elapsed, about 0:24:37 left (the 90-minute budget ends first)"
    step._status.value = "training: running; " + "a long message that must wrap rather than widen the dock " * 3
    qtbot.wait(200)
    window = viewer.window._qt_window
    assert window.width() <= 1280 and window.height() <= 800
    assert in_view(step._run.native, dock) and in_view(step._stop.native, dock)


TIMEOUT_MS = 180_000


def run_to_end(qtbot, step):
    assert step._run.enabled, step._status.value
    step._run.clicked.emit()
    qtbot.waitUntil(lambda: step._worker is None, timeout=TIMEOUT_MS)
    assert step._run.enabled and not step._stop.enabled


def write_config(path, config):
    from napari_lbs._core.foundation._config import config_to_toml

    path.write_text(config_to_toml(config))
    return path


def simulated_tiff(path, config, *, shape=(96, 96), count=6, seed=1):
    """A hologram TIFF as a camera writes it (no scale in the file) and its true particles."""
    import tifffile

    from napari_lbs._core import random_particle_field, simulate_hologram

    field = random_particle_field(shape, count=count, diameter_min_um=20, diameter_max_um=30, layers_um=config.layer_depths_um(), pixel_um=config.optics.pixel_um, seed=seed)
    tifffile.imwrite(path, simulate_hologram(field, wavelength_um=config.optics.wavelength_um))
    return field.table()


def oracle(monkeypatch, truth):
    """Prediction's detections replaced by the true particles, so what is measured is where the results land, not the network."""
    import dataclasses

    from napari_lbs._widgets import _prediction

    real = _prediction.predict_particles

    def predict(*args, **kwargs):
        result = real(*args, **kwargs)
        return dataclasses.replace(result, particles={**{k: np.asarray(v, float) for k, v in truth.items()}, "score": np.ones(len(truth["x_um"]))})

    monkeypatch.setattr(_prediction, "predict_particles", predict)


def test_a_hologram_opened_with_napari_s_reader_is_put_in_um_and_the_particles_sit_on_it(make_napari_viewer, qtbot, tmp_path, monkeypatch, detector, tiny_config):
    from qtpy.QtWidgets import QInputDialog

    truth = simulated_tiff(tmp_path / "holo.tif", tiny_config)
    oracle(monkeypatch, truth)
    asked = []
    monkeypatch.setattr(QInputDialog, "getDouble", lambda *args, **kwargs: asked.append(args) or (2.2, True))
    viewer = laptop_viewer(make_napari_viewer)
    image = viewer.open(tmp_path / "holo.tif", plugin="napari")[0]
    assert str(image.units[-1]) == "pixel"  # napari's reader knows no pixel size
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "5 Prediction")
    step.hologram.value = image
    step.model.value = detector.path
    step.device.value = "cpu"
    run_to_end(qtbot, step)
    assert len(asked) == 1  # the pixel size was unknown (no config): asked once
    assert all(str(unit) == "micrometer" for unit in image.units) and tuple(image.scale) == pytest.approx((2.2, 2.2))
    points = viewer.layers["holo particles"]
    on_points = np.array([points.data_to_world(p)[1:] for p in points.data])
    pixels = np.column_stack([truth["y_um"], truth["x_um"]]) / tiny_config.optics.pixel_um  # (row, col) of each particle's centre in the file
    on_image = np.array([image.data_to_world(p) for p in pixels])
    assert np.median(np.linalg.norm(on_points - on_image, axis=1)) <= 5.0
    # the file's pixel size is remembered: opened again, it is in µm at once
    again = viewer.open(tmp_path / "holo.tif", plugin="napari")[0]
    qtbot.waitUntil(lambda: str(again.units[-1]) == "micrometer", timeout=5000)
    assert tuple(again.scale) == pytest.approx((2.2, 2.2)) and len(asked) == 1


def test_a_recording_opened_with_napari_s_reader_runs_in_time_beside_its_particles(make_napari_viewer, qtbot, tmp_path, detector, tiny_config):
    import tifffile
    from napari.utils.notifications import notification_manager

    from napari_lbs._core import simulate_sequence

    messages = []
    notification_manager.notification_ready.connect(lambda notification: messages.append(str(notification.message)))

    recording = simulate_sequence(tiny_config, frames=3, flow="uniform", size=96, count=4, speed_um=6.0, seed=2)
    tifffile.imwrite(tmp_path / "run.tif", recording.frames, photometric="minisblack")
    viewer = laptop_viewer(make_napari_viewer)
    viewer.open(tmp_path / "run.tif", plugin="napari")
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "7 Batch")
    step.frames.value = tmp_path / "run.tif"
    step.model.value = detector.path
    step.device.value = "cpu"
    step.search_range.value = 10.0
    run_to_end(qtbot, step)
    frames, points = viewer.layers["run"], viewer.layers["run.tif particles"]
    assert frames.ndim == 4 and viewer.dims.axis_labels[0] == "frame" and viewer.dims.nsteps[0] == 3
    assert frames.data_to_world((2, 0, 10, 20))[0] == pytest.approx(2.0)  # frame 2 is time step 2, not a depth
    np.testing.assert_allclose(frames.data_to_world((0, 0, 10, 20))[2:], (22.0, 44.0))  # in µm, as the particles
    for z_um in (1800.0, 2200.0):  # the frame shows under the particles of every plane
        assert round(frames.world_to_data((0, z_um, 0, 0))[1]) == 0
    assert points.data_to_world(points.data[0])[0] == points.data[0, 0]
    qtbot.wait(300)  # drawn
    assert viewer.layers.extent.units is not None and not any("units" in message for message in messages), messages


def test_a_model_for_another_setup_is_a_warning_to_confirm_before_run(make_napari_viewer, qtbot, tmp_path, monkeypatch, detector):
    from qtpy.QtWidgets import QMessageBox

    answers, warnings = [QMessageBox.StandardButton.Cancel, QMessageBox.StandardButton.Yes], []

    def warn(parent, title, text, *args):
        warnings.append(text)
        return answers.pop(0)

    monkeypatch.setattr(QMessageBox, "warning", warn)
    viewer = laptop_viewer(make_napari_viewer)
    # a 3.45-µm camera's hologram, a model trained for 2.2-µm pixels, the config field empty ("the model's")
    image = viewer.add_image(np.random.default_rng(0).normal(1.0, 0.05, (96, 96)).astype(np.float32), name="camera", scale=(3.45, 3.45), units="µm")
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "5 Prediction")
    step.hologram.value = image
    step.model.value = detector.path
    step.device.value = "cpu"
    run_to_end(qtbot, step)
    assert len(warnings) == 1 and "optics.pixel_um=2.2" in warnings[0] and "3.45" in warnings[0]
    assert "not run" in step._status.value and "camera particles" not in viewer.layers
    run_to_end(qtbot, step)  # confirmed: it runs, on the hologram's pixel size
    assert len(warnings) == 2 and viewer.layers["camera particles"].metadata["provenance"]["config"]["optics"]["pixel_um"] == 3.45


def test_the_cli_refuses_a_model_for_other_optics_unless_forced(tmp_path, detector, tiny_config):
    import subprocess
    import sys

    from napari_lbs._core import ExperimentConfig

    simulated_tiff(tmp_path / "holo.tif", tiny_config)
    other = tiny_config.to_dict()
    other["optics"]["pixel_um"] = 3.45
    config = write_config(tmp_path / "camera.toml", ExperimentConfig.from_dict(other))

    def predict(*extra):
        command = [sys.executable, "-m", "napari_lbs._cli", "predict", str(tmp_path / "holo.tif"), "--model", str(detector.path), "--config", str(config), "--device", "cpu", *extra]
        return subprocess.run(command, capture_output=True, text=True, check=False)

    refused = predict("--out", str(tmp_path / "a.csv"))
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1
    assert "optics.pixel_um=2.2" in refused.stderr and "3.45" in refused.stderr and not (tmp_path / "a.csv").exists()
    forced = predict("--out", str(tmp_path / "b.csv"), "--force")
    assert forced.returncode == 0, forced.stderr and (tmp_path / "b.csv").is_file()


def left_on(timing: str) -> int:
    """The seconds a timing line says are left."""
    import re

    minutes, seconds = re.search(r"(\d+):(\d\d) left", timing).groups()
    return 60 * int(minutes) + int(seconds)


def test_prediction_s_time_left_follows_the_measured_throughput(make_napari_viewer, qtbot, monkeypatch, detector):
    import time

    from napari_lbs._core import Stopped
    from napari_lbs._widgets import _prediction

    def predict(*args, progress, should_stop, **kwargs):  # quick back-propagated planes, then slow network planes
        for done in range(1, 21):
            time.sleep(0.01 if done <= 10 else 0.4)
            progress(done, 20)
        raise Stopped("stopped after 20 of 20 steps")

    monkeypatch.setattr(_prediction, "predict_particles", predict)
    viewer = laptop_viewer(make_napari_viewer)
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "5 Prediction")
    step.hologram.value = viewer.add_image(np.random.default_rng(0).normal(1.0, 0.05, (96, 96)).astype(np.float32), name="holo", scale=(2.2, 2.2), units="µm")
    step.model.value = detector.path
    step._run.clicked.emit()
    qtbot.waitUntil(lambda: step._counts == "13/20" or step._worker is None, timeout=30_000)
    assert step._counts == "13/20", (step._status.value, step._timing.value)
    assert left_on(step._timing.value) >= 2, step._timing.value  # 7 planes of 0.4 s are left, not a count's 0:01
    qtbot.waitUntil(lambda: step._worker is None, timeout=30_000)


def test_training_s_time_left_is_bounded_by_its_budget_and_its_end_named_right(make_napari_viewer, qtbot, tmp_path, monkeypatch, tiny_config):
    import time

    import napari_lbs._widgets._training as training
    from napari_lbs._core import TrainingResult, generate_dataset
    from napari_lbs._core.pipeline import StepResult

    generate_dataset(tmp_path / "data", tiny_config, groups=2, seed=0)

    def train(request, *, progress, should_stop, report):  # 0.1 s a batch: 10 s for all 100
        for done in range(1, 21):
            time.sleep(0.1)
            progress(done, 100)
        return StepResult("", TrainingResult(request.out_path, {"best": {"epoch": 1, "score": [0.5, 0.6]}, "stop_reason": "time budget reached"}, True))

    monkeypatch.setattr(training, "train", train)
    viewer = laptop_viewer(make_napari_viewer)
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "4 Training")
    step.data.value = tmp_path / "data"
    step.output.value = tmp_path / "m.pt"
    step.minutes.value = 0.05  # 3 s
    step._run.clicked.emit()
    qtbot.waitUntil(lambda: step._counts == "19/100" or step._worker is None, timeout=30_000)
    assert step._counts == "19/100", (step._status.value, step._timing.value)
    assert "time budget ends first" in step._timing.value and left_on(step._timing.value) <= 3, step._timing.value
    qtbot.waitUntil(lambda: step._worker is None, timeout=30_000)
    assert "time budget reached" in step._status.value and "(stopped)" not in step._status.value


def test_training_names_why_it_ended(tmp_path, tiny_config):
    from napari_lbs._core import TrainingSettings, generate_dataset, train_model

    data = generate_dataset(tmp_path / "data", tiny_config, groups=3, seed=0)
    settings = TrainingSettings(epochs=50, batch_size=2, device="cpu", validation_groups=1, minutes=0.002)
    assert train_model(data, tmp_path / "a.pt", settings=settings).log["stop_reason"] == "time budget reached"
    settings = TrainingSettings(epochs=50, batch_size=2, device="cpu", validation_groups=1)
    validated = []  # stopped once an epoch is validated: a model to keep
    stopped = train_model(data, tmp_path / "b.pt", settings=settings, report=lambda record: validated.append(record) if "validation" in record else None,
                          should_stop=lambda: bool(validated))
    assert stopped.log["stop_reason"] == "stopped by you"


REFINED = ("index_contrast", "absorption", "z_err_um", "diameter_err_um", "index_err", "fit_residual", "refined")


def test_a_refined_table_s_columns_become_features_to_colour_by_and_save(make_napari_viewer, qtbot, tmp_path, monkeypatch, detector, tiny_config):
    from napari.plugins import _npe2

    from napari_lbs._core import read_particles

    truth = simulated_tiff(tmp_path / "holo.tif", tiny_config)
    rng = np.random.default_rng(3)
    count = len(truth["x_um"])
    refined = {**truth, **{name: rng.uniform(0.1, 0.3, count) for name in REFINED[:-1]}, "refined": np.ones(count, bool)}
    oracle(monkeypatch, refined)
    viewer = laptop_viewer(make_napari_viewer)
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "5 Prediction")
    step.hologram.value = viewer.add_image(np.random.default_rng(0).normal(1.0, 0.05, (96, 96)).astype(np.float32), name="holo", scale=(2.2, 2.2), units="µm")
    step.model.value = detector.path
    step.device.value = "cpu"
    run_to_end(qtbot, step)
    points = viewer.layers["holo particles"]
    assert set(REFINED) <= set(points.features.columns)
    assert "index_contrast" in step.colour_by.choices and "z_err_um" in step.colour_by.choices
    step.colour_by.value = "index_contrast"
    assert len({tuple(colour) for colour in np.round(points.border_color, 3)}) > 1  # rims from low to high
    step.colour_by.value = "match"
    assert len({tuple(colour) for colour in np.round(points.border_color, 3)}) == 1
    # File → Save Selected Layers offers the particle table first, and it keeps the features
    _, writers = _npe2.file_extensions_string_for_layers([points])
    assert writers[0].command == "napari-lbs.write_points"
    points.save(str(tmp_path / "saved.csv"), plugin="napari-lbs")
    assert {"x_um", "index_contrast", "z_err_um"} <= set(read_particles(tmp_path / "saved.csv"))


def test_points_that_are_not_particles_still_save_as_napari_writes_them(make_napari_viewer, tmp_path):
    viewer = make_napari_viewer()
    viewer.window.add_plugin_dock_widget("napari-lbs", "5 Prediction")
    marks = viewer.add_points(np.array([[1.0, 2.0], [3.0, 4.0]]), name="marks")
    marks.save(str(tmp_path / "marks.csv"), plugin="napari-lbs")
    assert (tmp_path / "marks.csv").read_text().splitlines()[0].startswith("index,axis-0")


def test_batch_stops_within_two_seconds_without_running_the_other_frames(make_napari_viewer, qtbot, tmp_path, monkeypatch, detector, tiny_config):
    import threading
    import time

    import tifffile

    from napari_lbs._core import Stopped, simulate_sequence
    from napari_lbs._core.recordings import _sequence

    recording = simulate_sequence(tiny_config, frames=8, flow="uniform", size=64, count=3, speed_um=6.0, seed=2)
    tifffile.imwrite(tmp_path / "run.tif", recording.frames, photometric="minisblack")
    started = []
    lock = threading.Lock()

    def slow_frame(hologram, model, config, background, settings, should_stop=None):  # a large frame: 20 s of planes
        with lock:
            started.append(time.perf_counter())
        for _ in range(400):
            if should_stop is not None and should_stop():
                raise Stopped("stopped between planes")
            time.sleep(0.05)
        raise AssertionError("a frame ran to its end after Stop")

    monkeypatch.setattr(_sequence, "_frame_particles", slow_frame)
    viewer = laptop_viewer(make_napari_viewer)
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "7 Batch")
    step.frames.value = tmp_path / "run.tif"
    step.model.value = detector.path
    step.device.value = "cpu"
    step._run.clicked.emit()
    qtbot.waitUntil(lambda: bool(started), timeout=60_000)
    clicked = time.perf_counter()
    step._stop.clicked.emit()
    qtbot.waitUntil(lambda: step._worker is None, timeout=60_000)
    assert time.perf_counter() - clicked <= 2.0 and "stopped" in step._status.value
    assert len(started) < 8  # the frames not yet begun never ran


def test_the_gap_map_has_a_labelled_colour_bar(make_napari_viewer, qtbot):
    from types import SimpleNamespace

    viewer = laptop_viewer(make_napari_viewer)
    layer = viewer.add_image(np.ones((256, 256), np.float32), name="holo", scale=(2.2, 2.2), units="µm")
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "6 Gap diagnosis")
    from scene_reports import scene_report

    diagnosis = SimpleNamespace(report=scene_report("illumination", grid=4, tile_px=64), tile_map=np.linspace(0, 1, 16).reshape(4, 4))
    request = SimpleNamespace(out_dir="report", settings=SimpleNamespace(level_z=3.0, structure_level=0.07))
    step.show((SimpleNamespace(value=diagnosis, summary="verdict: illumination"), request, layer))
    gap_map = next(layer for layer in viewer.layers if layer.name.startswith("gap"))
    bar = step._colour_bar.axes
    assert gap_map.colorbar.visible and bar.get_visible()
    assert bar.get_xlabel() == gap_map.name and str(gap_map.units[0]) == "micrometer"
    assert next(tick.get_text() for tick in bar.get_xticklabels()) != ""  # the values are written under the bar


STEP_CLASSES = ("BackpropWidget", "CalibrationWidget", "GenerateWidget", "TrainingWidget", "PredictionWidget", "DiagnosisWidget", "BatchWidget")


def other_value(widget, existing):
    """A value for ``widget`` that differs from its default (``existing``: a path that exists)."""
    from magicgui.widgets import CheckBox, ComboBox, FileEdit, LineEdit

    if isinstance(widget, FileEdit):
        return str(existing)
    if isinstance(widget, CheckBox):
        return not widget.value
    if isinstance(widget, ComboBox):
        return next(choice for choice in widget.choices if choice != widget.value)
    if isinstance(widget, LineEdit):
        return "0.26"
    return widget.max if widget.value != widget.max else widget.min


@pytest.mark.parametrize("name", STEP_CLASSES)
def test_every_setting_comes_back_after_a_restart_as_one_consistent_whole(make_napari_viewer, tmp_path, name):
    from magicgui.widgets import FileEdit

    import napari_lbs._widgets as widgets

    viewer = make_napari_viewer()
    step = getattr(widgets, name)(viewer)
    assert step._persisted(), name
    typed = {}
    for field in step._persisted():
        value = other_value(field, tmp_path)
        if isinstance(field, FileEdit):
            field.line_edit.value = value
        else:
            field.value = value
        typed[field.name] = value
    again = getattr(widgets, name)(viewer)  # napari started again: a new widget reads what the last one saved
    restored = {field.name: field.line_edit.value if isinstance(field, FileEdit) else field.value for field in again._persisted()}
    assert restored == typed


def test_a_remembered_material_comes_back_with_refine_so_run_is_not_blocked(make_napari_viewer, tmp_path):
    from napari_lbs._widgets import PredictionWidget

    viewer = make_napari_viewer()
    step = PredictionWidget(viewer)
    step.refine.value = True
    step.material.value = "0.26"
    again = PredictionWidget(viewer)
    assert again.refine.value and again.material.value == "0.26"
    assert again._material_problem() is None and "material" not in again._status.value


def test_a_remembered_record_that_no_longer_fits_the_fields_is_not_used_at_all(make_napari_viewer):
    import json

    from qtpy.QtCore import QSettings

    from napari_lbs._widgets import CalibrationWidget

    QSettings("napari-lbs", "CalibrationWidget").setValue("fields", json.dumps({"seed": 5, "generations": "many", "mode": "seed"}))
    step = CalibrationWidget(make_napari_viewer())
    assert (step.seed.value, step.generations.value, step.mode.value) == (0, 100, "robust")


def test_a_particle_layer_saved_under_its_proposed_name_gets_csv_and_opens_again(make_napari_viewer, tmp_path):
    """File › Save Selected Layers proposes the layer's name ("… particles", no extension); accepted, napari can open what was written."""
    from napari_lbs._core import read_particles, write_particles

    viewer = make_napari_viewer()
    _, truth = viewer.open_sample("napari-lbs", "synthetic_hologram")
    viewer.layers.selection = {truth}
    written = viewer.layers.save(str(tmp_path / "cropped_hologram particles"), selected=True, plugin="napari-lbs")
    assert written == [str(tmp_path / "cropped_hologram particles.csv")]
    reopened = viewer.open(written[0], plugin="napari-lbs")[0]  # a .csv: napari's own reader is offered too
    np.testing.assert_allclose(reopened.data, truth.data, atol=1e-5)
    # a table written without the extension opens too, no reader to choose: its header says what it is
    write_particles(tmp_path / "old particles", read_particles(written[0]))
    assert len(viewer.open(str(tmp_path / "old particles"), plugin=None)[0].data) == len(truth.data)  # plugin=None: as File › Open


def test_a_refined_prediction_shows_one_bar_over_its_named_phases(make_napari_viewer, qtbot, monkeypatch, detector):
    """The network's planes, the fit's batches, the second look and its refit count from 0 each: the bar goes once from 0 to the end, each phase named, time left of the whole."""
    import time

    from napari_lbs._core import Stopped
    from napari_lbs._core.foundation import begin_phase
    from napari_lbs._widgets import _prediction

    def refined(*args, progress, should_stop, **kwargs):
        for name, steps, seconds in (("network", 10, 0.02), ("fit 7 particles", 5, 0.2), ("second look", 10, 0.02), ("refit 8 particles", 5, 0.02)):
            begin_phase(progress, name)
            for done in range(1, steps + 1):
                time.sleep(seconds)
                progress(done, steps)
        raise Stopped("stopped after the refit")

    monkeypatch.setattr(_prediction, "refined_prediction", refined)
    viewer = laptop_viewer(make_napari_viewer)
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "5 Prediction")
    step.hologram.value = viewer.add_image(np.random.default_rng(0).normal(1.0, 0.05, (96, 96)).astype(np.float32), name="holo", scale=(2.2, 2.2), units="µm")
    step.model.value = detector.path
    step.refine.value = True
    seen = []
    step._relay.progress.connect(lambda *_: seen.append((step._bar.value, step._bar.max, step._timing.value)))
    step._run.clicked.emit()
    qtbot.waitUntil(lambda: step._worker is None, timeout=30_000)
    values = [value / maximum for value, maximum, _ in seen]
    assert values == sorted(values) and values[-1] == 1.0 and max(values[:-1]) < 1.0  # once from 0 to the end
    timing = [text for _, _, text in seen]
    assert any(text.startswith("network 10/10") for text in timing) and any(text.startswith("fit 7 particles 1/5") for text in timing)
    assert any(text.startswith("second look") for text in timing) and any(text.startswith("refit 8 particles") for text in timing)
    at_fit = next(text for text in timing if text.startswith("fit 7 particles 2/5"))
    assert left_on(at_fit) >= 1, at_fit  # the fit's 3 batches of 0.2 s and the second look are left


def test_a_recording_s_table_reopens_with_its_frames_on_the_time_axis(make_napari_viewer, tmp_path, tiny_config):
    from napari_lbs._core import link_tracks, simulate_sequence, write_particles
    from napari_lbs._layers import PlaneGrid, frame_points

    truth = simulate_sequence(tiny_config, frames=5, flow="uniform", size=64, count=3, speed_um=6.0, seed=2).truth
    write_particles(tmp_path / "truth.csv", truth)  # a simulated recording's truth: a frame column
    viewer = make_napari_viewer()
    reopened = viewer.open(str(tmp_path / "truth.csv"), plugin="napari-lbs")[0]
    assert reopened.data.shape == (len(truth["x_um"]), 4)
    np.testing.assert_array_equal(reopened.data[:, 0], truth["frame"])  # each particle at its own time, not all at one
    # a Batch layer saved and opened again keeps its time axis
    tracks = link_tracks(truth, search_range_um=20.0)
    data, keywords = frame_points(tracks, PlaneGrid.of_planes(tiny_config.volume.planes_um(), pixel_um=2.2))
    layer = viewer.add_points(data, **keywords, name="run particles")
    layer.save(str(tmp_path / "run.csv"), plugin="napari-lbs")
    again = viewer.open(str(tmp_path / "run.csv"), plugin="napari-lbs")[0]
    assert again.data.shape == layer.data.shape and again.axis_labels[0] == "frame"
    np.testing.assert_array_equal(again.data[:, 0], layer.data[:, 0])


def test_the_gap_step_refuses_a_z_stack_and_a_tile_that_leaves_one_in_a_line(make_napari_viewer, qtbot):
    viewer = make_napari_viewer()
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "6 Gap diagnosis")
    holo = viewer.add_image(np.ones((512, 512), np.float32), name="holo", scale=(2.2, 2.2), units="µm")
    stack = viewer.add_image(np.ones((61, 512, 512), np.float32), name="holo z-stack", metadata={"z_um": list(range(61)), "source": "holo"})
    step.hologram.value = stack
    assert not step._run.enabled and "z-stack" in step._status.value and "'holo'" in step._status.value
    step.hologram.value = holo
    assert "z-stack" not in step._status.value
    step.tile.value = 300
    assert not step._run.enabled and "tile 300: a 512x512 (x by y) frame holds 1 tile(s)" in step._status.value
    assert "4 × 4 tiles" in step.tile.tooltip and "after a run" in step._plot.axes.texts[0].get_text()


def test_predicted_particles_are_all_shown_coloured_by_depth(make_napari_viewer):
    from types import SimpleNamespace

    from napari_lbs._widgets import PredictionWidget

    viewer = make_napari_viewer()
    step = PredictionWidget(viewer)
    holo = viewer.add_image(np.ones((256, 256), np.float32), name="holo", scale=(2.2, 2.2), units="µm")
    rng = np.random.default_rng(0)
    particles = {"x_um": rng.uniform(0, 560, 40), "y_um": rng.uniform(0, 560, 40), "z_um": rng.uniform(1800, 4800, 40), "diameter_um": rng.uniform(20, 40, 40)}
    provenance = {"planes_um": [1800.0, 4800.0, 61], "config": {"optics": {"pixel_um": 2.2}}}
    step.show((SimpleNamespace(particles=particles, provenance=provenance, seconds=1.0), None, holo.name, (0.0, 0.0)))
    points = viewer.layers["holo particles"]
    for z_um in (1800.0, 3300.0, 4800.0):  # whatever the plane shown
        viewer.dims.set_point(0, z_um)
        assert len(points._view_data) == 40
    assert step.colour_by.value == "z_um" and viewer.dims.axis_labels[0] == "z"  # the slider is labelled z, not -3
    colours = np.asarray(points.border_color)
    assert len(np.unique(colours.round(3), axis=0)) > 10  # a colour per depth


def test_a_hologram_smaller_than_the_model_s_tile_keeps_run_disabled(make_napari_viewer, detector):
    viewer = make_napari_viewer()
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "5 Prediction")
    tile = int(detector.meta["tile_size"])
    step.model.value = detector.path
    step.hologram.value = viewer.add_image(np.ones((tile - 8, 2 * tile), np.float32), name="small", scale=(2.2, 2.2), units="µm")
    assert not step._run.enabled and f"{tile}-pixel tile" in step._status.value
    step.hologram.value = viewer.add_image(np.ones((tile, tile), np.float32), name="enough", scale=(2.2, 2.2), units="µm")
    assert step._run.enabled, step._status.value


def test_the_seven_tabs_fit_the_workflow_dock_at_1280_by_800(make_napari_viewer, qtbot):
    viewer = laptop_viewer(make_napari_viewer)
    _, workflow = viewer.window.add_plugin_dock_widget("napari-lbs", "LBS workflow")
    qtbot.wait(200)
    bar = workflow.tabs.tabBar()
    assert bar.sizeHint().width() <= workflow.tabs.width(), (bar.sizeHint().width(), workflow.tabs.width())  # no scroll arrows


def test_the_time_left_does_not_jump_with_a_few_slow_steps():
    from napari_lbs._widgets._base import time_left

    marks = [(0.1 * done, done) for done in range(201)]  # 20 s of 0.1-s steps, out of 1000
    before = time_left(marks, 1000)
    marks += [(marks[-1][0] + 1.0 * k, 200 + k) for k in range(1, 6)]  # then five slow ones (a validation pass)
    after = time_left(marks, 1000)
    assert before == pytest.approx(80.0) and after < 1.5 * before, (before, after)


def test_synthetic_data_s_preview_lies_beside_the_hologram(make_napari_viewer, tmp_path, tiny_config):
    from napari_lbs._core import generate_dataset, open_dataset
    from napari_lbs._widgets import GenerateWidget

    generate_dataset(tmp_path / "data", tiny_config, groups=2, seed=0)
    viewer = make_napari_viewer()
    holo = viewer.add_image(np.ones((256, 256), np.float32), name="holo", scale=(2.2, 2.2), units="µm")
    step = GenerateWidget(viewer)
    step.show(open_dataset(tmp_path / "data"))
    step.show(open_dataset(tmp_path / "data"))  # run again: the preview is replaced, not doubled
    previews = [layer for layer in viewer.layers if layer.name.startswith("training")]
    assert len(previews) == 2
    for layer in previews:
        assert layer.extent.world[0][-1] > holo.extent.world[1][-1]  # right of the hologram, not over its top-left tile
