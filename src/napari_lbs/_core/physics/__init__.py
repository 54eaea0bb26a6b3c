"""The physics: angular-spectrum optics, Lorenz–Mie and disc holograms, synthetic particle fields, the effect catalog.

Stands on the foundation only. Other wings import these names from ``napari_lbs._core.physics``, never from its
private modules; each name is imported on first use.

`_disc`
    Holograms of opaque discs (the seed"s particle model), batched and differentiable in torch.
`_effects`
    The effect catalog: parametric extensions of the seed"s simulator, for diagnosis and for data.
`_gaussian_blur`
    A Gaussian blur as sums of shifted slices, at every pixel or at the kept rows and columns.
`_interpolation`
    Cubic (Catmull–Rom) interpolation of radial tables, differentiable, for the Lorenz–Mie profiles.
`_lorenz_mie`
    Lorenz–Mie holograms of single spheres, batched and differentiable in torch.
`_optics`
    Angular-spectrum propagation of scalar fields between parallel planes.
`_synthesis`
    Random particle fields, their layer images, holograms and ground-truth label planes (HCS).
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_effects": ("EFFECTS", "OPTICAL_EFFECTS", "check_effects", "effect_hologram", "effects_from_report", "optical_hologram", "parse_effects", "sensor_image"),
        "_gaussian_blur": ("gaussian_blur",),
        "_lorenz_mie": ("fields_from_profiles", "holograms_from_fields", "lateral_derivatives", "mean_intensity", "mie_coefficients", "radial_profiles", "radial_step", "sphere_fields", "term_count", "weighted_coefficients"),
        "_optics": ("backpropagate", "backpropagated_blocks", "padded_shape", "propagate", "transfer_function"),
        "_synthesis": ("Distractors", "LABEL_SCALE", "ParticleField", "SizeDistribution", "distractor_scene", "distractors_from_report", "label_planes", "random_particle_field", "simulate_hologram", "sizes_from_report"),
    },
)
