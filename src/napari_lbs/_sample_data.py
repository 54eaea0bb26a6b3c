"""napari sample data: the seed paper's real hologram and a seeded synthetic hologram with its truth (all in µm)."""

from __future__ import annotations

from napari_lbs._core import load_config, load_sample_hologram, random_particle_field, simulate_hologram
from napari_lbs._core.foundation import SAMPLE_PROVENANCE
from napari_lbs._layers import UNITS, PlaneGrid, particle_points, prefer_particle_writer

SYNTHETIC_SEED = 2024
SYNTHETIC_SHAPE = (512, 512)
SYNTHETIC_PARTICLES = 48


def real_hologram():
    """The real 1024² hologram's red channel, with its optics in the layer metadata."""
    config = load_config(None)
    pixel_um = config.optics.pixel_um
    metadata = {"provenance": SAMPLE_PROVENANCE, "config": config.to_dict()}
    return [(load_sample_hologram(), {"name": "LBS real hologram", "scale": (pixel_um, pixel_um), "units": UNITS, "metadata": metadata}, "image")]


def synthetic_hologram():
    """A seeded 512² hologram of 48 opaque particles (default config) and its ground-truth Points on the default planes."""
    prefer_particle_writer()  # the truth saves as a particle table
    config = load_config(None)
    field = random_particle_field(
        SYNTHETIC_SHAPE,
        count=SYNTHETIC_PARTICLES,
        diameter_min_um=config.particles.diameter_min_um,
        diameter_max_um=config.particles.diameter_max_um,
        layers_um=config.layer_depths_um(),
        pixel_um=config.optics.pixel_um,
        seed=SYNTHETIC_SEED,
    )
    hologram = simulate_hologram(field, wavelength_um=config.optics.wavelength_um, medium_index=config.optics.medium_index)
    pixel_um = config.optics.pixel_um
    provenance = {"seed": SYNTHETIC_SEED, "particles": SYNTHETIC_PARTICLES, "config": config.to_dict(), "model": "opaque discs, superposed layers (HCS)"}
    data, keywords = particle_points(field.table(), PlaneGrid.of_planes(config.volume.planes_um(), pixel_um=pixel_um))
    return [
        (hologram, {"name": "synthetic hologram", "scale": (pixel_um, pixel_um), "units": UNITS, "metadata": {"provenance": provenance}}, "image"),
        (data, {"name": "synthetic truth", **keywords, "border_color": "yellow", "metadata": {"provenance": provenance}}, "points"),
    ]
