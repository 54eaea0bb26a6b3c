"""A gallery of a demo's lowest- and highest-score detections (docs/figures/real_low_score_detections.png).

Run: python scripts/detections_gallery.py DEMO_FOLDER [--low 16] [--high 8] [--out PNG]
For each detection, three panels 176 µm wide: the hologram around it, the back-propagated
plane nearest its depth (the demo's ``zstack.tif``) and the x–z section through it (depth
down, the red line at its depth). What a particle looks like, and what the network reports
that may not be one.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from napari_lbs._core import load_config, load_sample_hologram, read_particles, read_stack  # noqa: E402

HALF_PX = 40


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demo", type=Path, help="a `napari-lbs demo --out` folder")
    parser.add_argument("--low", type=int, default=16, help="lowest-score detections shown (default 16)")
    parser.add_argument("--high", type=int, default=8, help="highest-score detections shown (default 8)")
    parser.add_argument("--out", type=Path, default=Path("docs/figures/real_low_score_detections.png"))
    args = parser.parse_args()
    summary = json.loads((args.demo / "summary.json").read_text())
    particles = read_particles(args.demo / "particles.csv")
    stack, description = read_stack(args.demo / "zstack.tif")
    z_um = np.asarray(description["z_um"], float)
    hologram = load_sample_hologram()
    pixel_um = load_config(None).optics.pixel_um
    order = np.argsort(particles["score"], kind="stable")
    chosen = list(order[: args.low]) + list(order[len(order) - args.high :])
    columns = 4
    rows = -(-len(chosen) // columns)
    figure, axes = plt.subplots(rows, 3 * columns, figsize=(3 * columns * 1.3, rows * 1.45))
    for axis in axes.flat:
        axis.set_xticks([])
        axis.set_yticks([])
    for k, i in enumerate(chosen):
        row, col = divmod(k, columns)
        cx, cy = int(round(particles["x_um"][i] / pixel_um)), int(round(particles["y_um"][i] / pixel_um))
        y0, y1 = max(cy - HALF_PX, 0), min(cy + HALF_PX, hologram.shape[0])
        x0, x1 = max(cx - HALF_PX, 0), min(cx + HALF_PX, hologram.shape[1])
        plane = int(np.argmin(np.abs(z_um - particles["z_um"][i])))
        hologram_axis, plane_axis, section_axis = axes[row, 3 * col : 3 * col + 3]
        hologram_axis.imshow(hologram[y0:y1, x0:x1], cmap="gray")
        hologram_axis.set_title(f"score {particles['score'][i]:.2f}, d {particles['diameter_um'][i]:.0f} um", fontsize=7)
        plane_axis.imshow(stack[plane, y0:y1, x0:x1], cmap="gray")
        plane_axis.set_title(f"plane z {z_um[plane]:.0f} um", fontsize=7)
        section_axis.imshow(stack[:, min(cy, hologram.shape[0] - 1), x0:x1], cmap="gray", aspect="auto")
        section_axis.axhline(plane, color="red", lw=0.6)
        section_axis.set_title("x-z section", fontsize=7)
    figure.suptitle(f"{args.demo.name}: the {args.low} lowest- and {args.high} highest-score of {len(order)} detections "
                    f"(model {summary['model_sha256'][:12]}); panels {2 * HALF_PX * pixel_um:.0f} um wide", fontsize=9)
    figure.tight_layout()
    figure.savefig(args.out, dpi=80)
    print(args.out)


if __name__ == "__main__":
    main()
