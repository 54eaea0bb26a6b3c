"""The napari side as a user meets it (needs a display: xvfb-run): manifest, sample data, and the
"LBS workflow" dock driven through the whole workflow on the synthetic sample with tiny settings."""

import json
import time

import numpy as np
import pytest

from napari_lbs._core import ExperimentConfig, read_particles
from napari_lbs._core._config import config_to_toml

TIMEOUT_MS = 180_000
TILE = 64


@pytest.fixture(autouse=True)
def isolated_settings(tmp_path_factory):
    from qtpy.QtCore import QSettings

    QSettings.setPath(QSettings.Format.NativeFormat, QSettings.Scope.UserScope, str(tmp_path_factory.mktemp("qsettings")))


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


def test_workflow_dock_drives_the_whole_workflow_on_the_synthetic_sample(make_napari_viewer, qtbot, tmp_path, notifications):
    viewer = make_napari_viewer(show=True)
    viewer.window._qt_window.resize(1280, 800)
    hologram, truth = viewer.open_sample("napari-lbs", "synthetic_hologram")
    dock = workflow_dock(viewer)
    qtbot.wait(200)
    # the dock fits a 1280×800 laptop screen and leaves the image most of the width
    window = viewer.window._qt_window
    assert window.width() <= 1280 and window.height() <= 800, (window.width(), window.height())
    assert dock.width() <= 400 and viewer.window._qt_viewer.canvas.native.width() >= 500

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

    # the z slider steps through planes and every layer is in µm (no napari units warning)
    qtbot.wait(300)
    assert viewer.dims.range[0].step >= 50.0
    plane = int(round(truth.data[0, 0]))
    viewer.dims.set_point(0, truth.translate[0] + plane * truth.scale[0])
    shown = set(np.asarray(truth._view_indices).tolist())
    assert 0 in shown and shown == set(np.flatnonzero(np.round(truth.data[:, 0]) == plane).tolist())
    assert all(str(unit) == "micrometer" for layer in viewer.layers for unit in layer.units), {layer.name: layer.units for layer in viewer.layers}
    assert not [m for m in notifications if "Inconsistent units" in m], notifications


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
    viewer.close()
    viewer = make_napari_viewer()
    dock = workflow_dock(viewer)
    assert dock.calibration.config.line_edit.value == "" and dock.calibration.generations.value == 7
    assert "not found" not in dock.calibration._status.value and "not found" not in dock.backprop._status.value
    assert dock.training.data.line_edit.value == "lbs-data"  # the stale folder fell back to the default
    assert dock.generate.output.value == tmp_path / "to-make"
    dock.training.output.line_edit.value = ""
    assert not dock.training._run.enabled


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
