"""Particles refined by a Lorenz–Mie fit, their material, and the hologram of a whole table and what is left beside it.

Stands on physics and the foundation; independent of learning. Other wings import these names from ``napari_lbs._core.refine``, never from its
private modules; each name is imported on first use.

`_material`
    Which refined particles are of the sample"s material: a gate on the fitted index contrast.
`_refine`
    Every detection refined by a Lorenz–Mie fit of its hologram patch.
`_scene`
    The Lorenz–Mie hologram of a whole particle table, and what a hologram holds beyond it.
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_material": ("MATERIAL_SIGMAS", "MATERIAL_TOLERANCE", "same_material"),
        "_refine": ("RefineSettings", "refine_particles"),
        "_scene": ("particle_hologram", "residual_hologram", "residual_particles"),
    },
)
