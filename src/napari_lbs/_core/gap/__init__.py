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

from napari_lbs._core.foundation import lazy_exports

# names imported on first use: `diagnose_hologram` runs without torch, which only `diagnose_scene` (its refinement) loads
__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_amortized": ("Diagnoser", "DiagnosisSettings", "amortized_diagnoser", "default_cache_dir", "forest_posterior", "load_diagnoser"),
        "_detect": ("find_particles",),
        "_diagnose": ("Diagnosis", "diagnose_hologram"),
        "_known": ("known_sensor",),
        "_report": ("write_report",),
        "_scene_diagnosis": ("SceneDiagnosis", "SceneDiagnosisSettings", "diagnose_scene"),
        "_summaries": ("MIN_TILE_PX", "SUMMARY_GROUPS", "tile_summaries"),
        "_twosample": ("c2st", "mmd"),
    },
)
