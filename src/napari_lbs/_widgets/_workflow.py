"""The "LBS workflow" dock: the seven steps as tabs, each step's output filled into the next step's input."""

from __future__ import annotations

from pathlib import Path

from qtpy.QtWidgets import QLabel, QTabWidget, QVBoxLayout, QWidget

from napari_lbs._widgets._backprop import BackpropWidget
from napari_lbs._widgets._batch import BatchWidget
from napari_lbs._widgets._calibration import CalibrationWidget
from napari_lbs._widgets._diagnosis import DiagnosisWidget
from napari_lbs._widgets._generate import GenerateWidget
from napari_lbs._widgets._prediction import PredictionWidget
from napari_lbs._widgets._training import TrainingWidget

__all__ = ["WorkflowWidget"]

_MAX_WIDTH_PX = 400  # leaves a 1280-px screen most of its width for the image
_TAB_PADDING_PX = 3


class WorkflowWidget(QWidget):
    """One dock for the whole workflow (fits a 1280×800 screen: every tab scrolls).

    The calibration JSON a run writes becomes Synthetic data's calibration, the data set
    Training's data, the model Prediction's and Batch's model; each stays editable.

    Attributes
    ----------
    backprop, calibration, generate, training, prediction, diagnosis, batch : StepWidget
        The steps, in tab order.
    tabs : QTabWidget
    """

    def __init__(self, napari_viewer) -> None:
        super().__init__()
        self.backprop = BackpropWidget(napari_viewer)
        self.calibration = CalibrationWidget(napari_viewer)
        self.generate = GenerateWidget(napari_viewer)
        self.training = TrainingWidget(napari_viewer)
        self.prediction = PredictionWidget(napari_viewer)
        self.diagnosis = DiagnosisWidget(napari_viewer)
        self.batch = BatchWidget(napari_viewer)
        self.tabs = QTabWidget()
        self.tabs.setUsesScrollButtons(True)  # only where the dock is narrower than the default one
        # narrow tabs: all seven side by side in the dock's width, no scroll arrows
        self.tabs.tabBar().setStyleSheet(f"QTabBar::tab {{ padding-left: {_TAB_PADDING_PX}px; padding-right: {_TAB_PADDING_PX}px; }}")
        for label, step in (("1 Stack", self.backprop), ("2 Calib", self.calibration), ("3 Data", self.generate), ("4 Train", self.training), ("5 Predict", self.prediction), ("6 Gap", self.diagnosis), ("7 Batch", self.batch)):
            index = self.tabs.addTab(step.root_native_widget, label)
            self.tabs.setTabToolTip(index, type(step).__doc__.splitlines()[0])
        guide = QLabel("Open a hologram (File → Open Sample → LBS holography), then go through the tabs; each step's output fills the next step's input.")
        guide.setWordWrap(True)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.addWidget(guide)
        layout.addWidget(self.tabs)
        self.setMaximumWidth(_MAX_WIDTH_PX)
        self.calibration.produced.connect(lambda path: self._feed(self.generate.calibration, path))
        self.generate.produced.connect(lambda path: self._feed(self.training.data, path))
        self.training.produced.connect(lambda path: self._feed(self.prediction.model, path))
        self.training.produced.connect(lambda path: self._feed(self.batch.model, path))

    @property
    def steps(self) -> tuple:
        return (self.backprop, self.calibration, self.generate, self.training, self.prediction, self.diagnosis, self.batch)

    @staticmethod
    def _feed(field, path: Path) -> None:
        field.line_edit.value = str(path)
