"""Diagnosing the sim-to-real gap: which catalog effects the experiment holds, where the gap lies, how far it shrinks.

One concern per module:

`_summaries`
    `tile_summaries`: the measurements of one tile, one code path for real and simulated tiles.
`_features`
    `set_summaries`, `set_features`: a set of tiles (one hologram on a grid) as one feature vector.
`_scenarios`
    `ScenarioPrior`, `draw_scenario`, `simulate_tiles`, `TileGrid`: the simulations a diagnosis learns from.
`_forest`
    `ForestArrays`, `train_forest`: a random forest kept as plain arrays.
`_amortized`
    `amortized_diagnoser`, `forest_posterior`, `DiagnosisSettings`: simulate, train, cache per setup; the posterior.
`_twosample`
    `c2st`, `mmd`: two-sample tests (told apart? how far apart?).
`_detect`
    `find_particles`: the experiment's particles without a trained model (focus in the back-propagated volume).
`_known`
    `known_sensor`: what a file of integer counts states (bit depth, saturation).
`_diagnose`
    `diagnose_hologram`: posterior, verdict, where and how much.
`_heldout`
    `TileSplit`, `whittle_loglik`, `model_probabilities`: the held-out likelihood of a frame's model, tile by tile.
`_nested`
    `select_effects`: the catalog's camera effects as nested models of the frame, forward selection.
`_scene_diagnosis`
    `diagnose_scene`: the gap diagnosed on the experiment's own fitted particles.
`_report`
    `write_report`: ``report.json`` (docs/formats.md), ``report.md``, figures.
"""

from napari_lbs._core.gap._amortized import Diagnoser, DiagnosisSettings, amortized_diagnoser, default_cache_dir, forest_posterior, load_diagnoser
from napari_lbs._core.gap._detect import find_particles
from napari_lbs._core.gap._diagnose import Diagnosis, diagnose_hologram
from napari_lbs._core.gap._known import known_sensor
from napari_lbs._core.gap._report import write_report
from napari_lbs._core.gap._scene_diagnosis import SceneDiagnosis, SceneDiagnosisSettings, diagnose_scene
from napari_lbs._core.gap._summaries import MIN_TILE_PX, SUMMARY_GROUPS, tile_summaries
from napari_lbs._core.gap._twosample import c2st, mmd

__all__ = [
    "diagnose_hologram", "write_report", "find_particles", "diagnose_scene", "SceneDiagnosis", "SceneDiagnosisSettings", "Diagnosis", "DiagnosisSettings", "forest_posterior", "amortized_diagnoser", "Diagnoser", "load_diagnoser",
    "default_cache_dir", "known_sensor", "tile_summaries", "c2st", "mmd", "SUMMARY_GROUPS", "MIN_TILE_PX",
]
