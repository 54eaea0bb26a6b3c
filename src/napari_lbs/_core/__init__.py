"""napari-lbs computation, importable without Qt or napari (torch is imported lazily).

Long-running functions take keyword-only ``progress(done, total)`` and ``should_stop()``
callbacks (see `napari_lbs._core._progress`).
"""

from napari_lbs._core._calibration import (
    PARAM_BOUNDS,
    CalibrationResult,
    CalibrationSettings,
    HoloParams,
    calibrate,
    calibrate_hologram,
    choose_reference_tile,
    experimental_reference,
    holo_processing,
    score_params,
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

__all__ = [
    "PARAM_BOUNDS",
    "CalibrationResult",
    "CalibrationSettings",
    "HoloParams",
    "calibrate",
    "calibrate_hologram",
    "choose_reference_tile",
    "experimental_reference",
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
]
