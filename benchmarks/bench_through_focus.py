"""Particle optics from the spheres' through-focus centres: which material reproduces the back-propagated light on each sphere's axis?

A transparent sphere is a ball lens: its refracted light crosses the axis in a focus a few
tens of micrometres before the sphere (towards the sensor), and back-propagated, the centre
of its image stays partly bright over a depth range that depends on the index contrast; an
opaque sphere leaves its centre dark. Per sphere of a table (positions and sizes fitted or
known), the hologram is back-propagated to 16 depths from 200 µm before the sphere's depth to
100 µm past it, on a `HALF_PX`·2 square around it, and the mean intensity of its 3 × 3 centre
over the median of the 71² around it is its **profile**. The same is done on each material's
render of the whole table (`particle_holograms`, every sphere's rings to 1 cycle per pixel,
aliased as a camera records them), blurred by a Gaussian of each ``--blur-px``; the material
and blur whose profiles are nearest (summed squared difference over the spheres wholly
inside the frame's margin of `HALF_PX`) is the reading. Bootstrap over the spheres gives the
share of resamples each reading wins.

Modes:

* ``pseudo``: holograms of an independent forward model (`pseudoreal.mie_intensity`,
  pylorenzmie) of 60 spheres of 20–30 µm, polystyrene (n 1.59, contrast 0.26 in water) and
  n 1.45 (0.12), unblurred and blurred by 1.03 px, through `pseudoreal.camera` (photons, 8 bits),
  read with the spheres' true places, and for polystyrene through the blur once more with the
  rendered table's depths and diameters off by a fit's errors (σ 5 µm and 0.5 µm);
* ``real``: the built-in hologram with a table of its spheres (``--table``: e.g. the
  ``particles.csv`` of ``napari-lbs demo``; the spheres of 20–30 µm are read, every sphere of
  15 µm or more is rendered).

    python benchmarks/bench_through_focus.py pseudo --out benchmarks/results/diagnosis/through_focus_pseudo_2026-11-29.json
    python benchmarks/bench_through_focus.py real --table demo/particles.csv --out benchmarks/results/diagnosis/through_focus_real_2026-11-29.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

HALF_PX = 192
RELATIVE_DEPTHS_UM = np.arange(-200.0, 101.0, 20.0)
CONTRASTS = (None, 0.06, 0.12, 0.16, 0.19, 0.22, 0.26, 0.30, 0.33, 0.40)  # None: an opaque sphere


def profiles(hologram: np.ndarray, table, config) -> np.ndarray:
    """(spheres, depths): each sphere's centre over its surroundings, back-propagated to its depth + `RELATIVE_DEPTHS_UM` (`axis_profile`)."""
    from napari_lbs._core.gap._through_focus import axis_profile

    pixel = config.optics.pixel_um
    padded = np.pad(hologram.astype(np.float32), HALF_PX, mode="reflect")  # the spheres read lie inside the margin: their crops are the frame's
    return np.array([axis_profile(padded, int(round(sphere.y_um / pixel)), int(round(sphere.x_um / pixel)), sphere.z_um + RELATIVE_DEPTHS_UM, config, half_px=HALF_PX)
                     for sphere in table.itertuples()])


def reading(hologram: np.ndarray, rendered, read, config, *, blurs_px, seed: int = 0) -> dict:
    """The material and blur whose profiles are nearest the hologram's, over the spheres of ``read``."""
    from scipy.ndimage import gaussian_filter

    data = profiles(hologram, read, config)
    errors = np.array([[((data - profiles(gaussian_filter(image, blur) if blur else image, read, config)) ** 2).sum(1) for image in rendered] for blur in blurs_px])
    total = errors.sum(2)  # (blurs, materials)
    blur, material = np.unravel_index(int(np.argmin(total)), total.shape)
    rng = np.random.default_rng(seed)
    wins: dict[str, int] = {}
    for _ in range(200):
        pick = rng.integers(0, errors.shape[2], errors.shape[2])
        b, m = np.unravel_index(int(np.argmin(errors[:, :, pick].sum(2))), total.shape)
        key = f"{CONTRASTS[m]}@{blurs_px[b]}"
        wins[key] = wins.get(key, 0) + 1
    return {"spheres": int(errors.shape[2]), "contrasts": [str(c) for c in CONTRASTS], "blurs_px": list(blurs_px), "summed_squared_difference": total.round(4).tolist(),
            "best": {"index_contrast": str(CONTRASTS[material]), "blur_px": blurs_px[blur]}, "bootstrap_share": {k: v / 200 for k, v in sorted(wins.items())},
            "profile_data_median": np.median(data, 0).round(3).tolist()}


def rendered_materials(shape, table, config) -> list:
    """The table rendered as each of `CONTRASTS` (``None``: opaque) to 1 cycle per pixel (`particle_models`), unblurred."""
    from napari_lbs._core.gap._particle_models import particle_models

    return list(particle_models(shape, table, config, index_grid=[c for c in CONTRASTS if c is not None]).values())


def inside(table, shape, config):
    pixel = config.optics.pixel_um
    cols, rows = table["x_um"] / pixel, table["y_um"] / pixel
    return table[(cols > HALF_PX) & (cols < shape[1] - HALF_PX) & (rows > HALF_PX) & (rows < shape[0] - HALF_PX)]


def pseudo(config) -> list[dict]:
    import pandas as pd
    import pseudoreal
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(11)
    count, size, pixel = 60, 1024, pseudoreal.PIXEL_UM
    table = pd.DataFrame({"x_um": rng.uniform(0, (size - 1) * pixel, count), "y_um": rng.uniform(0, (size - 1) * pixel, count),
                          "z_um": rng.uniform(1900.0, 4700.0, count), "diameter_um": rng.uniform(20.0, 30.0, count)})
    rendered = rendered_materials((size, size), table, config)
    rows = []
    for name, index in (("polystyrene (contrast 0.26)", None), ("n 1.45 (contrast 0.12)", 1.45)):
        intensity = pseudoreal.mie_intensity((size, size), *(table[c].to_numpy() for c in ("x_um", "y_um", "z_um", "diameter_um")),
                                             None if index is None else np.full(count, index))
        for blur in (0.0, 1.03):
            frame = pseudoreal.camera(gaussian_filter(intensity, blur) if blur else intensity, rng=np.random.default_rng(5)).astype(np.float32)
            frame = frame / gaussian_filter(frame, 64)  # the envelope taken off
            started = time.perf_counter()
            row = {"frame": name, "camera_blur_px": blur, **reading(frame, rendered, inside(table, frame.shape, config), config, blurs_px=(blur,)),
                   "seconds": round(time.perf_counter() - started, 1)}
            rows.append(row)
            print(f"{name}, blur {blur}: read {row['best']} ({row['bootstrap_share']}), {row['spheres']} spheres", flush=True)
            if index is None and blur:
                rows += perturbed(frame, table, config, blur_px=blur)
    return rows


def perturbed(frame: np.ndarray, table, config, *, blur_px: float) -> list[dict]:
    """Readings with the rendered table's depths and diameters off by a fit's errors (normal, σ as given), the frame unchanged."""
    rows = []
    for z_sd_um, d_sd_um in ((5.0, 0.0), (0.0, 0.5), (10.0, 0.5)):
        errors = np.random.default_rng(3)
        fitted = table.assign(z_um=table["z_um"] + errors.normal(0.0, z_sd_um, len(table)), diameter_um=table["diameter_um"] + errors.normal(0.0, d_sd_um, len(table)))
        row = {"frame": "polystyrene (contrast 0.26), rendered table perturbed", "camera_blur_px": blur_px, "z_sd_um": z_sd_um, "diameter_sd_um": d_sd_um,
               **reading(frame, rendered_materials(frame.shape, fitted, config), inside(fitted, frame.shape, config), config, blurs_px=(blur_px,))}
        rows.append(row)
        print(f"  table off by z σ {z_sd_um} µm, d σ {d_sd_um} µm: read {row['best']} ({row['bootstrap_share']})", flush=True)
    return rows


def real(config, table_path: Path) -> list[dict]:
    import pandas as pd
    from scipy.ndimage import gaussian_filter

    from napari_lbs._core import load_sample_hologram

    hologram = load_sample_hologram().astype(np.float32)
    hologram = hologram / gaussian_filter(hologram, 64)
    table = pd.read_csv(table_path)
    table = table[table["diameter_um"] >= 15.0]
    read = inside(table[(table["diameter_um"] >= 20.0) & (table["diameter_um"] <= 30.0)], hologram.shape, config)
    started = time.perf_counter()
    row = {"table": str(table_path), "rendered_spheres": len(table), **reading(hologram, rendered_materials(hologram.shape, table, config), read, config,
                                                                                blurs_px=(0.8, 1.03, 1.3, 1.6)),
           "seconds": round(time.perf_counter() - started, 1)}
    print(f"built-in hologram: read {row['best']} ({row['bootstrap_share']}), {row['spheres']} spheres", flush=True)
    return [row]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=("pseudo", "real"))
    parser.add_argument("--table", type=Path, help="real: the built-in hologram's spheres (x_um, y_um, z_um, diameter_um)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    from napari_lbs._core import load_config

    config = load_config()
    load_before = os.getloadavg()
    rows = pseudo(config) if args.mode == "pseudo" else real(config, args.table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"rows": rows, "relative_depths_um": RELATIVE_DEPTHS_UM.tolist(), "half_px": HALF_PX,
                                    "load_before": load_before, "load_after": os.getloadavg()}, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
