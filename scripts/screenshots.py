"""Screenshots of the LBS workflow dock for docs/, from one successful run on the real sample hologram.

Run under a display: ``xvfb-run -a python scripts/screenshots.py [--out DIR] [--quick]``. In a
1280×800 window it opens the real hologram, docks "LBS workflow" and clicks through the six
tabs as a user would (back-propagation, calibration on a reference ROI, synthetic data,
training, prediction refined with the sample's material, gap diagnosis), each step's output
feeding the next. It saves each tab after its run, the window with the particles in 2-D on their plane and in 3-D, into
docs/figures/. About 20 minutes on 2 idle CPU cores, 10 of them training, which takes as long
as its 5 epochs need (``--quick``: a token run of a few minutes that checks the script, not
the figures). Work files go to ``--out`` (default a temporary folder).
``--roi-preview`` makes only roi_preview.png (the reference ROI with its I_e before any run, seconds);
``--lab-user`` only the figures of what a new user meets (`lab_user`, seconds).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import napari
import numpy as np
from qtpy.QtCore import QSettings
from qtpy.QtWidgets import QApplication

from napari_lbs._layers import show_every_depth

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


STEPS = ("1 Back-propagation", "2 Calibration", "3 Synthetic data", "4 Training", "5 Prediction", "6 Gap diagnosis", "7 Batch")


def grab_dialog_then(figure: Path, answer) -> None:
    """In 0.8 s, save the window with the dialog napari-lbs opened, then close the dialog with ``answer(dialog)``."""
    from qtpy.QtCore import QTimer

    def grab():
        dialog = QApplication.activeModalWidget()
        settle(0.3)
        dialog.grab().save(str(figure))
        answer(dialog)

    QTimer.singleShot(800, grab)


def lab_user(viewer, work: Path, figures: Path) -> None:
    """Figures of what a new user meets, without any long run (seconds).

    Each step widget alone in a 300-px dock; a camera TIFF opened with napari's own reader,
    the pixel size asked once, and its particles (the truth CSV) on it in µm; a model trained
    for 2.2-µm pixels about to run on a 3.45-µm camera's hologram: the setup warning.
    """
    import tifffile
    from qtpy.QtCore import Qt
    from qtpy.QtGui import QPainter, QPixmap

    from napari_lbs._core import (
        DatasetLayout,
        ExperimentConfig,
        TrainingSettings,
        generate_dataset,
        random_particle_field,
        simulate_hologram,
        train_model,
        write_particles,
    )

    window = viewer.window._qt_window
    docks = []
    for name in STEPS:
        dock, _ = viewer.window.add_plugin_dock_widget("napari-lbs", name)
        window.resizeDocks([dock], [300], Qt.Orientation.Horizontal)
        settle(0.5)
        docks.append(dock.grab())
        viewer.window.remove_dock_widget(dock)
    sheet = QPixmap(sum(d.width() for d in docks) + 8 * (len(docks) - 1), max(d.height() for d in docks))
    sheet.fill(Qt.GlobalColor.black)
    painter = QPainter(sheet)
    x = 0
    for pixmap in docks:
        painter.drawPixmap(x, 0, pixmap)
        x += pixmap.width() + 8
    painter.end()
    sheet.save(str(figures / "widgets_alone.png"))

    config = ExperimentConfig.from_dict({"volume": {"z_min_um": 1800.0, "z_max_um": 2200.0, "z_step_um": 100.0}, "particles": {"per_tile": 3, "layer_step_um": 200.0}, "tile": {"size": 64}})
    field = random_particle_field((384, 384), count=14, diameter_min_um=20, diameter_max_um=30, layers_um=config.layer_depths_um(), pixel_um=2.2, seed=4)
    tifffile.imwrite(work / "camera.tif", simulate_hologram(field, wavelength_um=0.66))
    write_particles(work / "camera-particles.csv", field.table(), force=True)  # --out may hold an earlier run
    image = viewer.open(work / "camera.tif", plugin="napari")[0]
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "1 Back-propagation")
    step.hologram.value = image
    step.config.line_edit.value = ""
    grab_dialog_then(figures / "pixel_size_dialog.png", lambda dialog: dialog.accept())
    step._run.clicked.emit()  # napari's reader gave pixels: the step asks the pixel size (2.2 µm offered) and remembers it for the file
    while step._worker is not None:
        settle(0.2)
    viewer.layers.remove(f"{image.name} z-stack")
    particles = viewer.open(work / "camera-particles.csv", plugin="napari-lbs")[0]
    show_every_depth(viewer, particles)  # every particle, whatever its depth, over the 2-D hologram
    particles.border_color, particles.border_width = "cyan", 0.12
    viewer.reset_view()
    settle(1.0)
    window.grab().save(str(figures / "user_file_aligned.png"))

    data = generate_dataset(work / "data", config, groups=2, layout=DatasetLayout(kind="stack", context_planes=2), seed=5)
    model = train_model(data, work / "model.pt", settings=TrainingSettings(epochs=1, batch_size=4, device="cpu", validation_groups=1, patch_size=32, context=(-2, -1, 0, 1, 2))).model_path
    camera = viewer.add_image(np.asarray(image.data), name="3.45-µm camera", scale=(3.45, 3.45), units="µm")
    _, step = viewer.window.add_plugin_dock_widget("napari-lbs", "5 Prediction")
    step.hologram.value = camera
    step.model.value = model
    step.config.line_edit.value = ""
    grab_dialog_then(figures / "setup_check.png", lambda dialog: dialog.reject())
    step._run.clicked.emit()
    settle(0.5)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="work folder (calibration, data set, model, report)")
    parser.add_argument("--quick", action="store_true", help="a token run that checks the script")
    parser.add_argument("--figures", type=Path, default=FIGURES, help="where the PNGs go (default docs/figures)")
    parser.add_argument("--roi-preview", action="store_true", help="make only roi_preview.png")
    parser.add_argument("--lab-user", action="store_true", help="make only the new-user figures (widgets alone, a user's file, the setup check; seconds)")
    args = parser.parse_args()
    figures = args.figures
    work = args.out or Path(tempfile.mkdtemp(prefix="lbs-screenshots-"))
    work.mkdir(parents=True, exist_ok=True)
    figures.mkdir(parents=True, exist_ok=True)
    # the steps' remembered settings of this run only: the figures show the defaults, whatever was typed before
    QSettings.setPath(QSettings.Format.NativeFormat, QSettings.Scope.UserScope, str(work / "settings"))

    viewer = napari.Viewer()
    window = viewer.window._qt_window
    window.resize(1280, 800)
    if args.lab_user:
        lab_user(viewer, work, figures)
        viewer.close()
        return
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
    # no time budget in the full run: its figures show all 5 epochs however busy the machine is
    step.epochs.value, step.minutes.value, step.device.value = (1, 0.3, "cpu") if args.quick else (5, 0.0, "auto")
    run_step(dock, step)

    step = dock.prediction
    step.hologram.value = hologram
    step.config.line_edit.value = ""
    step.reference.line_edit.value = ""
    # refined, with the sample's material (polystyrene in water), as the demo runs it: the figure shows the size-index plot
    step.refine.value = True
    step.material.value = "0.26"
    run_step(dock, step)
    points = viewer.layers["LBS real hologram particles"]

    step = dock.diagnosis
    step.hologram.value = hologram
    step.config.line_edit.value = ""
    step.output.value = work / "diagnosis"
    run_step(dock, step)

    for index, name in enumerate(TAB_FIGURES):
        dock.tabs.setCurrentIndex(index)
        settle(0.3)
        dock.grab().save(str(figures / f"{name}.png"))

    # 2-D: the plane holding the most particles, the ROI and I_e/I_s beside it
    viewer.layers["gap: unexplained share of the structure"].visible = False
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
