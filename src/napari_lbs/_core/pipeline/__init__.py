"""The pipeline every front uses: one step per task, a frozen request in, a `StepResult` out.

The top wing: stands on every other. Other wings import these names from ``napari_lbs._core.pipeline``, never from its
private modules; each name is imported on first use.

`_pipeline`
    The pipeline: one step per task, a frozen request in, a `StepResult` out.
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_pipeline": ("BackpropRequest", "CalibrateRequest", "DEMO_SAMPLE_DISTRACTORS", "DemoRequest", "DiagnoseRequest", "EvaluateRequest", "GenerateRequest", "PredictRequest", "SimulateRequest", "TrackRequest", "TrainRequest", "backprop", "calibrate", "demo", "diagnose", "evaluate", "generate", "predict", "prediction_outputs", "refined_prediction", "requested_effects", "simulate", "track", "train"),
    },
)
