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
