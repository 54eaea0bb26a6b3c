"""Diagnosing the sim-to-real gap: which catalog effects the experiment holds, where the gap lies, how far it shrinks.

One concern per module:

`_detect`
    `find_particles`: the experiment's particles without a trained model (focus in the back-propagated volume).
`_heldout`
    `TileSplit`, `whittle_loglik`, `model_probabilities`: the held-out likelihood of a frame's model, tile by tile.
`_scene_image`
    `Scene`: the fitted particles' hologram, whole and in depth groups, and the blurs that act on it by depth.
`_unexplained`
    `unexplained_share`, `share_by_depth`, `line_pattern`: what a frame's model leaves, by tile, band and depth.
`_nested`
    `select_effects`: the catalog's camera effects as nested models of the frame, forward selection.
`_particle_models`
    `particle_models`: the scene's particles rendered as opaque spheres and as transparent ones, for the optics tests.
`_optics_power`
    `optics_power_test`: opaque against transparent spheres by the power spectrum of their fine rings.
`_through_focus`
    `through_focus_test`: opaque against transparent spheres by the light on each sphere's axis, back-propagated through its depth.
`_dust_layer`
    `dust_layer`: dust on a window outside the volume, a layer of grains fitted in what the frame's model leaves and among the scene's particles.
`_levels`
    `levels_test`: quantization and saturation read from the levels a frame of integer counts uses.
`_scene_diagnosis`
    `diagnose_scene`: the gap diagnosed on the experiment's own fitted particles.
`_report`
    `write_report`: ``report.json`` (docs/formats.md), ``report.md``, figures; `parameter_text`: an effect's parameters with their errors.
"""

from napari_lbs._core.foundation import lazy_exports

# names imported on first use: `find_particles` runs without torch, which only `diagnose_scene` (its refinement) loads
__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_detect": ("find_particles",),
        "_report": ("parameter_text", "write_report"),
        "_scene_diagnosis": ("SceneDiagnosis", "SceneDiagnosisSettings", "diagnose_scene"),
    },
)
