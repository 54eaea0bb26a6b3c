"""Particles refined by a Lorenz–Mie fit, their material, and the hologram of a whole table and what is left beside it.

Stands on physics and the foundation; independent of learning. Other wings import these names from ``napari_lbs._core.refine``, never from its
private modules; each name is imported on first use.

`_batches`
    One batch"s fit, the neighbours in its model, and the batches run in this process or a pool of workers.
`_levenberg_marquardt`
    Robust least squares of the patches: Huber weights, the noise scale, Levenberg–Marquardt.
`_material`
    Which refined particles are of the sample"s material: a gate on the fitted index contrast.
`_model`
    The forward model of a batch of patches and its Jacobian.
`_patches`
    The refinement"s inputs checked, and the hologram patches it fits.
`_refine`
    Every detection refined by a Lorenz–Mie fit of its hologram patch: the rounds over the batches, the table.
`_rings`
    Searches on ring profiles: the symmetric centre, then depth, size and index.
`_scene`
    The Lorenz–Mie hologram of a whole particle table, and what a hologram holds beyond it.
`_settings`
    What the refinement fits, within which bounds, and how (`RefineSettings`).
`_valley`
    The valley profile about a fit: a restart in a deeper valley, the diameter"s and index"s intervals.
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_material": ("MATERIAL_SIGMAS", "MATERIAL_TOLERANCE", "same_material"),
        "_patches": ("SATURATED_PIXELS", "unsaturated_pixels"),
        "_refine": ("RefineSettings", "refine_particles"),
        "_scene": ("particle_hologram", "particle_holograms", "residual_hologram", "residual_particles"),
    },
)
