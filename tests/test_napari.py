"""The napari side as a user meets it (needs a display: xvfb-run): manifest, sample data, and the
"LBS workflow" dock driven through the whole workflow on the synthetic sample with tiny settings."""

import json
import time

import numpy as np
import pytest

from napari_lbs._core import ExperimentConfig, read_particles
from napari_lbs._core.foundation._config import config_to_toml

TIMEOUT_MS = 180_000
TILE = 64


@pytest.fixture(autouse=True)
def isolated_settings(tmp_path_factory):
    from qtpy.QtCore import QSettings

    QSettings.setPath(QSettings.Format.NativeFormat, QSettings.Scope.UserScope, str(tmp_path_factory.mktemp("qsettings")))


@pytest.fixture(autouse=True)
def offered_pixel_size(monkeypatch):
    """An image added in code is in pixels: a step with an empty config asks its pixel size, answered here with the one offered."""
    from qtpy.QtWidgets import QInputDialog

    monkeypatch.setattr(QInputDialog, "getDouble", lambda parent, title, label, value, *args, **kwargs: (value, True))


@pytest.fixture
def notifications():
    """Every napari notification message shown during the test."""
    from napari.utils.notifications import notification_manager

    messages = []

    def record(notification):
        messages.append(str(notification.message))

    notification_manager.notification_ready.connect(record)
    yield messages
    notification_manager.notification_ready.disconnect(record)


def tiny_config_file(path):
    """17 planes 100 µm apart (3 prediction chunks), 64-px tiles, 3 particles a tile."""
    config = ExperimentConfig.from_dict({
        "volume": {"z_min_um": 1800.0, "z_max_um": 3400.0, "z_step_um": 100.0},
        "particles": {"per_tile": 3, "layer_step_um": 400.0},
        "tile": {"size": TILE},
    })
    path.write_text(config_to_toml(config))
    return path


def workflow_dock(viewer):
    _, widget = viewer.window.add_plugin_dock_widget("napari-lbs", "LBS workflow")
    return widget


def run_to_end(qtbot, step):
    assert step._run.enabled, step._status.value
    step._run.clicked.emit()
    qtbot.waitUntil(lambda: step._worker is None, timeout=TIMEOUT_MS)
    assert step._progress_bar is None and not step._stop.enabled
    assert not step._status.value.startswith("error") and "running" not in step._status.value, step._status.value
    assert "took" in step._timing.value, step._timing.value


def test_manifest_validates():
    from importlib.resources import files

    from npe2 import PluginManifest

    manifest = PluginManifest.from_file(files("napari_lbs") / "napari.yaml")
    manifest.validate_imports()
    assert manifest.name == "napari-lbs"


def test_real_sample_hologram_opens_with_micrometre_scale(make_napari_viewer):
    viewer = make_napari_viewer()
    layers = viewer.open_sample("napari-lbs", "real_hologram")
    layer = layers[0]
    assert layer.data.shape == (1024, 1024) and layer.data.dtype == np.float32
    assert tuple(layer.scale) == (2.2, 2.2) and str(layer.units[0]) == "micrometer"
    assert "MIT" in layer.metadata["provenance"]["source"]


def integer_ticks(axes) -> bool:
    return all(float(tick).is_integer() for tick in axes.get_xticks())


def test_workflow_dock_drives_the_whole_workflow_on_the_synthetic_sample(make_napari_viewer, qtbot, tmp_path, notifications, recwarn, monkeypatch):
    from scene_reports import StandIn

    import napari_lbs._core.gap as gap

    viewer = make_napari_viewer(show=True)
    viewer.window._qt_window.resize(1280, 800)
    hologram, truth = viewer.open_sample("napari-lbs", "synthetic_hologram")
    dock = workflow_dock(viewer)
    qtbot.wait(200)
    # the dock fits a 1280×800 laptop screen and leaves the image most of the width
    window = viewer.window._qt_window
    assert window.width() <= 1280 and window.height() <= 800, (window.width(), window.height())
    assert dock.width() <= 400 and viewer.window._qt_viewer.canvas.native.width() >= 500
    assert all(field.tooltip for step in dock.steps for field in step._fields)

    # the particle table writer and reader round-trip through napari's own save/open
    truth_csv = tmp_path / "truth.csv"
    viewer.layers.selection.active = truth
    assert viewer.layers.save(str(truth_csv), selected=True, plugin="napari-lbs") == [str(truth_csv)]
    table = read_particles(truth_csv)
    assert list(table)[:4] == ["x_um", "y_um", "z_um", "diameter_um"] and len(table["x_um"]) == 48
    reread = viewer.open(str(truth_csv), plugin="napari-lbs")[0]
    np.testing.assert_allclose(reread.data, truth.data, atol=1e-5)
    np.testing.assert_allclose(reread.features["diameter_um"], truth.features["diameter_um"], rtol=1e-6)
    viewer.layers.remove(reread)

    config = tiny_config_file(tmp_path / "tiny.toml")
    # 1: back-propagation
    dock.backprop.hologram.value = hologram
    dock.backprop.config.value = config
    run_to_end(qtbot, dock.backprop)
    stack = viewer.layers["synthetic hologram z-stack"]
    assert stack.data.shape == (17, 512, 512) and tuple(stack.scale) == pytest.approx((100.0, 2.2, 2.2))

    # 2: calibration on the one ROI (a second click keeps one layer, a second rectangle is replaced)
    step = dock.calibration
    step.hologram.value = hologram
    step.config.value = config
    step.add_roi.clicked.emit()
    step.add_roi.clicked.emit()
    rois = [layer for layer in viewer.layers if layer.metadata.get("napari_lbs_roi")]
    assert len(rois) == 1 and tuple(rois[0].scale) == pytest.approx((2.2, 2.2))
    rois[0].add_rectangles(np.array([[100.3, 200.6], [150, 260]]))
    assert len(rois[0].data) == 1 and np.allclose(np.asarray(rois[0].data[0]).min(axis=0), [100, 201])
    step.generations.value, step.population.value = 2, 4
    step.output.line_edit.value = ""
    assert not step._run.enabled and "choose where to save" in step._status.value
    step.output.value = tmp_path / "cal.json"
    run_to_end(qtbot, step)
    assert json.loads((tmp_path / "cal.json").read_text())["roi"] == [201, 100, TILE]
    i_e, i_s = viewer.layers["I_e (experiment)"], viewer.layers["I_s (synthetic)"]
    assert tuple(i_e.translate) == pytest.approx((100 * 2.2, 201 * 2.2)) and tuple(i_e.scale) == pytest.approx((2.2, 2.2))
    assert i_s.translate[1] > i_e.translate[1] + TILE * 2.2
    assert "SSIM" in step._status.value and len(step._plot.axes.lines) == 1
    assert [r["generation"] for r in step._live_history] == [1, 2]  # the curve grew generation by generation
    assert step._plot.axes.get_legend() is not None and integer_ticks(step._plot.axes)

    # 3: synthetic data, fed the calibration just written
    step = dock.generate
    assert step.calibration.value == tmp_path / "cal.json"
    step.config.value = config
    step.groups.value = 4
    step.output.line_edit.value = ""
    assert not step._run.enabled and "choose where to save" in step._status.value
    step.output.value = tmp_path / "data"
    run_to_end(qtbot, step)
    assert json.loads((tmp_path / "data" / "dataset.json").read_text())["complete"]

    # 4: training, fed the data set; the activity-dock progress bar advances
    step = dock.training
    assert step.data.value == tmp_path / "data"
    step.output.value = tmp_path / "m.pt"
    step.epochs.value, step.device.value = 1, "cpu"
    step._run.clicked.emit()
    shown = []
    step._progress_bar.events.value.connect(lambda event: shown.append(event.value))
    qtbot.waitUntil(lambda: step._worker is None, timeout=TIMEOUT_MS)
    assert shown and max(shown) > 0 and step._bar.value > 0 and "took" in step._timing.value
    assert (tmp_path / "m.pt").is_file() and step._plot.batches and step._plot.epochs
    # its plot: on napari's dark theme, legended, whole batches, not squashed in the dock
    dock.tabs.setCurrentWidget(step.root_native_widget)
    qtbot.wait(100)
    plot = step._plot
    assert sum(plot.canvas.figure.get_facecolor()[:3]) < 0.9 and plot.canvas.height() >= 150
    assert plot.ji_axes.get_legend() is not None and integer_ticks(plot.loss_axes)

    # 5: prediction, fed the model, scored against the truth saved above
    step = dock.prediction
    assert step.model.value == tmp_path / "m.pt"
    step.hologram.value = hologram
    step.device.value = "cpu"
    step.reference.value = truth_csv
    run_to_end(qtbot, step)
    points = viewer.layers["synthetic hologram particles"]
    assert tuple(points.scale) == pytest.approx((100.0, 2.2, 2.2)) and points.translate[0] == pytest.approx(1800.0)
    assert "ER" in step._status.value and "JI" in step._status.value
    # a result stays until the step runs again
    viewer.add_image(np.zeros((8, 8), np.float32), name="extra", scale=(2.2, 2.2), units="µm")
    assert "JI" in step._status.value and "ready" not in step._status.value
    assert "SSIM" in dock.calibration._status.value and "groups" in dock.generate._status.value

    # 6: gap diagnosis (a stand-in engine: tests/test_diagnosis.py runs the real one), a map with a colour bar over the hologram
    monkeypatch.setattr(gap, "diagnose_scene", StandIn([("sensor_blur", True)]))
    step = dock.diagnosis
    step.hologram.value = hologram
    step.config.value = config
    step.tile.value = 128
    step.output.line_edit.value = ""
    assert not step._run.enabled and "choose where to save" in step._status.value
    step.output.value = tmp_path / "gap"
    run_to_end(qtbot, step)
    gap_map = viewer.layers["gap: unexplained share of the structure"]
    assert gap_map.colorbar.visible and gap_map.data.shape == (4, 4) and (tmp_path / "gap" / "report.json").is_file()

    # the z slider steps through planes and every layer is in µm (no napari units warning)
    qtbot.wait(300)
    assert viewer.dims.range[0].step >= 50.0
    plane = int(round(truth.data[0, 0]))
    viewer.dims.set_point(0, truth.translate[0] + plane * truth.scale[0])
    shown = set(np.asarray(truth._view_indices).tolist())
    assert 0 in shown and shown == set(np.flatnonzero(np.round(truth.data[:, 0]) == plane).tolist())
    assert all(str(unit) == "micrometer" for layer in viewer.layers for unit in layer.units), {layer.name: layer.units for layer in viewer.layers}
    assert not [m for m in notifications if "Inconsistent units" in m], notifications
    assert not [w for w in recwarn if "out_of_slice_display" in str(w.message)]


def test_the_roi_shows_its_tile_reference_image_before_any_run(make_napari_viewer, qtbot, tmp_path, monkeypatch):
    from napari_lbs._core import load_config
    from napari_lbs._core.calibration._calibrate import experimental_reference, reference_planes
    from napari_lbs._widgets import _calibration

    planes_made, references_made = [], []

    def counted_planes(*args, **kwargs):
        planes_made.append(1)
        return reference_planes(*args, **kwargs)

    def slow_reference(stack, **kwargs):  # slow enough to be overtaken by a newer move
        references_made.append(1)
        time.sleep(0.4)
        return experimental_reference(stack, **kwargs)

    monkeypatch.setattr(_calibration, "reference_planes", counted_planes)
    monkeypatch.setattr(_calibration, "experimental_reference", slow_reference)
    viewer = make_napari_viewer()
    hologram, _ = viewer.open_sample("napari-lbs", "synthetic_hologram")
    step = workflow_dock(viewer).calibration
    config = tiny_config_file(tmp_path / "tiny.toml")
    step.hologram.value = hologram
    step.config.value = config
    step.add_roi.clicked.emit()
    roi = viewer.layers["reference ROI"]

    def place(row, col):  # the user draws the rectangle anew; the tool keeps only the newest
        roi.add_rectangles(np.array([[row, col], [row + TILE, col + TILE]], float))

    def idle():
        return step._preview_running is None and not step._preview_timer.isActive()

    # dragged through three places in quick succession: one computation once it rests, on the last place
    for row, col in ((10, 20), (30, 40), (100, 201)):
        place(row, col)
    qtbot.waitUntil(lambda: "I_e (experiment)" in viewer.layers and idle(), timeout=60_000)
    i_e = viewer.layers["I_e (experiment)"]
    assert len(planes_made) == 1 and len(references_made) == 1
    assert tuple(i_e.translate) == pytest.approx((100 * 2.2, 201 * 2.2)) and tuple(i_e.scale) == pytest.approx((2.2, 2.2))
    assert all(str(unit) == "micrometer" for unit in i_e.units)
    planes = reference_planes(np.asarray(hologram.data), load_config(config))
    np.testing.assert_allclose(i_e.data, experimental_reference(planes[:, 100 : 100 + TILE, 201 : 201 + TILE]), atol=1e-6)
    # one image, under the ROI, and the ROI stays in hand
    assert viewer.layers.index(i_e) < viewer.layers.index(roi) and viewer.layers.selection.active is roi
    assert [layer.name for layer in viewer.layers].count("I_e (experiment)") == 1

    # moved while a preview is being computed: the stale one never shows, the newest does
    shown = []
    i_e.events.translate.connect(lambda event: shown.append(tuple(np.round(i_e.translate / 2.2))))
    place(200, 60)
    qtbot.waitUntil(lambda: step._preview_running is not None, timeout=5_000)
    place(300, 400)
    qtbot.waitUntil(lambda: len(references_made) == 3 and idle(), timeout=30_000)
    assert shown == [(300, 400)] and len(planes_made) == 1  # the planes are reused while hologram and config stay
    np.testing.assert_allclose(i_e.data, experimental_reference(planes[:, 300 : 300 + TILE, 400 : 400 + TILE]), atol=1e-6)


def test_particle_tables_are_saved_and_opened_without_choosing_a_plugin(make_napari_viewer, tmp_path, monkeypatch):
    import napari.settings
    from napari._app_model import get_app_model
    from napari._qt import qt_viewer
    from napari._qt.dialogs.qt_reader_dialog import QtReaderDialog, open_with_dialog_choices
    from napari.plugins import _npe2
    from qtpy.QtWidgets import QFileDialog

    from napari_lbs._core.foundation._io import PARTICLE_COLUMNS

    monkeypatch.setattr(napari.settings, "_SETTINGS", napari.settings.NapariSettings(config_path=tmp_path / "napari-settings.yaml"))
    viewer = make_napari_viewer()
    _, truth = viewer.open_sample("napari-lbs", "synthetic_hologram")
    path = tmp_path / "truth.csv"
    io_menu = next(action.menu() for action in viewer.window.file_menu.actions() if action.menu() and action.text() == "IO Utilities")
    assert {"Save particle table (LBS holography)", "Open particle table (LBS holography)"} <= {action.text() for action in io_menu.actions()}

    # File → IO Utilities → Save particle table: the active Points layer, as the particle table, no writer to pick
    monkeypatch.setattr(QFileDialog, "getSaveFileName", staticmethod(lambda *args, **kwargs: (str(tmp_path / "truth"), "")))
    viewer.layers.selection.active = truth
    get_app_model().commands.execute_command("napari-lbs.save_particle_table").result()
    table = read_particles(path)
    assert tuple(table)[:4] == PARTICLE_COLUMNS and len(table["x_um"]) == 48
    # napari's own Save dialog offers the particle table for a Points layer too
    assert "LBS holography particle table (*.csv)" in _npe2.file_extensions_string_for_layers([truth])[0].split(";;")

    # File → IO Utilities → Open particle table: no reader to pick
    monkeypatch.setattr(QFileDialog, "getOpenFileNames", staticmethod(lambda *args, **kwargs: ([str(path)], "")))
    opened = get_app_model().commands.execute_command("napari-lbs.open_particle_table").result()
    np.testing.assert_allclose(opened[0].data, truth.data, atol=1e-5)
    np.testing.assert_allclose(opened[0].features["diameter_um"], truth.features["diameter_um"], rtol=1e-6)

    # drag and drop / File → Open (napari's _qt_open): napari asks once, with LBS holography chosen ...
    asked = []
    monkeypatch.setattr(qt_viewer, "handle_gui_reading", lambda paths, *args, **kwargs: asked.append(paths))
    viewer.window._qt_viewer._qt_open([str(path)], stack=False)
    assert asked == [[str(path)]]
    readers = _npe2.get_readers(str(path))
    dialog = QtReaderDialog(pth=str(path), readers=readers)
    assert dialog._get_plugin_choice() == "LBS holography"
    # ... and after OK with "remember" ticked, particle tables open without asking
    open_with_dialog_choices("LBS holography", True, dialog._extension, readers, [str(path)], False, viewer.window._qt_viewer)
    viewer.window._qt_viewer._qt_open([str(path)], stack=False)
    assert len(asked) == 1 and viewer.layers[-1].metadata["source"] == str(path) and tuple(viewer.layers[-1].units) == tuple(truth.units)
    np.testing.assert_allclose(viewer.layers[-1].data, truth.data, atol=1e-5)
    # napari's own Points CSVs still open as before, handed on to napari's reader
    napari_csv = tmp_path / "napari-points.csv"
    viewer.layers.selection.active = truth
    viewer.layers.save(str(napari_csv), selected=True, plugin="napari.write_points")  # napari's writer by name (the plugin's is first): index,axis-0,...
    assert napari_csv.read_text().startswith("index,axis-0")
    viewer.window._qt_viewer._qt_open([str(napari_csv)], stack=False)
    assert len(asked) == 1 and viewer.layers[-1].name.startswith("napari-points")
    np.testing.assert_allclose(viewer.layers[-1].data, truth.data, atol=1e-5)


def test_prediction_stop_is_acknowledged_at_once(make_napari_viewer, qtbot, tmp_path):
    from napari_lbs._core import TrainingSettings, generate_dataset, load_config, train_model

    config = load_config(tiny_config_file(tmp_path / "tiny.toml"))
    generate_dataset(tmp_path / "data", config, groups=2, seed=0)
    train_model(tmp_path / "data", tmp_path / "m.pt", settings=TrainingSettings(epochs=1, device="cpu", validation_groups=1))
    viewer = make_napari_viewer()
    hologram, _ = viewer.open_sample("napari-lbs", "synthetic_hologram")
    dock = workflow_dock(viewer)
    step = dock.prediction
    step.hologram.value = hologram
    step.model.value = tmp_path / "m.pt"
    step.device.value = "cpu"
    step._run.clicked.emit()
    qtbot.wait(800)  # into the work: back-propagation done, the first plane chunk under way
    assert step._worker is not None
    clicked = time.perf_counter()
    step._stop.clicked.emit()
    acknowledged = time.perf_counter() - clicked
    assert acknowledged < 1.0 and "stopping" in step._status.value and not step._stop.enabled
    qtbot.waitUntil(lambda: step._worker is None, timeout=10_000)
    ended = time.perf_counter() - clicked
    assert ended < 3.0, f"prediction ended {ended:.1f} s after Stop"
    assert step._run.enabled and "stopped" in step._status.value


def test_settings_are_restored_as_typed(make_napari_viewer, tmp_path):
    viewer = make_napari_viewer()
    dock = workflow_dock(viewer)
    dock.calibration.config.line_edit.value = ""
    dock.calibration.generations.value = 7
    dock.training.data.value = tmp_path / "gone"  # a folder that will not exist at the next start
    dock.generate.output.value = tmp_path / "to-make"  # an output folder that does not exist yet
    dock.generate.effects.value = "particle_phase:index_contrast=0.26,transmission=1"  # a text field
    viewer.close()
    viewer = make_napari_viewer()
    dock = workflow_dock(viewer)
    assert dock.calibration.config.line_edit.value == "" and dock.calibration.generations.value == 7
    assert "not found" not in dock.calibration._status.value and "not found" not in dock.backprop._status.value
    assert dock.training.data.line_edit.value == "lbs-data"  # the stale folder fell back to the default
    assert dock.generate.output.value == tmp_path / "to-make"
    assert dock.generate.effects.value == "particle_phase:index_contrast=0.26,transmission=1"
    dock.training.output.line_edit.value = ""
    assert not dock.training._run.enabled
    dock.prediction.model.line_edit.value = ""
    assert not dock.prediction._run.enabled and "choose a model" in dock.prediction._status.value and "not found" not in dock.prediction._status.value


def test_an_rgb_hologram_is_reduced_with_a_notification(make_napari_viewer, qtbot, tmp_path, notifications):
    viewer = make_napari_viewer()
    rgb = np.zeros((64, 64, 3), np.uint8)
    rgb[..., 0] = np.random.default_rng(0).integers(0, 255, (64, 64))
    layer = viewer.add_image(rgb, name="colour", rgb=True, scale=(2.2, 2.2), units="µm")
    dock = workflow_dock(viewer)
    dock.backprop.hologram.value = layer
    dock.backprop.config.value = tiny_config_file(tmp_path / "tiny.toml")
    run_to_end(qtbot, dock.backprop)
    assert any("reduced to its red channel" in m for m in notifications), notifications
    assert viewer.layers["colour z-stack"].data.shape == (17, 64, 64)
