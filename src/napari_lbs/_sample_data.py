"""napari sample data: the seed paper's real hologram as an Image layer (µm scale)."""

from __future__ import annotations

from napari_lbs._core import SAMPLE_PROVENANCE, load_config, load_sample_hologram


def real_hologram():
    """The real 1024² hologram's red channel, with its optics in the layer metadata."""
    config = load_config(None)
    pixel_um = config.optics.pixel_um
    metadata = {"provenance": SAMPLE_PROVENANCE, "config": config.to_dict()}
    return [(load_sample_hologram(), {"name": "LBS real hologram", "scale": (pixel_um, pixel_um), "units": "µm", "metadata": metadata}, "image")]
