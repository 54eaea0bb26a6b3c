"""Particle optics on the built-in real hologram: does the data prefer transparent spheres to opaque ones?

The scene is found without a network (`find_particles`), the strongest ``--particles``
guesses are refined with the index contrast held at each value of a grid (absorption 0:
transparent spheres) and once as opaque spheres (index contrast 0, absorption ``--opaque-kappa``),
every other parameter fitted. Per particle and model the fit's relative rms residual is
kept; reported are the mean squared residual over the particles refined under every model,
each particle's best index contrast, and the paired difference opaque − best transparent,
with the load average before and after. A second part starts the free fit (index contrast
fitted) at several values, to show whether the fitted index follows its start.

Two more views of the same fits, where the experiment's structured background weighs less:

- **The frame's held-out likelihood.** Each model's fitted particles are rendered over the
  whole frame to 1 cycle per pixel (`particle_hologram`: the refracted light's far rings
  included), through a camera blur of each ``--camera-blur-px`` (Gaussian σ; the built-in
  frame's colour sensor blurs by about 1 px), and the residual is judged tile by tile by the
  Whittle likelihood against its own spectrum (`whittle_loglik`, 4 × 4 tiles), which weighs
  the background's strong bands down. Reported per model: the summed gain over opaque spheres
  and the tiles it wins.
- **The discs at focus.** Each particle's 256² neighbourhood is back-propagated to its fitted
  depth; a transparent sphere's refracted light keeps its disc partly bright there, an
  opaque one's is dark. The mean intensity inside 0.3 of its radius, less the background's
  power ``|E − 1|²`` 30–100 px away (what the other particles and the camera add there), is
  compared with each model's own particle rendered alone and back-propagated the same way:
  per model, the median absolute difference and the particles it matches better than opaque.

    python benchmarks/bench_particle_optics.py --particles 48 --out benchmarks/results/diagnosis/particle_optics.json
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import pandas as pd

from scipy import ndimage

from napari_lbs._core import ExperimentConfig, RefineSettings, find_particles, load_sample_hologram, particle_hologram, refine_particles
from napari_lbs._core.gap._heldout import TileSplit, tile_spectra, whittle_loglik
from napari_lbs._core.physics import propagate


def frame_likelihood(hologram: np.ndarray, tables: dict, config: ExperimentConfig, settings: RefineSettings, *, blur_px: float) -> dict:
    """Each model's summed held-out Whittle gain over the opaque model's, and the tiles it wins (module docstring)."""
    split = TileSplit.of(hologram.shape, grid=4)
    logliks = {}
    for name, table in tables.items():
        rendered = particle_hologram(hologram.shape, table, config, settings=settings, reach_cycles_per_px=1.0)
        if blur_px > 0:
            rendered = ndimage.gaussian_filter(rendered, blur_px)
        spectra = tile_spectra(hologram - rendered, split)
        logliks[name] = whittle_loglik((spectra, spectra), split)
    return {name: {"gain_nats": round(float((ll - logliks["opaque"]).sum()), 1), "tiles_won": int(np.sum(ll > logliks["opaque"]))}
            for name, ll in logliks.items() if name != "opaque"}


def disc_brightness(hologram: np.ndarray, tables: dict, config: ExperimentConfig, settings: RefineSettings, *, blur_px: float) -> dict:
    """The discs at focus: the data's brightness inside each disc less the background's power, against each model's (module docstring)."""
    optics = config.optics
    size = 256

    def crop(row: pd.Series) -> tuple[int, int]:
        top = int(min(max(round(row["y_um"] / optics.pixel_um) - size // 2, 0), hologram.shape[0] - size))
        left = int(min(max(round(row["x_um"] / optics.pixel_um) - size // 2, 0), hologram.shape[1] - size))
        return top, left

    def inside(image: np.ndarray, row: pd.Series, top: int, left: int) -> tuple[float, float]:
        """Mean brightness inside the disc and background power about it, ``image`` being the crop at (top, left)."""
        field = propagate(image.astype(np.complex128), -float(row["z_um"]), wavelength_um=optics.wavelength_um,
                          pixel_um=optics.pixel_um, medium_index=optics.medium_index)
        rows, cols = np.indices(field.shape)
        r = np.hypot(rows - (row["y_um"] / optics.pixel_um - top), cols - (row["x_um"] / optics.pixel_um - left))
        disc = r < 0.3 * 0.5 * float(row["diameter_um"]) / optics.pixel_um
        ring = (r > 30) & (r < 100)
        return float(np.mean(np.abs(field[disc]) ** 2)), float(np.mean(np.abs(field[ring] - 1.0) ** 2))

    measured = []
    for _, row in tables["opaque"].iterrows():
        top, left = crop(row)
        brightness, background = inside(hologram[top:top + size, left:left + size], row, top, left)
        measured.append(brightness - background)
    measured = np.asarray(measured)
    misfit = {}
    for name, table in tables.items():
        predicted = []
        for _, row in table.iterrows():
            top, left = crop(row)
            # the particle alone, rendered on its crop: its coordinates taken to the crop's
            alone = particle_hologram((size, size), pd.DataFrame([row]).assign(x_um=row["x_um"] - left * optics.pixel_um, y_um=row["y_um"] - top * optics.pixel_um),
                                      config, settings=settings, reach_cycles_per_px=1.0)
            if blur_px > 0:
                alone = ndimage.gaussian_filter(alone, blur_px)
            predicted.append(inside(alone, row, top, left)[0])
        misfit[name] = np.abs(measured - np.asarray(predicted))
    return {"measured_median": round(float(np.median(measured)), 4),
            "models": {name: {"median_abs_difference": round(float(np.median(m)), 4), "particles_better_than_opaque": int(np.sum(m < misfit["opaque"]))}
                       for name, m in misfit.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=16)
    parser.add_argument("--grid", type=float, nargs="+", default=[0.06, 0.12, 0.18, 0.22, 0.26, 0.30, 0.36, 0.45])
    parser.add_argument("--starts", type=float, nargs="+", default=[0.05, 0.26, 0.45])
    parser.add_argument("--opaque-kappa", type=float, default=1.0)
    parser.add_argument("--camera-blur-px", type=float, nargs="+", default=[0.0, 1.0])
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    load = [os.getloadavg()[0]]
    hologram = load_sample_hologram().astype(np.float64)
    hologram /= hologram.mean()
    config = ExperimentConfig()
    started = time.perf_counter()
    guesses = pd.DataFrame(find_particles(hologram, config, max_particles=args.particles))
    seconds = {"find": round(time.perf_counter() - started, 1)}
    settings = RefineSettings(workers=1, min_gain=0.0)
    models = {"opaque": {"index_contrast": 0.0, "absorption": args.opaque_kappa}}
    models.update({f"{value:g}": {"index_contrast": value, "absorption": 0.0} for value in args.grid})
    residual, diameters, tables = {}, {}, {}
    for name, fixed in models.items():
        started = time.perf_counter()
        table = refine_particles(hologram, guesses, config, fixed=fixed, settings=settings)
        seconds[name] = round(time.perf_counter() - started, 1)
        residual[name] = table["fit_residual"].to_numpy(np.float64)
        tables[name] = table
        diameters[name] = table["diameter_um"].to_numpy(np.float64)
        print(name, seconds[name], "s", flush=True)
    costs = np.array([residual[name] ** 2 for name in models])
    common = np.all(np.isfinite(costs), axis=0)
    costs = costs[:, common]
    names = list(models)
    transparent = costs[1:]
    best = np.argmin(transparent, axis=0)
    free = {}
    for start in args.starts:
        table = refine_particles(hologram, guesses, config, settings=RefineSettings(workers=1, index_contrast=start))
        kept = table[table["refined"]]
        free[f"{start:g}"] = {"index_contrast_quartiles": np.percentile(kept["index_contrast"], [25, 50, 75]).round(4).tolist(),
                              "median_fit_residual": round(float(kept["fit_residual"].median()), 5), "diameter_median_um": round(float(kept["diameter_um"].median()), 2)}
        print("free fit from", start, free[f"{start:g}"], flush=True)
    # the frame-wide views need every model's fit of the same particles
    common_rows = np.flatnonzero(common)
    fitted = {name: table.iloc[common_rows].reset_index(drop=True) for name, table in tables.items()}
    likelihood, discs = {}, {}
    for blur_px in args.camera_blur_px:
        started = time.perf_counter()
        likelihood[f"{blur_px:g}"] = frame_likelihood(hologram, fitted, config, settings, blur_px=blur_px)
        discs[f"{blur_px:g}"] = disc_brightness(hologram, fitted, config, settings, blur_px=blur_px)
        seconds[f"views_blur_{blur_px:g}"] = round(time.perf_counter() - started, 1)
        print("camera blur", blur_px, likelihood[f"{blur_px:g}"], discs[f"{blur_px:g}"], flush=True)
    load.append(os.getloadavg()[0])
    result = {
        "particles": int(common.sum()),
        "mean_squared_residual": {name: round(float(row.mean()), 6) for name, row in zip(names, costs, strict=True)},
        "best_index_contrast_per_particle": [float(names[1 + b]) for b in best],
        "opaque_minus_best_transparent": {"mean": float((costs[0] - transparent.min(axis=0)).mean()), "per_particle": (costs[0] - transparent.min(axis=0)).round(6).tolist()},
        "diameter_median_um": {name: round(float(np.median(d[common])), 2) for name, d in diameters.items()},
        "free_fit_by_start": free,
        "frame_heldout_gain_over_opaque_by_blur_px": likelihood,
        "disc_at_focus_by_blur_px": discs,
        "seconds": seconds,
        "load_average": load,
    }
    with open(args.out, "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=1)
    print(json.dumps({k: result[k] for k in ("particles", "mean_squared_residual", "free_fit_by_start", "frame_heldout_gain_over_opaque_by_blur_px")}, indent=1))


if __name__ == "__main__":
    main()
