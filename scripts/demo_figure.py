"""The figure of a demo's detections over the real hologram (docs/figures/demo_real_particles.png).

Run: python scripts/demo_figure.py DEMO_FOLDER [--out PNG]
Left: the hologram with a circle per particle (diameter to scale, colour = score). Right:
the particles seen from the side (x against depth), the same colours.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from napari_lbs._core import load_config, load_sample_hologram, read_particles  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demo", type=Path, help="a `napari-lbs demo --out` folder")
    parser.add_argument("--out", type=Path, default=Path("docs/figures/demo_real_particles.png"))
    args = parser.parse_args()
    summary = json.loads((args.demo / "summary.json").read_text())
    particles = read_particles(args.demo / "particles.csv")
    hologram = load_sample_hologram()
    pixel_um = load_config(None).optics.pixel_um
    extent = (0, hologram.shape[1] * pixel_um, hologram.shape[0] * pixel_um, 0)
    figure, (top, side) = plt.subplots(1, 2, figsize=(13, 6.2), gridspec_kw={"width_ratios": [1, 1.1]})
    top.imshow(hologram, cmap="gray", extent=extent)
    for x, y, d, s in zip(particles["x_um"], particles["y_um"], particles["diameter_um"], particles["score"], strict=True):
        top.add_patch(plt.Circle((x, y), max(d, 15.0), fill=False, lw=1.2, color=plt.cm.plasma(s)))
    top.set(title=f"{len(particles['x_um'])} particles (circle radius: the diameter, at least 15 um)", xlabel="x (um)", ylabel="y (um)")
    points = side.scatter(particles["x_um"], particles["z_um"], s=particles["diameter_um"] ** 2 / 8, c=particles["score"], cmap="plasma", vmin=0, vmax=1)
    side.set(title="side view", xlabel="x (um)", ylabel="depth z (um, air-equivalent)", ylim=(4800, 1800))
    figure.colorbar(points, ax=side, label="score (probability)")
    validation = summary["validation"]
    figure.suptitle(f"napari-lbs demo on the real hologram, trained on {summary['training']['data']}\n"
                    f"synthetic validation ER {100 * validation['er']:.1f} %, JI {validation['ji']:.3f}; score threshold {validation['threshold']:g}", fontsize=9)
    figure.tight_layout()
    figure.savefig(args.out, dpi=90)
    print(args.out)


if __name__ == "__main__":
    main()
