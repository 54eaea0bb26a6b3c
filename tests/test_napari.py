"""The napari side: manifest and sample data in a real viewer (needs a display: xvfb-run)."""

import numpy as np


def test_manifest_validates():
    from importlib.resources import files

    from npe2 import PluginManifest

    manifest = PluginManifest.from_file(files("napari_lbs") / "napari.yaml")
    manifest.validate_imports()
    assert manifest.name == "napari-lbs"


def test_real_sample_hologram_opens_with_micrometre_scale(make_napari_viewer):
    viewer = make_napari_viewer()
    layers = viewer.open_sample("napari-lbs", "real_hologram")
    layer = layers[0]
    assert layer.data.shape == (1024, 1024) and layer.data.dtype == np.float32
    assert tuple(layer.scale) == (2.2, 2.2)
    assert "MIT" in layer.metadata["provenance"]["source"]
