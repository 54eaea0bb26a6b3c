"""Refinement benchmark: Lorenz–Mie scenes made by pylorenzmie, refined from perturbed truth.

A hologram of polystyrene spheres (n = 1.59) in water, 16–36 µm, at air-equivalent depths
1900–4700 µm (the default config's convention) is made by pylorenzmie (an independent
implementation: `benchmarks/pseudoreal.py`, pixel-integrated, 8-bit camera with photon
noise and an off-centre beam envelope). Its partial-wave sum is carried 40 orders further
than pylorenzmie 3.4.0 does by default: at its own truncation the coefficients of
non-absorbing spheres of this size are wrong (tests/test_refine.py). Each particle's
starting guess is the truth moved by ~N(0, 1.5) µm laterally, ~N(0, 15) µm in depth and
~N(0, 1.5) µm in diameter, with the index contrast started at polystyrene's 0.26.

Reported: median |Δz|, |Δd|, |Δ(n_p - n_m)| of the refined particles, the fraction (and
count) whose error is within twice the reported uncertainty, per parameter, and seconds per
particle, wall and core (user + system CPU of the process); beside them, in the same run:
pylorenzmie's own fit (`Feature.optimize`, Levenberg–Marquardt, the same patches, started
at the same guesses) on a few particles, and, with ``--old-src``, another version of
napari-lbs (e.g. ``git archive <commit> src | tar -x -C /tmp/old``) on the first
``--old-particles`` guesses of the same scene, run in a subprocess, with the current code
on the same subset. The load average is logged before and after.

    python benchmarks/bench_refine.py --particles 30 --size 1024 --threads 2 --old-src /tmp/old/src --out benchmarks/results/refine/fit.json
    python benchmarks/bench_refine.py --forward --out benchmarks/results/refine/forward.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

WATER = 1.33
CONTRAST = 1.59 - WATER


def converge_pylorenzmie() -> None:
    """Carry pylorenzmie's partial-wave sums 40 orders further (its default truncation is too short for non-absorbing spheres)."""
    from pylorenzmie.theory import Sphere

    stock = Sphere.wiscombe_yang
    Sphere.wiscombe_yang = staticmethod(lambda x, m: stock(x, m) + 40)


def scene(count: int, size: int, seed: int):
    import pandas as pd
    import pseudoreal

    rng = np.random.default_rng(seed)
    margin = 40 * pseudoreal.PIXEL_UM
    extent = (size - 1) * pseudoreal.PIXEL_UM
    truth = pd.DataFrame({
        "x_um": rng.uniform(margin, extent - margin, count),
        "y_um": rng.uniform(margin, extent - margin, count),
        "z_um": rng.uniform(1900.0, 4700.0, count),
        "diameter_um": rng.uniform(16.0, 36.0, count),
    })
    intensity = pseudoreal.mie_intensity((size, size), truth.x_um, truth.y_um, truth.z_um, truth.diameter_um)
    frame = pseudoreal.camera(intensity, rng=rng).astype(np.float64)
    start = truth.copy()
    start["x_um"] += rng.normal(0.0, 1.5, count)
    start["y_um"] += rng.normal(0.0, 1.5, count)
    start["z_um"] += rng.normal(0.0, 15.0, count)
    start["diameter_um"] += rng.normal(0.0, 1.5, count)
    return frame / frame.mean(), truth, start


def pylorenzmie_fit(hologram: np.ndarray, start, *, pixel_um: float, wavelength_um: float, patch_px: int) -> tuple[float, dict]:
    """pylorenzmie's own fit of one patch: seconds and the fitted values (µm, air-equivalent depth)."""
    from pylorenzmie.analysis import Feature
    from pylorenzmie.analysis.Hologram import Hologram

    col, row = round(start.x_um / pixel_um), round(start.y_um / pixel_um)
    half = patch_px // 2
    top, left = max(row - half, 0), max(col - half, 0)
    crop = hologram[top : top + patch_px, left : left + patch_px]
    feature = Feature(Hologram(data=crop, corner=(left, top)))
    instrument = feature.model.instrument
    instrument.wavelength, instrument.magnification, instrument.n_m = wavelength_um, pixel_um, WATER
    particle = feature.particle
    particle.x_p, particle.y_p = start.x_um / pixel_um, start.y_um / pixel_um
    particle.z_p = start.z_um * WATER / pixel_um
    particle.a_p, particle.n_p, particle.k_p = start.diameter_um / 2, WATER + CONTRAST, 0.0
    feature.optimizer.variables = ["x_p", "y_p", "z_p", "a_p", "n_p"]
    feature.model.coordinates = feature.flat_coordinates
    began = time.perf_counter()
    result = feature.optimize()
    seconds = time.perf_counter() - began
    return seconds, {"z_um": float(result["z_p"]) * pixel_um / WATER, "diameter_um": 2 * float(result["a_p"]), "index_contrast": float(result["n_p"]) - WATER}


def forward_check(size: int = 160) -> list[dict]:
    """Our Lorenz–Mie hologram against pylorenzmie's (point-sampled, the same sphere) over the size and depth range, with both timings."""
    import torch
    from pylorenzmie.theory import LorenzMie, Sphere
    from pylorenzmie.theory.Instrument import Instrument

    from napari_lbs._core.physics._lorenz_mie import sphere_holograms

    rows = []
    pixel, wavelength = 2.2, 0.66
    for diameter in (16.0, 26.0, 36.0):
        for z_air in (1900.0, 3300.0, 4700.0):
            z = z_air * WATER
            centre = (size / 2 + 0.3, size / 2 - 0.2)
            instrument = Instrument(wavelength=wavelength, magnification=pixel, n_m=WATER)
            sphere = Sphere(a_p=diameter / 2, n_p=WATER + CONTRAST, k_p=0.0, x_p=centre[0], y_p=centre[1], z_p=z / pixel)
            model = LorenzMie(coordinates=LorenzMie.meshgrid((size, size)), particle=sphere, instrument=instrument)
            model.hologram()  # compile
            began = time.perf_counter()
            reference = model.hologram()
            theirs = time.perf_counter() - began
            grid_rows, grid_cols = np.mgrid[0:size, 0:size].astype(float)
            dx = torch.tensor(((grid_cols - centre[0]) * pixel).ravel())[None]
            dy = torch.tensor(((grid_rows - centre[1]) * pixel).ravel())[None]
            began = time.perf_counter()
            ours = sphere_holograms(dx, dy, *(torch.tensor([v]) for v in (z, diameter, CONTRAST, 0.0)), wavelength_um=wavelength, medium_index=WATER)[0].numpy()
            mine = time.perf_counter() - began
            relative = float(np.sqrt(np.mean((ours - reference) ** 2)) / np.sqrt(np.mean((reference - 1.0) ** 2)))
            rows.append({"diameter_um": diameter, "z_air_um": z_air, "relative_rms": relative, "seconds_ours": mine, "seconds_pylorenzmie": theirs})
            print(f"  d {diameter:.0f} µm, z {z_air:.0f} µm: relative rms {relative:.1e}; {mine:.3f} s vs pylorenzmie {theirs:.3f} s", flush=True)
    return rows


def _core_seconds() -> float:
    """CPU seconds of this process and of its finished worker processes."""
    import resource

    return sum(u.ru_utime + u.ru_stime for u in (resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)))


def timed_refine(hologram, start, *, threads: int, workers: int = 1) -> tuple[object, float, float]:
    """``refine_particles`` with the default settings (and ``workers`` processes): (table, wall seconds, core seconds)."""
    import torch

    from napari_lbs._core import RefineSettings, load_config, refine_particles

    torch.set_num_threads(threads)
    wall, core = time.perf_counter(), _core_seconds()
    refined = refine_particles(hologram, start, load_config(), settings=RefineSettings(workers=workers))
    return refined, time.perf_counter() - wall, _core_seconds() - core


def scores(refined, truth) -> dict:
    """Medians over the refined particles and 2σ coverage over all (a fit left unrefined counts as outside) against the truth, matched by order."""
    dz = refined.z_um.to_numpy() - truth.z_um.to_numpy()
    dd = refined.diameter_um.to_numpy() - truth.diameter_um.to_numpy()
    dn = refined.index_contrast.to_numpy() - CONTRAST
    ok = refined.refined.to_numpy(bool)
    inside = {"z": np.abs(dz) <= 2 * refined.z_err_um.to_numpy(), "diameter": np.abs(dd) <= 2 * refined.diameter_err_um.to_numpy(),
              "index": np.abs(dn) <= 2 * refined.index_err.to_numpy()}
    return {
        "refined": f"{int(ok.sum())}/{ok.size}",
        "median_abs_dz_um": float(np.median(np.abs(dz[ok]))), "median_abs_dd_um": float(np.median(np.abs(dd[ok]))), "median_abs_dn": float(np.median(np.abs(dn[ok]))),
        "within_2sigma": {k: float(np.mean(v)) for k, v in inside.items()}, "within_2sigma_count": {k: f"{int(v.sum())}/{v.size}" for k, v in inside.items()},
        "index_within_0.01": float(np.mean(np.abs(dn) <= 0.01)),
        "rows": [{"truth_z_um": float(t.z_um), "truth_d_um": float(t.diameter_um), "dz_um": float(a), "dd_um": float(b), "dn": float(c),
                  "z_err_um": float(e), "diameter_err_um": float(f), "index_err": float(g)}
                 for t, a, b, c, e, f, g in zip(truth.itertuples(), dz, dd, dn, refined.z_err_um, refined.diameter_err_um, refined.index_err, strict=True)],
    }


def other_version(source: Path, hologram, start, *, threads: int) -> dict:
    """The refinement of another napari-lbs source tree on the same hologram and guesses, in a subprocess: its table and timings."""
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        np.save(folder / "hologram.npy", hologram)
        start.to_csv(folder / "start.csv", index=False)
        code = (
            "import sys, json, numpy as np, pandas as pd; sys.path.insert(0, sys.argv[1]); import bench_refine as b;"
            "t, w, c = b.timed_refine(np.load(sys.argv[2] + '/hologram.npy'), pd.read_csv(sys.argv[2] + '/start.csv'), threads=int(sys.argv[3]));"
            "t.to_csv(sys.argv[2] + '/out.csv', index=False); import napari_lbs; print(json.dumps({'wall': w, 'core': c, 'module': napari_lbs.__file__}))"
        )
        env = {**os.environ, "PYTHONPATH": str(source)}
        done = subprocess.run([sys.executable, "-c", code, str(Path(__file__).resolve().parent), str(folder), str(threads)], env=env, check=True,
                              capture_output=True, text=True)
        import pandas as pd

        timing = json.loads(done.stdout.strip().splitlines()[-1])
        return {"table": pd.read_csv(folder / "out.csv"), **timing}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--workers", type=int, default=1, help="refinement processes (RefineSettings.workers; each with one thread)")
    parser.add_argument("--pylorenzmie", type=int, default=3, help="particles also fitted by pylorenzmie (0: none)")
    parser.add_argument("--old-src", type=Path, help="another napari-lbs source tree (its src folder) to time on a subset of the same scene")
    parser.add_argument("--old-particles", type=int, default=6, help="guesses given to --old-src (and to the current code again, for the same subset)")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--forward", action="store_true", help="only compare the forward model with pylorenzmie (160² holograms over the size and depth range)")
    args = parser.parse_args(argv)

    import torch

    from napari_lbs._core import RefineSettings, load_config

    torch.set_num_threads(args.threads)
    converge_pylorenzmie()
    if args.forward:
        rows = forward_check()
        text = json.dumps({"threads": args.threads, "forward": rows, "max_relative_rms": max(r["relative_rms"] for r in rows)}, indent=1)
        print(text)
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text + "\n")
        return 0
    config = load_config()
    began = time.perf_counter()
    hologram, truth, start = scene(args.particles, args.size, args.seed)
    print(f"scene: {args.particles} spheres on {args.size}² in {time.perf_counter() - began:.1f} s; load average {os.getloadavg()}", flush=True)
    report = {"particles": args.particles, "size": args.size, "seed": args.seed, "threads": args.threads, "workers": args.workers,
              "load_average_before": os.getloadavg()}
    refined, wall, core = timed_refine(hologram, start, threads=args.threads, workers=args.workers)
    kept = refined.index.size
    report.update({"kept": int(kept), "seconds": wall, "core_seconds": core, "seconds_per_particle": wall / args.particles,
                   "core_seconds_per_particle": core / args.particles})
    print(f"  refined {kept}/{args.particles} in {wall:.1f} s ({core:.1f} core-s)", flush=True)
    if kept == len(truth):
        report.update(scores(refined, truth))
    if args.old_src:
        subset = start.iloc[: args.old_particles].reset_index(drop=True)
        old = other_version(args.old_src, hologram, subset, threads=args.threads)
        mine, wall_s, core_s = timed_refine(hologram, subset, threads=args.threads)
        part = truth.iloc[: args.old_particles].reset_index(drop=True)
        report["same_subset"] = {
            "particles": args.old_particles, "old_src": str(args.old_src), "old_module": old["module"],
            "old": {"seconds_per_particle": old["wall"] / args.old_particles, "core_seconds_per_particle": old["core"] / args.old_particles,
                    **({k: v for k, v in scores(old["table"], part).items() if k != "rows"} if len(old["table"]) == len(part) else {})},
            "current": {"seconds_per_particle": wall_s / args.old_particles, "core_seconds_per_particle": core_s / args.old_particles,
                        **({k: v for k, v in scores(mine, part).items() if k != "rows"} if len(mine) == len(part) else {})},
        }
        report["same_subset"]["old_over_current_core"] = old["core"] / core_s
        report["same_subset"]["old_over_current_wall"] = old["wall"] / wall_s
        print(f"  same {args.old_particles} guesses: old {old['wall']:.1f} s ({old['core']:.1f} core-s), current {wall_s:.1f} s ({core_s:.1f} core-s)", flush=True)
    if args.pylorenzmie:
        fits = []
        for i in range(min(args.pylorenzmie, args.particles)):
            core_began = time.process_time()
            spent, values = pylorenzmie_fit(hologram, start.iloc[i], pixel_um=config.optics.pixel_um, wavelength_um=config.optics.wavelength_um,
                                            patch_px=RefineSettings().patch_px)
            fits.append({"seconds": spent, "core_seconds": time.process_time() - core_began, "dz_um": values["z_um"] - float(truth.z_um[i]),
                         "dd_um": values["diameter_um"] - float(truth.diameter_um[i]), "dn": values["index_contrast"] - CONTRAST})
            print(f"  pylorenzmie particle {i}: {spent:.1f} s", flush=True)
        per = float(np.mean([f["seconds"] for f in fits]))
        per_core = float(np.mean([f["core_seconds"] for f in fits]))
        report["pylorenzmie"] = {"fits": fits, "seconds_per_particle": per, "core_seconds_per_particle": per_core,
                                 "ours_over_pylorenzmie": report["seconds_per_particle"] / per,
                                 "ours_over_pylorenzmie_core": report["core_seconds_per_particle"] / per_core}
    report["load_average_after"] = os.getloadavg()
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        temporary = args.out.with_suffix(".tmp")
        temporary.write_text(text + "\n")
        temporary.replace(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
