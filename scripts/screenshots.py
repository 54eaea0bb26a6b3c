"""Screenshots of the LBS workflow dock for docs/, from one successful run on the real sample hologram.

Run under a display: ``xvfb-run -a python scripts/screenshots.py [--out DIR] [--quick]``. In a
1280×800 window it opens the real hologram, docks "LBS workflow" and clicks through the six
tabs as a user would (back-propagation, calibration on a reference ROI, synthetic data,
training, prediction, gap diagnosis), each step's output feeding the next. It saves each tab
after its run, the window with the particles in 2-D on their plane and in 3-D, into
docs/figures/. About 12 minutes on 2 CPU cores (``--quick``: a token run of about 2 minutes
that checks the script, not the figures). Work files go to ``--out`` (default a temporary folder).
``--roi-preview`` makes only roi_preview.png (the reference ROI with its I_e before any run, seconds).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import napari
import numpy as np
from qtpy.QtWidgets import QApplication

FIGURES = Path(__file__).resolve().parents[1] / "docs" / "figures"
TAB_FIGURES = ("widget_1_back-propagation", "widget_2_calibration", "widget_3_synthetic_data", "widget_4_training", "widget_5_prediction", "widget_6_gap_diagnosis")


def settle(seconds: float = 0.5) -> None:
    """Let Qt draw for ``seconds``."""
    end = time.time() + seconds
    while time.time() < end:
        QApplication.processEvents()
        time.sleep(0.02)


def run_step(dock, step) -> None:
    """Show the step's tab, click Run, wait until it has finished; fail on an error."""
    dock.tabs.setCurrentWidget(step.root_native_widget)
    if not step._run.enabled:
        raise RuntimeError(f"{step.title}: Run disabled: {step._status.value}")
    step._run.clicked.emit()
    while step._worker is not None:
        settle(0.2)
    if step._status.value.startswith("error"):
        raise RuntimeError(f"{step.title}: {step._status.value}")
    print(f"{step.title}: {step._status.value} ({step._timing.value})", flush=True)
    settle(0.5)


def place_roi(viewer, dock, hologram, figures: Path) -> None:
    """Put the reference ROI on the hologram's middle tile and save the window once its I_e preview is shown."""
    step = dock.calibration
    dock.tabs.setCurrentWidget(step.root_native_widget)
    step.hologram.value = hologram
    step.config.line_edit.value = ""
    step.add_roi.clicked.emit()
    roi = viewer.layers["reference ROI"]
    roi.data = [np.array([[384.0, 384.0], [640.0, 640.0]])]
    settle(1.0)
    while "I_e (experiment)" not in viewer.layers or step._preview_running is not None or step._preview_timer.isActive():
        settle(0.2)
    viewer.scene.camera.center = tuple(np.asarray(hologram.scale) * 512)
    viewer.scene.camera.zoom = viewer.window._qt_viewer.canvas.native.height() / (1.6 * 512 * hologram.scale[0])
    settle(1.0)
    viewer.window._qt_window.grab().save(str(figures / "roi_preview.png"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="work folder (calibration, data set, model, report)")
    parser.add_argument("--quick", action="store_true", help="a token run that checks the script")
    parser.add_argument("--figures", type=Path, default=FIGURES, help="where the PNGs go (default docs/figures)")
    parser.add_argument("--roi-preview", action="store_true", help="make only roi_preview.png")
    args = parser.parse_args()
    figures = args.figures
    work = args.out or Path(tempfile.mkdtemp(prefix="lbs-screenshots-"))
    work.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)

    viewer = napari.Viewer()
    window = viewer.window._qt_window
    window.resize(1280, 800)
    hologram = viewer.open_sample("napari-lbs", "real_hologram")[0]
    _, dock = viewer.window.add_plugin_dock_widget("napari-lbs", "LBS workflow")
    settle(1.0)
    if args.roi_preview:
        place_roi(viewer, dock, hologram, figures)
        viewer.close()
        return

    step = dock.backprop
    step.hologram.value = hologram
    step.config.line_edit.value = ""
    run_step(dock, step)
    stack = viewer.layers["LBS real hologram z-stack"]

    place_roi(viewer, dock, hologram, figures)
    viewer.reset_view()
    step = dock.calibration
    step.generations.value, step.population.value = (3, 6) if args.quick else (40, 12)
    step.output.value = work / "calibration.json"
    run_step(dock, step)

    step = dock.generate
    step.config.line_edit.value = ""
    step.groups.value = 4 if args.quick else 64
    step.output.value = work / "data"
    run_step(dock, step)
    for name in ("training input (group 0)", "training label (group 0)"):
        viewer.layers[name].visible = False

    step = dock.training
    step.output.value = work / "model.pt"
    step.epochs.value, step.minutes.value, step.device.value = (1, 0.3, "cpu") if args.quick else (5, 6.0, "auto")
    run_step(dock, step)

    step = dock.prediction
    step.hologram.value = hologram
    step.config.line_edit.value = ""
    step.reference.line_edit.value = ""
    run_step(dock, step)
    points = viewer.layers["LBS real hologram particles"]

    step = dock.diagnosis
    step.hologram.value = hologram
    step.config.line_edit.value = ""
    step.sim_tiles.value, step.evaluations.value = (2, 8) if args.quick else (4, 16)
    step.output.value = work / "diagnosis"
    run_step(dock, step)

    for index, name in enumerate(TAB_FIGURES):
        dock.tabs.setCurrentIndex(index)
        settle(0.3)
        dock.grab().save(str(figures / f"{name}.png"))

    # 2-D: the plane holding the most particles, the ROI and I_e/I_s beside it
    viewer.layers["gap by region"].visible = False
    plane = int(np.bincount(np.round(points.data[:, 0]).astype(int)).argmax()) if len(points.data) else 0
    viewer.layers.selection.active = points
    viewer.dims.set_point(0, stack.translate[0] + plane * stack.scale[0])
    dock.tabs.setCurrentIndex(4)
    viewer.reset_view()
    settle(1.0)
    window.grab().save(str(figures / "napari_window.png"))
    # 3-D: the sensor (the hologram at z = 0) and every particle in its box 1.8-4.8 mm away
    for name in ("I_e (experiment)", "I_s (synthetic)", "reference ROI", stack.name):
        viewer.layers[name].visible = False
    points.bounding_box.visible = True
    viewer.axes.visible = viewer.canvas.overlays.scale_bar.visible = True
    viewer.dims.axis_labels = ("z", "y", "x")
    viewer.dims.ndisplay = 3
    viewer.reset_view()
    viewer.scene.camera.angles = (-60.0, 30.0, 110.0)
    viewer.scene.camera.zoom *= 0.6
    settle(1.0)
    window.grab().save(str(figures / "napari_3d.png"))
    viewer.close()
    print(f"figures in {figures}; work files in {work}")


if __name__ == "__main__":
    main()
