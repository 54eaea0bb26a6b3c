"""napari-lbs computation, importable without Qt or napari.

Long-running functions take keyword-only ``progress(done, total)`` and ``should_stop()``
callbacks (see `napari_lbs._core._progress`).

Every public name is listed here but imported on first use (PEP 562): ``import
napari_lbs._core`` loads no numpy, scipy or torch, so the console script starts fast and
only pays for the modules a command uses (torch only for the network, training and
prediction).
"""

import importlib

_NAMES = {
    "_calibration": (
        "PARAM_BOUNDS", "CalibrationResult", "CalibrationSettings", "HoloParams", "calibrate", "calibrate_hologram", "choose_reference_tile",
        "experimental_planes", "experimental_reference", "holo_processing", "reference_planes", "score_params",
    ),
    "_config": (
        "ConfigError", "ExperimentConfig", "OpticsConfig", "ParticlesConfig", "TileConfig", "VolumeConfig", "load_config", "write_config",
        "MAX_PLANES",
    ),
    "_dataset": (
        "DATASET_FORMAT", "DatasetLayout", "InputProcessing", "SyntheticDataset", "dataset_summary", "generate_dataset", "open_dataset",
        "synthetic_group",
    ),
    "_detection": ("PeakDecoder", "PlaneLinker", "detect_particles", "suppress"),
    "_flow": ("FLOWS", "SimulatedSequence", "flow_positions", "simulate_sequence"),
    "_effects": (
        "BASELINE", "EFFECTS", "OPTICAL_EFFECTS", "Effect", "check_effects", "effect_hologram", "effects_from_report", "optical_hologram",
        "parse_effect", "parse_effects", "sensor_image",
    ),
    "_gap": (
        "SUMMARY_GROUPS", "Diagnosis", "DiagnosisSettings", "diagnose_hologram", "diagnose_tiles", "gap_statistic", "measured_fringe", "real_spread",
        "tile_summaries", "where_gap", "write_report", "MIN_TILE_PX", "TileLayout", "field_surroundings", "known_sensor", "adapted_tile_px", "resampled_gaps",
    ),
    "_files": ("write_json", "json_safe", "read_text", "read_json_object"),
    "_heatmaps": ("FocusSpec", "FocusTargets", "context_indices", "focus_targets"),
    "_io": (
        "PARTICLE_COLUMNS", "InputError", "as_hologram", "check_table_name", "read_hologram", "read_particles", "read_stack", "write_particles",
        "write_stack",
    ),
    "_metrics": ("AXIAL_TOL_UM", "LATERAL_TOL_UM", "depth_errors_um", "diameter_errors_um", "match_particles", "score_particles", "seed_scores"),
    "_network": (
        "MODEL_FORMAT", "PRESETS", "FORMULATIONS", "focus_maps", "LoadedModel", "UNet", "build_network", "check_model_matches", "inference_network", "load_model",
        "network_outputs", "resolve_device", "save_model",
    ),
    "_optics": ("backpropagate", "padded_shape", "propagate", "propagation_grid", "set_transfer_cache_limit", "superpose", "transfer_function"),
    "_prediction": ("PredictionResult", "predict_particles", "tile_layout", "tile_normalisation"),
    "_progress": ("Stopped",),
    "_sequence": ("BACKGROUND_MODES", "HologramFrames", "SequenceResult", "local_cluster", "open_frames", "predict_sequence", "sequence_background"),
    "_samples": ("SAMPLE_PROVENANCE", "load_sample_hologram", "sample_hologram_path"),
    "_synthesis": (
        "LABEL_SCALE", "Distractors", "ParticleField", "count_for_ppp", "disc_coverage", "distractor_scene", "label_planes", "layer_images",
        "random_particle_field", "simulate_hologram",
    ),
    "_tracking": ("DISPLACEMENT_COLUMNS", "link_tracks"),
    "_training": ("THRESHOLD_FRACTIONS", "FOCUS_THRESHOLDS", "TrainingResult", "TrainingSettings", "train_model"),
    "_validation": (
        "HOLO_PARAM_RANGES", "check_intensity_image", "check_holo_params", "check_calibration", "check_memory", "check_disk", "check_output_path", "check_dataset_manifest", "check_model_payload", "check_prediction_meta", "load_resume_state",
        "check_resume_matches",
    ),
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
