"""napari-lbs computation, importable without Qt or napari (torch is imported lazily).

Long-running functions take keyword-only ``progress(done, total)`` and ``should_stop()``
callbacks (see `napari_lbs._core._progress`).

The names from the network, training and prediction modules need torch; they are listed
here like the others but imported on first use (PEP 562), so ``import napari_lbs._core``
stays light.
"""

import importlib

from napari_lbs._core._calibration import (
    PARAM_BOUNDS,
    CalibrationResult,
    CalibrationSettings,
    HoloParams,
    calibrate,
    calibrate_hologram,
    choose_reference_tile,
    experimental_planes,
    experimental_reference,
    holo_processing,
    score_params,
)
from napari_lbs._core._dataset import (
    DATASET_FORMAT,
    DatasetLayout,
    InputProcessing,
    SyntheticDataset,
    dataset_summary,
    generate_dataset,
    open_dataset,
    synthetic_group,
)
from napari_lbs._core._detection import PeakDecoder, PlaneLinker, detect_particles, suppress
from napari_lbs._core._heatmaps import FocusSpec, FocusTargets, context_indices, focus_targets
from napari_lbs._core._effects import (
    BASELINE,
    EFFECTS,
    OPTICAL_EFFECTS,
    Effect,
    check_effects,
    effect_hologram,
    effects_from_report,
    optical_hologram,
    parse_effect,
    sensor_image,
)
from napari_lbs._core._gap import (
    SUMMARY_GROUPS,
    Diagnosis,
    DiagnosisSettings,
    diagnose_hologram,
    diagnose_tiles,
    gap_statistic,
    measured_fringe,
    real_spread,
    tile_summaries,
    where_gap,
    write_report,
)
from napari_lbs._core._config import (
    ConfigError,
    ExperimentConfig,
    OpticsConfig,
    ParticlesConfig,
    TileConfig,
    VolumeConfig,
    load_config,
    write_config,
)
from napari_lbs._core._io import (
    PARTICLE_COLUMNS,
    InputError,
    as_hologram,
    read_hologram,
    read_particles,
    read_stack,
    write_json,
    write_particles,
    write_stack,
)
from napari_lbs._core._metrics import AXIAL_TOL_UM, LATERAL_TOL_UM, depth_errors_um, match_particles, score_particles, seed_scores
from napari_lbs._core._optics import (
    backpropagate,
    padded_shape,
    propagate,
    propagation_grid,
    set_transfer_cache_limit,
    superpose,
    transfer_function,
)
from napari_lbs._core._progress import Stopped
from napari_lbs._core._samples import SAMPLE_PROVENANCE, load_sample_hologram, sample_hologram_path
from napari_lbs._core._synthesis import (
    LABEL_SCALE,
    ParticleField,
    count_for_ppp,
    disc_coverage,
    label_planes,
    layer_images,
    random_particle_field,
    simulate_hologram,
)

_TORCH_NAMES = {
    "_network": ("MODEL_FORMAT", "PRESETS", "FORMULATIONS", "focus_maps", "LoadedModel", "UNet", "build_network", "check_model_matches", "load_model", "network_outputs", "resolve_device", "save_model"),
    "_training": ("THRESHOLD_FRACTIONS", "FOCUS_THRESHOLDS", "TrainingResult", "TrainingSettings", "train_model"),
    "_prediction": ("PredictionResult", "predict_particles", "tile_layout"),
}
_LAZY = {name: module for module, names in _TORCH_NAMES.items() for name in names}


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(f"napari_lbs._core.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "PARAM_BOUNDS",
    "CalibrationResult",
    "CalibrationSettings",
    "HoloParams",
    "calibrate",
    "calibrate_hologram",
    "choose_reference_tile",
    "experimental_reference",
    "experimental_planes",
    "holo_processing",
    "score_params",
    "ConfigError",
    "ExperimentConfig",
    "OpticsConfig",
    "ParticlesConfig",
    "TileConfig",
    "VolumeConfig",
    "load_config",
    "write_config",
    "PARTICLE_COLUMNS",
    "InputError",
    "as_hologram",
    "read_hologram",
    "read_particles",
    "read_stack",
    "write_json",
    "write_particles",
    "write_stack",
    "AXIAL_TOL_UM",
    "LATERAL_TOL_UM",
    "match_particles",
    "score_particles",
    "seed_scores",
    "depth_errors_um",
    "backpropagate",
    "padded_shape",
    "propagate",
    "propagation_grid",
    "set_transfer_cache_limit",
    "superpose",
    "transfer_function",
    "Stopped",
    "SAMPLE_PROVENANCE",
    "load_sample_hologram",
    "sample_hologram_path",
    "LABEL_SCALE",
    "ParticleField",
    "count_for_ppp",
    "disc_coverage",
    "label_planes",
    "layer_images",
    "random_particle_field",
    "simulate_hologram",
    "DATASET_FORMAT",
    "DatasetLayout",
    "InputProcessing",
    "SyntheticDataset",
    "dataset_summary",
    "generate_dataset",
    "open_dataset",
    "synthetic_group",
    "PlaneLinker",
    "detect_particles",
    "PeakDecoder",
    "suppress",
    "FocusSpec",
    "FocusTargets",
    "context_indices",
    "focus_targets",
    "BASELINE",
    "EFFECTS",
    "OPTICAL_EFFECTS",
    "Effect",
    "optical_hologram",
    "sensor_image",
    "check_effects",
    "parse_effect",
    "effects_from_report",
    "effect_hologram",
    "SUMMARY_GROUPS",
    "Diagnosis",
    "DiagnosisSettings",
    "diagnose_hologram",
    "diagnose_tiles",
    "gap_statistic",
    "real_spread",
    "tile_summaries",
    "measured_fringe",
    "where_gap",
    "write_report",
    *_LAZY,
]
