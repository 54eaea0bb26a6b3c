"""napari dock widgets: thin fronts over `napari_lbs._core`, one per step, and the workflow dock.

`_base` holds what every step shares (Run/Stop, validation, progress, results, settings);
`_fields` the form's fields, their readers and checks; one module per step; `_workflow` puts
the seven steps in one dock.
"""

from napari_lbs._widgets._backprop import BackpropWidget
from napari_lbs._widgets._batch import BatchWidget
from napari_lbs._widgets._calibration import CalibrationWidget
from napari_lbs._widgets._diagnosis import DiagnosisWidget
from napari_lbs._widgets._generate import GenerateWidget
from napari_lbs._widgets._prediction import PredictionWidget
from napari_lbs._widgets._training import TrainingWidget
from napari_lbs._widgets._workflow import WorkflowWidget

__all__ = ["BackpropWidget", "CalibrationWidget", "GenerateWidget", "TrainingWidget", "PredictionWidget", "DiagnosisWidget", "BatchWidget", "WorkflowWidget"]
