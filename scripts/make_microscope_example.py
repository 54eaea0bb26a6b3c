"""The built-in synthetic microscope example (src/napari_lbs/data/microscope_example*).

Run: python scripts/make_microscope_example.py [--out src/napari_lbs/data]

Four polystyrene spheres (index contrast 0.26) of 0.8–3 µm diameter in water, 12–36 µm from
the focal plane, seen through a 60× objective on a camera of 6 µm pixels (0.1 µm at the
sample), 660 nm: 256² pixels. The hologram is the project's own Lorenz–Mie model
(`particle_hologram`: every sphere's field added coherently, each pixel integrating its area)
times a Gaussian illumination, recorded as 16-bit camera counts with photon and read noise
and a dark offset (none saturates: the brightest focal spot reaches twice the unobstructed light); a background frame (the same illumination, other noise) and a dark frame
go with it. Writes, deterministically (one seed):

- ``microscope_example.toml``: the config (camera pitch and magnification);
- ``microscope_example_hologram.tif``, ``microscope_example_background.tif``,
  ``microscope_example_dark.tif``: uint16 counts;
- ``microscope_example_truth.csv``: the spheres (``x_um, y_um, z_um, diameter_um,
  index_contrast``), depths physical (the config's medium index is water's).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from napari_lbs._core import load_config, write_particles
from napari_lbs._core.refine import RefineSettings, particle_hologram

SEED = 20261127
SHAPE = (256, 256)
CONFIG = """[optics]
wavelength_um = 0.66
camera_pixel_um = 6.0      # stored as pixel_um = 6.0 / 60 = 0.1 (the pitch at the sample)
magnification = 60.0
medium_index = 1.33        # depths are physical distances in water

[volume]
z_min_um = 5.0
z_max_um = 45.0
z_step_um = 0.5

[particles]
diameter_min_um = 0.5
diameter_max_um = 3.0
per_tile = 4
layer_step_um = 5.0

[tile]
size = 256
"""
TRUTH = {
    "x_um": np.array([6.4, 19.3, 7.1, 18.2]),
    "y_um": np.array([7.0, 5.9, 19.6, 18.4]),
    "z_um": np.array([12.0, 20.0, 28.0, 36.0]),
    "diameter_um": np.array([0.8, 1.5, 2.2, 3.0]),
    "index_contrast": np.full(4, 0.26),
}
FULL_WELL = 3000.0  # counts of the unobstructed light at the beam's centre
DARK = 100.0  # the camera's offset (counts)
READ_NOISE = 3.0  # counts rms


def make(out: Path) -> None:
    rng = np.random.default_rng(SEED)
    out.mkdir(parents=True, exist_ok=True)
    config_path = out / "microscope_example.toml"
    config_path.write_text(CONFIG, encoding="utf-8")
    config = load_config(config_path)
    # patches wide enough that every sphere's fringes cover the whole frame
    settings = RefineSettings(medium_index=config.optics.medium_index, patch_px=max(SHAPE))
    model = particle_hologram(SHAPE, TRUTH, config, settings=settings)
    rows, cols = np.mgrid[: SHAPE[0], : SHAPE[1]]
    beam = np.exp(-((rows - 0.45 * SHAPE[0]) ** 2 + (cols - 0.55 * SHAPE[1]) ** 2) / (2 * (1.2 * SHAPE[0]) ** 2))

    def camera(intensity: np.ndarray) -> np.ndarray:
        electrons = rng.poisson(FULL_WELL * intensity) + rng.normal(DARK, READ_NOISE, SHAPE)
        return np.clip(np.round(electrons), 0, 65535).astype(np.uint16)

    import tifffile

    tifffile.imwrite(out / "microscope_example_hologram.tif", camera(model * beam))
    tifffile.imwrite(out / "microscope_example_background.tif", camera(beam))
    tifffile.imwrite(out / "microscope_example_dark.tif", camera(np.zeros(SHAPE)))
    write_particles(out / "microscope_example_truth.csv", TRUTH, force=True)  # the example is made again whole


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "src" / "napari_lbs" / "data")
    make(parser.parse_args().out)


if __name__ == "__main__":
    main()
