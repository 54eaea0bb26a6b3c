"""Microscopy refinement benchmark: pylorenzmie holograms of single spheres seen through an objective.

Each case is one sphere in water (n_m = 1.33) under 660 nm light, seen at 0.0851 µm pixels
at the sample (e.g. a 7.24 µm camera pitch behind an 85× objective), 10–50 µm from the
focal plane; the radius is one of 0.5, 1, 2, 5 µm (within ±10 %) and the index contrast
``n_p - n_m`` uniform in 0.05–0.3. The hologram is pylorenzmie's (an independent
implementation; its partial-wave sum carried 40 orders further, as `benchmarks/pseudoreal.py`
does), each pixel the mean of 2 × 2 point samples, times an off-centre Gaussian illumination,
recorded by a camera (3000 photo-electrons at the unobstructed light, Poisson noise,
3 counts of read noise, a dark offset of 100 counts; 16-bit counts, or with ``--bits 12`` a
full scale of 4095 at which the brightest focal spots saturate) and divided by a background frame (the
same illumination, its own noise) after the dark offset is taken off — what
``napari-lbs refine --background --dark`` does. The cases are laid side by side in one frame,
each in its own 400² cell (34 µm: a cell holds one sphere's hologram only, and the fits'
neighbour reach, 1.5 patches, stays inside it for patches up to 22 µm), so `refine_particles` fits them in batches as it
fits a real frame.

Starts: the truth moved 0.2 µm laterally (random direction) and ±1.5 µm in depth (random
sign), the diameter scaled by a factor uniform in 0.9–1.1, the index contrast started 0.02
from the truth (random sign): a sample whose material and size are known roughly. The fit is
the ``refine`` command's (`refine_hologram` from these guesses: the frame binned 2 × 2, as its
0.0851 µm pitch is finer than λ/(2n) needs, then `refine_particles` with
``medium_index=1.33, depth_window_um=5`` and otherwise the defaults: patches of 128 binned
pixels, 21.8 µm), then its looks in the residual (``--detection-rounds``; 1 fits the starts
alone). As ``refine`` does, the frame's clipped pixels (five or more at its largest count: a
saturated camera's, at 12 bits) are left out of the fits (`unsaturated_pixels` of the
counts); ``--keep-clipped`` fits through them, the comparison. A particle a look adds, which no start was of, is counted as ``extra`` (each cell
holds one sphere: a false find) and listed, and stays out of the accuracy.

Two sets: ``dev`` (seed 1, where the method is looked at) and ``frozen`` (seed 2), whose
cases are written to ``benchmarks/results/microscopy/frozen_cases.json`` before its first
run and read from there afterwards, so the scored cases never change with the code.

Reported: median |Δd|/d, |Δ(n_p - n_m)|, |Δz|, the fraction within twice the reported
standard deviation per parameter, and seconds per particle of the fit, wall and core (user +
system CPU of the process; one process on this machine's threads; the load average is logged).

    python benchmarks/bench_microscopy.py --set dev --out benchmarks/results/microscopy/dev_16bit_2026-11-27.json
    python benchmarks/bench_microscopy.py --set frozen --out benchmarks/results/microscopy/frozen_16bit_2026-11-27.json
    python benchmarks/bench_microscopy.py --set frozen --bits 12 --out benchmarks/results/microscopy/frozen_2026-11-27.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

WAVELENGTH_UM = 0.66
PIXEL_UM = 0.0851
N_MEDIUM = 1.33
CELL = 400
SUPERSAMPLE = 2
RADII_UM = (0.5, 1.0, 2.0, 5.0)
PER_RADIUS = 5
RESULTS = Path(__file__).resolve().parent / "results" / "microscopy"
FROZEN_CASES = RESULTS / "frozen_cases.json"
SEEDS = {"dev": 1, "frozen": 2}
TARGETS = {"median_rel_diameter": 0.01, "median_index": 0.005, "median_z_um": 0.1, "coverage": 0.9, "seconds_per_particle": 0.2}


def draw_cases(seed: int) -> list[dict]:
    """The spheres and their starting guesses (µm; the cell's own coordinates)."""
    rng = np.random.default_rng(seed)
    cases = []
    for radius in RADII_UM:
        for _ in range(PER_RADIUS):
            diameter = 2.0 * radius * rng.uniform(0.9, 1.1)
            contrast = rng.uniform(0.05, 0.3)
            z = rng.uniform(10.0, 50.0)
            x, y = (CELL / 2 + rng.uniform(-0.5, 0.5, 2)) * PIXEL_UM
            angle = rng.uniform(0.0, 2.0 * np.pi)
            cases.append({"x_um": x, "y_um": y, "z_um": z, "diameter_um": diameter, "index_contrast": contrast,
                          "start": {"x_um": x + 0.2 * np.cos(angle), "y_um": y + 0.2 * np.sin(angle), "z_um": z + 1.5 * rng.choice([-1.0, 1.0]),
                                    "diameter_um": diameter * rng.uniform(0.9, 1.1), "index_contrast": contrast + 0.02 * rng.choice([-1.0, 1.0])}})
    return cases


def cases_of(which: str) -> list[dict]:
    if which == "dev":
        return draw_cases(SEEDS["dev"])
    if not FROZEN_CASES.is_file():  # written once, before the frozen set's first run
        FROZEN_CASES.parent.mkdir(parents=True, exist_ok=True)
        FROZEN_CASES.write_text(json.dumps({"seed": SEEDS["frozen"], "cases": draw_cases(SEEDS["frozen"])}, indent=1) + "\n")
    return json.loads(FROZEN_CASES.read_text())["cases"]


def pylorenzmie_intensity(spheres: list[dict], shape: tuple[int, int], *, pixel_um: float = PIXEL_UM) -> np.ndarray:
    """pylorenzmie's hologram of spheres in water on a ``shape`` grid, each pixel the mean of SUPERSAMPLE² points.

    Parameters
    ----------
    spheres : list of dict
        Each with ``x_um, y_um`` (pixel ``(r, c)`` at ``(c, r) × pixel_um``), ``z_um`` (from
        the focal plane, in water), ``diameter_um`` and ``index_contrast``; their scattered
        fields add coherently.
    shape : (rows, cols)
    pixel_um : float
        The pitch at the sample (µm).

    Returns
    -------
    (rows, cols) array
        Intensity, unobstructed light 1.
    """
    from pylorenzmie.theory import LorenzMie, Sphere
    from pylorenzmie.theory.Instrument import Instrument

    s = SUPERSAMPLE
    rows, cols = shape
    yy, xx = np.meshgrid((np.arange(rows * s) + 0.5) / s - 0.5, (np.arange(cols * s) + 0.5) / s - 0.5, indexing="ij")  # sub-pixel centres (pixels)
    points = np.stack([xx.ravel(), yy.ravel()])
    instrument = Instrument(wavelength=WAVELENGTH_UM, magnification=pixel_um, n_m=N_MEDIUM)
    particles = [Sphere(a_p=sphere["diameter_um"] / 2 + 1e-6, n_p=N_MEDIUM + sphere["index_contrast"], k_p=0.0,
                        x_p=sphere["x_um"] / pixel_um, y_p=sphere["y_um"] / pixel_um, z_p=sphere["z_um"] / pixel_um) for sphere in spheres]
    stock = Sphere.wiscombe_yang
    Sphere.wiscombe_yang = staticmethod(lambda x, m: stock(x, m) + 40)
    try:
        hologram = LorenzMie(coordinates=points, particle=particles, instrument=instrument).hologram()
    finally:
        Sphere.wiscombe_yang = staticmethod(stock)
    return np.asarray(hologram, dtype=np.float64).reshape(rows, s, cols, s).mean(axis=(1, 3))


def camera_frame(intensity: np.ndarray, rng: np.random.Generator, *, bits: int = 16, raw: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``intensity`` under an off-centre Gaussian illumination, recorded with a background frame and normalised (with ``raw``, and the frame's counts).

    The camera: 3000 photo-electrons at the unobstructed light, Poisson noise, a dark offset
    of 100 counts with 3 counts of read noise, ``bits``-bit counts; the background frame is
    the illumination alone, with its own noise. Returns ``(hologram - dark) / (background -
    dark)``, as ``napari-lbs refine --background --dark`` sees it.
    """
    yy, xx = np.mgrid[: intensity.shape[0], : intensity.shape[1]]
    beam = np.exp(-((yy - 0.45 * intensity.shape[0]) ** 2 + (xx - 0.55 * intensity.shape[1]) ** 2) / (2 * (0.8 * intensity.shape[0]) ** 2))

    def camera(light: np.ndarray) -> np.ndarray:
        counts = rng.poisson(3000.0 * light) + rng.normal(100.0, 3.0, light.shape)
        return np.clip(np.round(counts), 0, 2**bits - 1)

    hologram, background = camera(intensity * beam), camera(beam)
    normalised = (hologram - 100.0) / (background - 100.0)
    return (normalised, hologram) if raw else normalised


def mosaic(cases: list[dict], rng: np.random.Generator, *, bits: int = 16) -> tuple[np.ndarray, np.ndarray, int]:
    """The normalised frame of every case's cell, as `refine --background --dark` sees it, its counts (`camera_frame`), and the cells per row."""
    per_row = int(np.ceil(np.sqrt(len(cases))))
    rows = -(-len(cases) // per_row)
    intensity = np.ones((rows * CELL, per_row * CELL))
    for i, case in enumerate(cases):
        r, c = divmod(i, per_row)
        intensity[r * CELL:(r + 1) * CELL, c * CELL:(c + 1) * CELL] = pylorenzmie_intensity([case], (CELL, CELL))
    return *camera_frame(intensity, rng, bits=bits, raw=True), per_row


def run(which: str, *, patch_um: float | None = None, bits: int = 16, detection_rounds: int | None = None, keep_clipped: bool = False) -> dict:
    import pandas as pd
    import torch

    from napari_lbs._core import ExperimentConfig
    from napari_lbs._core.pipeline import DETECTION_ROUNDS, refine_hologram
    from napari_lbs._core.refine import unsaturated_pixels

    detection_rounds = DETECTION_ROUNDS if detection_rounds is None else detection_rounds

    cases = cases_of(which)
    load_before = os.getloadavg()
    started = time.perf_counter()
    frame, counts, per_row = mosaic(cases, np.random.default_rng(SEEDS[which] + 100), bits=bits)
    render_s = time.perf_counter() - started
    offsets = [(divmod(i, per_row)[1] * CELL * PIXEL_UM, divmod(i, per_row)[0] * CELL * PIXEL_UM) for i in range(len(cases))]
    guesses = pd.DataFrame([{name: case["start"][name] + (dx if name == "x_um" else dy if name == "y_um" else 0.0)
                             for name in ("x_um", "y_um", "z_um", "diameter_um", "index_contrast")} for case, (dx, dy) in zip(cases, offsets, strict=True)])
    guesses["case"] = np.arange(len(cases))
    config = ExperimentConfig.from_dict({"optics": {"wavelength_um": WAVELENGTH_UM, "pixel_um": PIXEL_UM, "medium_index": N_MEDIUM},
                                         "volume": {"z_min_um": 5.0, "z_max_um": 60.0, "z_step_um": 0.5},
                                         "particles": {"diameter_min_um": 0.9, "diameter_max_um": 11.0, "layer_step_um": 5.0}})
    started, cpu = time.perf_counter(), time.process_time()
    # as `refine` does: a saturated camera's clipped pixels (at 12 bits) are left out of the fits
    valid = None if keep_clipped else unsaturated_pixels(counts)
    fitted, record = refine_hologram(frame, config, guesses=guesses, medium_index=N_MEDIUM, depth_window_um=5.0, patch_um=patch_um,
                                     detection_rounds=detection_rounds, valid=valid)
    fit_s, fit_core_s = time.perf_counter() - started, time.process_time() - cpu
    table = pd.DataFrame(fitted)
    extra = table[table["case"].isna()]
    rows = []
    for _, fit in table.dropna(subset=["case"]).iterrows():
        case = cases[int(fit["case"])]
        rows.append({"radius_class_um": RADII_UM[int(fit["case"]) // PER_RADIUS], "diameter_um": case["diameter_um"], "index_contrast": case["index_contrast"],
                     "z_um": case["z_um"], "d_err": fit["diameter_um"] - case["diameter_um"], "n_err": fit["index_contrast"] - case["index_contrast"],
                     "z_err": fit["z_um"] - case["z_um"], "d_sigma": fit["diameter_err_um"], "n_sigma": fit["index_err"], "z_sigma": fit["z_err_um"],
                     "refined": bool(fit["refined"]), "fit_residual": fit["fit_residual"]})
    frame_rows = pd.DataFrame(rows)
    within = lambda err, sigma: float(np.mean(np.abs(frame_rows[err]) <= 2.0 * frame_rows[sigma])) if len(frame_rows) else float("nan")
    summary = {
        "kept": len(frame_rows), "cases": len(cases), "refined": int(frame_rows["refined"].sum()) if len(frame_rows) else 0, "extra": len(extra),
        "median_rel_diameter": float(np.median(np.abs(frame_rows["d_err"]) / frame_rows["diameter_um"])),
        "median_index": float(np.median(np.abs(frame_rows["n_err"]))), "median_z_um": float(np.median(np.abs(frame_rows["z_err"]))),
        "coverage": {"z": within("z_err", "z_sigma"), "diameter": within("d_err", "d_sigma"), "index": within("n_err", "n_sigma")},
        "seconds_per_particle": fit_s / len(cases), "core_seconds_per_particle": fit_core_s / len(cases),
    }
    per_class = {str(r): {"median_rel_diameter": float(np.median(np.abs(g["d_err"]) / g["diameter_um"])), "median_index": float(np.median(np.abs(g["n_err"]))),
                          "median_z_um": float(np.median(np.abs(g["z_err"])))} for r, g in frame_rows.groupby("radius_class_um")}
    extra_rows = extra[["x_um", "y_um", "z_um", "diameter_um", "index_contrast", "fit_residual", "refined"]].to_dict(orient="records")
    return {"set": which, "summary": summary, "per_radius": per_class, "targets": TARGETS, "particles": rows, "extra": extra_rows, "render_s": render_s, "fit_s": fit_s,
            "threads": torch.get_num_threads(), "load_before": load_before, "load_after": os.getloadavg(),
            "setup": {"wavelength_um": WAVELENGTH_UM, "pixel_um": PIXEL_UM, "n_medium": N_MEDIUM, "cell_px": CELL, "supersample": SUPERSAMPLE, "bits": bits,
                      "radii_um": RADII_UM, "per_radius": PER_RADIUS, "detection_rounds": detection_rounds, "fit": record,
                      "pixels_left_out": 0 if valid is None else int(np.count_nonzero(~valid)), "keep_clipped": keep_clipped}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", choices=("dev", "frozen"), default="dev")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--patch-um", type=float, help="largest patch edge (µm; default the refine command's)")
    parser.add_argument("--bits", type=int, choices=(12, 16), default=16, help="the camera's counts (12: the brightest focal spots saturate)")
    parser.add_argument("--detection-rounds", type=int, help="looks for particles, the starts' fit first (default the refine command's; 1: the starts alone)")
    parser.add_argument("--keep-clipped", action="store_true", help="fit through the saturated camera's clipped pixels too (the comparison for leaving them out)")
    args = parser.parse_args()
    result = run(args.set, patch_um=args.patch_um, bits=args.bits, detection_rounds=args.detection_rounds, keep_clipped=args.keep_clipped)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(json.dumps({"summary": result["summary"], "per_radius": result["per_radius"], "load": [result["load_before"], result["load_after"]]}, indent=1))


if __name__ == "__main__":
    main()
