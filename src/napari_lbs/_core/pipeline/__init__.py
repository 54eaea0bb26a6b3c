"""The pipeline every front uses: one step per task, a frozen request in (its data positional, its options keyword-only), a `StepResult` out.

The top wing: stands on every other. Other wings import these names from ``napari_lbs._core.pipeline``, never from its
private modules; each name is imported on first use. The console script and the widgets only build requests and show
results; the steps read the inputs, run `_core`'s functions, write the outputs with their provenance and say in one
line what they did.

`_common`
    What every step shares: `StepResult`, the provenance outputs record, the readers of a request's inputs.
`_setup_steps`
    The steps that start from one hologram or none: simulate, backprop and calibrate.
`_data_steps`
    The steps that make and use a training set: generate and train.
`_predict`
    The steps that find particles: predict (a hologram or a recording, refined by a fit on request) and track.
`_binning`
    The pitch a particle's fit sees (a microscope's pixels binned) and the depths it scans, for refine and predict --refine.
`_refine_step`
    The step that fits without training: refine (the classical detector's guesses, fitted by Lorenz–Mie theory, then those their residual holds).
`_diagnose_step`
    The steps that measure: diagnose (the sim-to-real gap of a setup's holograms) and evaluate.
`_demo`
    The demo: every step in turn on the built-in real hologram, recorded in ``summary.json``.
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_common": ("StepResult", "provenance", "read_calibration"),
        "_setup_steps": ("BackpropRequest", "CalibrateRequest", "SimulateRequest", "backprop", "calibrate", "simulate"),
        "_data_steps": ("GenerateRequest", "TrainRequest", "generate", "report_distractors", "report_sizes", "requested_effects", "train", "training_processing"),
        "_predict": ("PredictRequest", "REFINE_PROPOSAL_FRACTION", "TrackRequest", "predict", "prediction_outputs", "refined_prediction", "track"),
        "_binning": ("fringe_binning",),
        "_refine_step": ("DETECTION_ROUNDS", "RefineRequest", "refine", "refine_hologram"),
        "_diagnose_step": ("DIAGNOSED_FRAMES", "DiagnoseRequest", "EvaluateRequest", "diagnose", "evaluate", "tiles_per_side"),
        "_demo": ("DEMO_SAMPLE_DISTRACTORS", "DemoRequest", "demo"),
    },
)
