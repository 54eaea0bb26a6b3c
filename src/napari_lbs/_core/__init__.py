"""napari-lbs scripting API, importable without Qt or napari.

The names below are the user-facing functions and result types, each documented with an
example in docs/api.md. Every other module and name under ``napari_lbs._core`` is private:
code inside the package imports those from their wing (docs/README.md).

Long-running functions take keyword-only ``progress(done, total)`` and ``should_stop()``
callbacks (see `napari_lbs._core.foundation._progress`).

Every name is imported on first use (PEP 562): ``import napari_lbs._core`` loads no numpy,
scipy or torch, so the console script starts fast and only pays for the modules a command
uses (torch only for the network, training and prediction).
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "foundation": ("InputError", "ConfigError", "Stopped", "ExperimentConfig", "load_config", "write_config", "read_hologram", "read_stack", "write_stack", "read_particles", "write_particles", "load_sample_hologram"),
        "physics": ("backpropagate", "propagate", "ParticleField", "random_particle_field", "simulate_hologram", "Distractors", "EFFECTS", "parse_effects", "effects_from_report"),
        "calibration": ("CalibrationSettings", "CalibrationResult", "HoloParams", "calibrate_hologram"),
        "learning": ("DatasetLayout", "InputProcessing", "generate_dataset", "open_dataset", "SyntheticDataset", "TrainingSettings", "TrainingResult", "train_model", "load_model", "LoadedModel", "predict_particles", "PredictionSettings", "PredictionResult", "match_particles", "score_particles"),
        "refine": ("RefineSettings", "refine_particles", "same_material", "particle_hologram", "residual_hologram", "residual_particles"),
        "gap": ("SceneDiagnosisSettings", "SceneDiagnosis", "diagnose_scene", "write_report", "find_particles"),
        "recordings": ("simulate_sequence", "SimulatedSequence", "open_frames", "HologramFrames", "sequence_background", "predict_sequence", "SequenceResult", "link_tracks"),
        "pipeline": ("refined_prediction",),
    },
)
