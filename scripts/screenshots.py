"""Screenshots of the napari-lbs widgets for docs/ (run under a display: xvfb-run -a python scripts/screenshots.py).

Opens the real sample hologram, back-propagates it with the Back-propagation widget, adds a
reference ROI, docks every widget and saves the window and each widget into docs/figures/.
"""

from __future__ import annotations

import time
from pathlib import Path

import napari
from qtpy.QtWidgets import QApplication

FIGURES = Path(__file__).resolve().parents[1] / "docs" / "figures"
WIDGETS = ["1 Back-propagation", "2 Calibration", "3 Synthetic data", "4 Training", "5 Prediction", "6 Gap diagnosis"]


def settle(seconds: float = 0.5) -> None:
    end = time.time() + seconds
    while time.time() < end:
        QApplication.processEvents()
        time.sleep(0.02)


def main() -> None:
    FIGURES.mkdir(parents=True, exist_ok=True)
    viewer = napari.Viewer()
    viewer.window.resize(1500, 950)
    viewer.open_sample("napari-lbs", "real_hologram")
    widgets = {name: viewer.window.add_plugin_dock_widget("napari-lbs", name)[1] for name in WIDGETS}
    backprop = widgets["1 Back-propagation"]
    backprop.hologram.value = viewer.layers["LBS real hologram"]
    backprop._run.clicked.emit()
    while backprop._worker is None and not backprop._run.enabled:
        settle(0.1)
    while backprop._worker is not None:
        settle(0.2)
    calibration = widgets["2 Calibration"]
    calibration.hologram.value = viewer.layers["LBS real hologram"]
    calibration.add_roi.clicked.emit()
    viewer.layers.selection.active = viewer.layers["LBS real hologram z-stack"]
    viewer.dims.set_current_step(0, 20)
    settle(1.0)
    for name, widget in widgets.items():
        widget.native.grab().save(str(FIGURES / f"widget_{name.split()[0]}_{'_'.join(name.lower().split()[1:])}.png"))
    viewer.window._qt_window.grab().save(str(FIGURES / "napari_window.png"))
    viewer.close()


if __name__ == "__main__":
    main()
