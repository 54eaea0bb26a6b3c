"""napari-lbs scripting API, importable without Qt or napari.

The names below are the user-facing functions and result types, each documented with an
example in docs/api.md. Every other module and name under ``napari_lbs._core`` is private:
code inside the package imports those from their own module.

Long-running functions take keyword-only ``progress(done, total)`` and ``should_stop()``
callbacks (see `napari_lbs._core._progress`).

Every name is imported on first use (PEP 562): ``import napari_lbs._core`` loads no numpy,
scipy or torch, so the console script starts fast and only pays for the modules a command
uses (torch only for the network, training and prediction).
"""

import importlib

_NAMES = {
    "_errors": ("InputError", "ConfigError"),
    "_progress": ("Stopped",),
    "_config": ("ExperimentConfig", "load_config", "write_config"),
    "_io": ("read_hologram", "read_stack", "write_stack", "read_particles", "write_particles"),
    "_samples": ("load_sample_hologram",),
    "_optics": ("backpropagate", "propagate"),
    "_synthesis": ("ParticleField", "random_particle_field", "simulate_hologram", "Distractors"),
    "_calibration": ("CalibrationSettings", "CalibrationResult", "HoloParams", "calibrate_hologram"),
    "_dataset": ("DatasetLayout", "InputProcessing", "generate_dataset", "open_dataset", "SyntheticDataset"),
    "_training": ("TrainingSettings", "TrainingResult", "train_model"),
    "_network": ("load_model", "LoadedModel"),
    "_prediction": ("predict_particles", "PredictionResult"),
    "_refine": ("RefineSettings", "refine_particles"),
    "_material": ("same_material",),
    "_scene": ("particle_hologram", "residual_hologram", "residual_particles"),
    "_metrics": ("match_particles", "score_particles"),
    "_gap": ("DiagnosisSettings", "Diagnosis", "diagnose_hologram", "write_report"),
    "_effects": ("EFFECTS", "parse_effects", "effects_from_report"),
    "_flow": ("simulate_sequence", "SimulatedSequence"),
    "_frames": ("open_frames", "HologramFrames"),
    "_background": ("sequence_background",),
    "_sequence": ("predict_sequence", "SequenceResult"),
    "_tracking": ("link_tracks",),
}
_MODULE_OF = {name: module for module, names in _NAMES.items() for name in names}


def __getattr__(name: str):
    if name in _MODULE_OF:
        value = getattr(importlib.import_module(f"napari_lbs._core.{_MODULE_OF[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_MODULE_OF))


__all__ = list(_MODULE_OF)
