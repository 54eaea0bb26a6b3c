"""Built-in data: the seed paper's real 1024² hologram (MIT, see data/LICENSE-lbs-experiment.txt)."""

from __future__ import annotations

from importlib.resources import files

import numpy as np

__all__ = ["sample_hologram_path", "load_sample_hologram", "SAMPLE_PROVENANCE"]

SAMPLE_PROVENANCE = {
    "source": "zhoubozhen/LBS data/experiment_data/cropped_hologram.bmp (MIT, Copyright (c) 2024 zhoubozhen)",
    "setup": "polystyrene spheres 20-30 um in water, 3 mm cuvette; 660 nm; 2.2 um pixels; depths 1800-4800 um",
    "channel": "red (the laser's colour; green and blue hold little signal)",
}


def sample_hologram_path():
    """Path of the shipped RGB hologram (lossless WebP, bit-identical to the seed's BMP)."""
    return files("napari_lbs") / "data" / "lbs_experiment_hologram.webp"


def load_sample_hologram(*, rgb: bool = False) -> np.ndarray:
    """The seed's real hologram: its red channel as float32 (1024, 1024), or the raw uint8 RGB."""
    from PIL import Image

    with Image.open(sample_hologram_path()) as handle:
        image = np.asarray(handle.convert("RGB"))
    return image if rgb else image[..., 0].astype(np.float32)
