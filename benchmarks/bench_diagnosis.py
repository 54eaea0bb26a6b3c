"""Gap-diagnosis benchmarks (issues 6 and 13): withheld-effect suites, independent forward model, real hologram.

Sub-commands:

``suite [--tile PX] [--tiles N] [--particles P] [--evaluations E] [--controls C] [--jobs J] [--cases I ...]``
    Injection and recovery: for every effect id, pseudo-experiments made with that effect on
    at its weak and its strong setting (`Effect.injections`, at `Effect.injection_density`
    times P particles per tile) on top of a known baseline (contrast 0.8, read noise 0.04,
    gamma 1.2), diagnosed by a simulator that has to find it; plus C controls with nothing
    withheld, the last at the densest injection's density; J cases at once (processes); only the
    cases of indices I, in that order, if given (0-17: the effects, weak then strong, in catalog
    order; then the controls). Prints
    one JSON line per case, then top-1 accuracy of the verdict, the median shrink of a
    correctly named effect, the controls' false alarms and the mean time per diagnosis.
``independent [--index N] [--supersample S] ...``
    Pseudo-experiments from Lorenz–Mie theory (pylorenzmie, a model the diagnosis never uses):
    transparent spheres of refractive index N in water (1.59: polystyrene; 1.37: cell-like),
    the intensity averaged over S × S points per pixel (a pixel integrates over its area).
    The verdict should be ``particle_phase`` wherever the sphere's refracted light stays within
    the sensor's bandwidth.
``mie [--cases I ...] [--seed S] [--keep DIR] [--known-effect ID:NAME=VALUE,...]``
    A second withheld-effect suite the diagnosis was not built on (issue 13): 512² holograms of
    Lorenz–Mie polystyrene spheres (`pseudoreal.mie_intensity`), an 8-bit camera and each
    withheld effect written here, independently of `_effects`, with other parameterisations
    (the design comment above `MIE_EFFECTS`, fixed before the first run); diagnosed as the CLI does (`diagnose_hologram`
    on the uint8 image, default settings). Prints one JSON line per case, then top-1, the
    false-alarm rate and their 95 % Wilson intervals, and the same for the first half's verdict
    alone (where the diagnosis cross-fits: the verdict without cross-fitting). ``--seed`` draws other scenes of the same
    design (default 2026, the suite's; the method was developed on seed 7, docs/diagnosis.md).
``absorbing [--cases I ...] [--seed S] [--keep DIR]``
    The third withheld-effect suite (issue 13, fixed 2026-11-23 before its first run; the design
    comment above `ABSORBING_DESIGN`): Lorenz–Mie spheres that absorb (what the seed's simulator
    assumes) as the scene, so that transparent spheres and a coarse bit depth can be withheld
    too; 512² and 1024² holograms; effects parameterised independently of `_effects` and of the
    ``mie`` suite. ``--keep`` pickles each case's fits (`Diagnosis.halves`) so that the verdict
    rule can be re-scored (`rescore`) without refitting. Development scenes: ``--seed 8``.
``signature CASE [--size PX] [--scenes N] [--top K]``
    Which summaries a withheld effect of the third suite moves, and by how much: N scenes of
    `_absorbing_scene` drawn twice with the same spheres and camera noise, once plain and once
    with CASE (an `ABSORBING_DESIGN` case), cut into the tiles `diagnose_hologram` would cut;
    prints the K largest paired differences of each summary in units of the plain tiles'
    tile-to-tile spread (what a held-out z divides by), beside the same for the baseline's
    own noise (read noise doubled), so that an effect the fitted noise can mimic shows.
``rescore DIR``
    The verdicts of kept cases (``absorbing`` or ``mie --keep DIR``) scored again with the current code.
``threads [--repeats N]``
    One fit evaluation's simulated summaries at 1024² (8 tiles of 256²) on the summary thread
    pool against one thread, interleaved in one run: median seconds, speed-up, identical results.
``real``
    The seed's real 1024² hologram: the full diagnosis with default settings, timed (target
    <= 3 min on 2 idle cores), report written to docs/figures/diagnosis-real/.

Run: python benchmarks/bench_diagnosis.py suite|independent|mie|absorbing|rescore|signature|threads|real
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy import ndimage

from napari_lbs._core import (
    EFFECTS,
    DiagnosisSettings,
    ExperimentConfig,
    diagnose_hologram,
    load_config,
    load_sample_hologram,
    parse_effects,
    random_particle_field,
    write_report,
)
from napari_lbs._core._effects import OPTICAL_EFFECTS, optical_hologram, sensor_image
from napari_lbs._core._gap import diagnose_tiles

CONFIG = ExperimentConfig()
TRUE_BASELINE = {"contrast": 0.8, "sigma": 0.04, "gamma": 1.2}

# The second suite's design, fixed on 2026-11-22 before its first run. Every case: a 512²
# hologram of MIE_SPHERES polystyrene spheres (20–30 µm, 1900–4700 µm air-equivalent depth,
# seeded by the case index), the camera `mie_camera` (mean MIE_LEVEL counts, Gaussian read
# noise MIE_READ_NOISE counts, rounding, 8 bits) and at most one withheld effect, each
# parameterised differently from `_effects`:
#   illumination       cos⁴ vignetting about an off-centre point, 40 % lost at the far corner
#                      (`_effects`: a Gaussian beam envelope)
#   shot_noise         Poisson photon counts, MIE_PHOTONS photons at the mean level
#   sensor_blur        binomial [1 4 6 4 1]/16 kernel on the intensity, each axis (σ = 1 px;
#                      `_effects`: a Gaussian on the recorded image)
#   coherence          a disc source of angular radius 2 mrad: 7 illumination angles (centre
#                      and a ring at 2/3 of the radius), each shifting a sphere's hologram by
#                      z·θ, intensities averaged (`_effects`: a Gaussian blur of the scattered field)
#   parasitic_fringes  a tilted-window fringe, 6 % amplitude, 11 px period at 0.4 rad, with a
#                      quadratic chirp (curvature radius 2 m; `_effects`: a straight fringe)
#   spherical_wave     a point source 20 mm before the sensor: each sphere magnified by
#                      M = L / (L − z) in position, size and depth (`_effects`: per layer)
#   control ×5         nothing withheld (expected verdict: null)
# Left out, with the reason: particle_phase (every scene here is transparent Mie spheres
# already), multiple_scattering (Mie fields are superposed, single scattering), quantization
# (the 8-bit depth is known from the file).
MIE_EFFECTS = ("illumination", "shot_noise", "sensor_blur", "coherence", "parasitic_fringes", "spherical_wave")
MIE_CONTROLS = 5
MIE_SIZE = 512
MIE_SPHERES = 25  # the real hologram's density: about 100 spheres in 1024²
MIE_LEVEL = 150.0  # counts at unobstructed light
MIE_READ_NOISE = 1.5  # counts
MIE_PHOTONS = 200.0


def pseudo_tiles(effects: dict, *, tile: int, count: int, particles: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng([seed, 5])
    tiles = []
    for _ in range(count):
        field = random_particle_field((tile, tile), count=particles, diameter_min_um=20, diameter_max_um=30, layers_um=CONFIG.layer_depths_um(), pixel_um=2.2, seed=rng)
        intensity = optical_hologram(field, {k: v for k, v in effects.items() if k in OPTICAL_EFFECTS}, wavelength_um=0.66)
        sensor = {k: v for k, v in effects.items() if k not in OPTICAL_EFFECTS}
        tiles.append(sensor_image(intensity, TRUE_BASELINE, sensor, noise=rng.standard_normal((tile, tile)).astype(np.float32)))
    return tiles


def _suite_case(case: tuple) -> dict:
    """Diagnose one withheld-effect case: (index, effect id or None, strength, density, options)."""
    index, effect_id, strength, density, (tile, tiles, particles, evaluations) = case
    effects = {} if effect_id is None else {effect_id: EFFECTS[effect_id].injections[strength]}
    case_particles = round(particles * density)
    case_start = time.perf_counter()
    settings = DiagnosisSettings(sim_tiles=6, evaluations=evaluations)
    report = diagnose_tiles(pseudo_tiles(effects, tile=tile, count=tiles, particles=case_particles, seed=100 + index), CONFIG, settings=settings, particles_per_tile=case_particles).report
    verdict = report["verdict"]
    own = next((e for e in report["effects"] if e["id"] == effect_id), None)
    return {
        "withheld": effect_id,
        "strength": ["weak", "strong"][strength] if effect_id else "control",
        "particles_per_tile": case_particles,
        "baseline_gap": round(report["gap"]["baseline"], 2),
        "verdict": verdict["id"],
        "correct": verdict["id"] == effect_id,
        "per_half": verdict.get("per_half"),
        "reason": verdict["reason"],
        "shrink_of_withheld": round(own["shrink"], 2) if own else None,
        "ablated_gap_of_withheld": round(own["gap_ablated"], 2) if own and "gap_ablated" in own else None,
        "confirmed": bool(own and own["confirmed"]),
        "seconds": round(time.perf_counter() - case_start, 1),
    }


def suite(tile: int, tiles: int, particles: int, evaluations: int, controls: int, jobs: int, indices: list[int] | None = None) -> None:
    # (effect, strength, density); the last control sits at the densest injection's density
    densest = max(density for effect in EFFECTS.values() for density in effect.injection_density)
    cases = [(effect_id, strength, EFFECTS[effect_id].injection_density[strength]) for effect_id in EFFECTS for strength in (0, 1)]
    cases += [(None, c, densest if c == controls - 1 else 1.0) for c in range(controls)]
    options = (tile, tiles, particles, evaluations)
    start = time.perf_counter()
    rows = []
    # each case is seeded by its index, so the rows do not depend on how many run at once
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        chosen = indices if indices is not None else range(len(cases))
        for row in pool.map(_suite_case, [(index, *cases[index], options) for index in chosen]):
            rows.append(row)
            print(json.dumps(row), flush=True)
    injected = [r for r in rows if r["withheld"]]
    controls_rows = [r for r in rows if not r["withheld"]]
    top1 = np.mean([r["correct"] for r in injected])
    shrinks = [r["shrink_of_withheld"] for r in injected if r["correct"]]
    print(f"top-1 {100 * top1:.0f} % over {len(injected)} withheld-effect cases (target >= 90 %); "
          f"median shrink of the named effect {np.median(shrinks) if shrinks else float('nan'):.2f} (target >= 0.5); "
          f"false alarms on controls {sum(not r['correct'] for r in controls_rows)}/{len(controls_rows)}; "
          f"{(time.perf_counter() - start) / len(rows) * jobs:.1f} s per diagnosis ({tiles} tiles of {tile}², {jobs} at once)")
    print(_single_split_line(rows))


def independent(tile: int, tiles: int, particles: int, evaluations: int, sphere_index: float, supersample: int) -> None:
    # pylorenzmie is a test/benchmark extra: the diagnosis itself never uses it
    from pylorenzmie.theory import LorenzMie, Sphere
    from pylorenzmie.theory.Instrument import Instrument

    config = ExperimentConfig.from_dict({"optics": {"wavelength_um": 0.66, "pixel_um": 2.2, "medium_index": 1.33}})
    rng = np.random.default_rng(42)
    instrument = Instrument(wavelength=0.66, magnification=2.2, n_m=1.33)
    real = []
    for _ in range(tiles):
        spheres = [
            Sphere(a_p=rng.uniform(10, 15) + 1e-6, n_p=sphere_index, k_p=0.0, x_p=rng.uniform(0, tile), y_p=rng.uniform(0, tile), z_p=rng.choice(config.layer_depths_um()) / 2.2)
            for _ in range(particles)
        ]
        # a camera pixel integrates the intensity over its area: sample supersample² points per
        # pixel and average (pixel-centre samples alias the spheres' wide-angle refracted light)
        offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
        coordinates = np.stack(np.meshgrid(np.add.outer(np.arange(tile), offsets).ravel(), np.add.outer(np.arange(tile), offsets).ravel())).reshape(2, -1)
        model = LorenzMie(coordinates=coordinates, particle=spheres, instrument=instrument)
        intensity = model.hologram().reshape(tile, supersample, tile, supersample).mean(axis=(1, 3)).astype(np.float32)
        real.append(sensor_image(intensity, TRUE_BASELINE, {}, noise=rng.standard_normal((tile, tile)).astype(np.float32)))
    start = time.perf_counter()
    report = diagnose_tiles(real, config, settings=DiagnosisSettings(sim_tiles=6, evaluations=evaluations), particles_per_tile=particles).report
    print(json.dumps({"verdict": report["verdict"], "baseline_gap": round(report["gap"]["baseline"], 2), "seconds": round(time.perf_counter() - start, 1), "effects": [(e["id"], round(e["shrink"], 2)) for e in report["effects"]]}))
    phase_rad = 2 * np.pi / 0.66 * (sphere_index - 1.33) * 25.0
    print(f"spheres n = {sphere_index} in water: phase delay through a 25 um sphere {phase_rad:.0f} rad; "
          f"expected verdict particle_phase where the refracted light stays within the sensor's bandwidth; got {report['verdict']['id']}")


def _mie_scene(effect_id: str | None, rng: np.random.Generator) -> np.ndarray:
    """Pixel-integrated Lorenz–Mie intensity of one case's spheres, with the optical withheld effect (unobstructed = 1)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import pseudoreal

    extent = (MIE_SIZE - 1) * pseudoreal.PIXEL_UM
    x, y = rng.uniform(0, extent, MIE_SPHERES), rng.uniform(0, extent, MIE_SPHERES)
    z, d = rng.uniform(1900.0, 4700.0, MIE_SPHERES), rng.uniform(20.0, 30.0, MIE_SPHERES)
    shape = (MIE_SIZE, MIE_SIZE)
    if effect_id == "spherical_wave":
        source_um, centre = 20000.0, extent / 2
        magnification = source_um / (source_um - z)
        return pseudoreal.mie_intensity(shape, centre + magnification * (x - centre), centre + magnification * (y - centre), magnification * z, magnification * d)
    if effect_id == "coherence":
        radius_rad = 2e-3
        angles = [(0.0, 0.0)] + [(2 / 3 * radius_rad * np.cos(a), 2 / 3 * radius_rad * np.sin(a)) for a in np.arange(6) * np.pi / 3]
        return np.mean([pseudoreal.mie_intensity(shape, x + z * tx, y + z * ty, z, d) for tx, ty in angles], axis=0)
    return pseudoreal.mie_intensity(shape, x, y, z, d)


def mie_camera(intensity: np.ndarray, effect_id: str | None, rng: np.random.Generator) -> np.ndarray:
    """The suite's 8-bit camera, with the sensor-side withheld effect (the design comment above `MIE_EFFECTS`)."""
    rows, cols = intensity.shape
    image = intensity.astype(np.float64)
    yy, xx = np.mgrid[0:rows, 0:cols] / max(rows, cols)
    if effect_id == "illumination":
        distance = np.hypot(xx - 0.6, yy - 0.4)
        focal = distance.max() / np.sqrt(1 / np.sqrt(0.6) - 1)  # cos⁴θ = 0.6 at the far corner
        image = image / (1 + (distance / focal) ** 2) ** 2
    if effect_id == "parasitic_fringes":
        phase = 2 * np.pi * (xx * np.cos(0.4) + yy * np.sin(0.4)) * max(rows, cols) / 11.0
        radius_um = np.hypot(xx - 0.5, yy - 0.5) * max(rows, cols) * 2.2
        image = image * (1 + 0.06 * np.cos(phase + np.pi * radius_um**2 / (0.66 * 2e6)))
    if effect_id == "sensor_blur":
        kernel = np.array([1, 4, 6, 4, 1]) / 16
        image = np.apply_along_axis(np.convolve, 0, np.pad(image, ((2, 2), (0, 0)), mode="reflect"), kernel, mode="valid")
        image = np.apply_along_axis(np.convolve, 1, np.pad(image, ((0, 0), (2, 2)), mode="reflect"), kernel, mode="valid")
    if effect_id == "shot_noise":
        image = rng.poisson(image * MIE_PHOTONS) / MIE_PHOTONS
    counts = image * MIE_LEVEL + rng.normal(0.0, MIE_READ_NOISE, image.shape)
    return np.clip(np.round(counts), 0, 255).astype(np.uint8)


def _wilson(successes: int, trials: int) -> tuple[float, float]:
    """95 % Wilson score interval of a proportion."""
    if trials == 0:
        return (0.0, 1.0)
    z = 1.96
    p = successes / trials
    centre = (p + z**2 / (2 * trials)) / (1 + z**2 / trials)
    half = z * np.sqrt(p * (1 - p) / trials + z**2 / (4 * trials**2)) / (1 + z**2 / trials)
    return (max(0.0, centre - half), min(1.0, centre + half))


def _single_split_line(rows: list[dict]) -> str:
    """Top-1 and false alarms of the first half's verdict alone: the diagnosis without cross-fitting (its fits, scored on its own held-out half)."""
    rows = [r for r in rows if r["per_half"]]
    if not rows:
        return "not cross-fitted"
    injected = [r for r in rows if r["withheld"]]
    hits = sum(r["per_half"][0] == r["withheld"] for r in injected)
    alarms = sum(r["per_half"][0] is not None for r in rows if not r["withheld"])
    both = sum(r["per_half"][0] == r["per_half"][1] == r["withheld"] for r in injected)
    return (f"first half alone (no cross-fit): top-1 {hits}/{len(injected)} (95 % interval {_wilson(hits, len(injected))[0]:.2f}-{_wilson(hits, len(injected))[1]:.2f}), "
            f"false alarms {alarms}/{len(rows) - len(injected)}; both halves right alone: {both}/{len(injected)}")


def mie(cases: list[int] | None, seed: int = 2026, keep: str | None = None, stated: dict | None = None) -> None:
    design = [*MIE_EFFECTS, *[None] * MIE_CONTROLS]
    rows = []
    for index in cases if cases is not None else range(len(design)):
        effect_id = design[index]
        rng = np.random.default_rng([index, seed])
        made = time.perf_counter()
        counts = mie_camera(_mie_scene(effect_id, rng), effect_id, rng)
        made = time.perf_counter() - made
        start, cpu = time.perf_counter(), time.process_time()
        diagnosis = diagnose_hologram(counts, CONFIG, stated=stated)
        row = _row(index, effect_id, diagnosis.report, {"seconds": round(time.perf_counter() - start, 1), "cpu_seconds": round(time.process_time() - cpu, 1), "hologram_seconds": round(made, 1)})
        rows.append(row)
        print(json.dumps(row), flush=True)
        if keep:
            _keep(Path(keep), index, row, diagnosis)
    print(_score_line(rows) + f"; mean {np.mean([r['seconds'] for r in rows]):.0f} s per diagnosis")
    print(_single_split_line(rows))


# The third suite's design, fixed on 2026-11-23 before its first run. Every case: a hologram of
# Lorenz–Mie spheres of 20–30 µm at 1900–4700 µm (air-equivalent; seeded by the case index and
# the suite's seed) at the real hologram's density (25 per 512², 100 per 1024²), ABSORBING
# (n = 1.59 + 1.0i: the seed's simulator assumes opaque particles), recorded by the camera
# `absorbing_camera` (mean ABSORBING_LEVEL counts, Gaussian read noise 1.5 counts, rounding,
# uint8), with at most one withheld effect, each parameterised independently of `_effects` and
# of the ``mie`` suite:
#   illumination       a polynomial vignetting, I·(1 − 0.35 ρ²), ρ the distance from (0.3, 0.65)
#                      of the field in field widths (`_effects`: a Gaussian envelope; ``mie``: cos⁴)
#   shot_noise         Poisson photon counts, 120 photons at the mean level
#   sensor_blur        pixel crosstalk: a 3 × 3 kernel on the light (centre 0.6, edges 0.08,
#                      corners 0.02), before the noise
#   coherence          an extended source: a square of ±1.8 mrad, sampled by 3 × 3 angles, each
#                      shifting a sphere's hologram by z·θ, intensities averaged
#   parasitic_fringes  a reflection off a tilted cover glass: a fringe of period 9 px at 1.1 rad,
#                      amplitude 5 % at the field's centre falling as a Gaussian (half the field
#                      width, 1/e) across it
#   dust               (expected `parasitic_fringes`: CONTRACT.md's "static fringes from dust,
#                      windows, etalons") 12 absorbing Lorenz–Mie dust grains per 512² of 8–40 µm
#                      on the far window, 6000 µm air-equivalent, outside the volume
#   particle_phase     the spheres transparent polystyrene (n = 1.59) instead of absorbing
#   quantization       a 6-bit camera: 64 levels over the same full scale, written to uint8
#                      (every 4th level)
#   spherical_wave     a point source 25 mm before the sensor (each sphere magnified by
#                      M = L / (L − z) in position, size and depth)
#   control            nothing withheld (expected verdict: null)
# Cases 0–8: the cases above at 512²; 9–13: 5 controls at 512²; 14–18 at 1024²:
# illumination, particle_phase, shot_noise, 2 controls. Scored: top-1 over the effect cases,
# false alarms over the controls, each with its 95 % Wilson interval. Left out:
# multiple_scattering (Mie fields are superposed: single scattering).
ABSORBING_DESIGN = (  # (case, expected verdict, hologram edge in px)
    *[(case, case, 512) for case in ("illumination", "shot_noise", "sensor_blur", "coherence", "parasitic_fringes", "particle_phase", "quantization", "spherical_wave")],
    ("dust", "parasitic_fringes", 512),
    *[(None, None, 512)] * 5,
    ("illumination", "illumination", 1024), ("particle_phase", "particle_phase", 1024), ("shot_noise", "shot_noise", 1024), (None, None, 1024), (None, None, 1024),
)
ABSORBING_INDEX = 1.59 + 1.0j
ABSORBING_LEVEL = 150.0


def _absorbing_scene(case: str | None, size: int, rng: np.random.Generator) -> np.ndarray:
    """Pixel-integrated Lorenz–Mie intensity of one case of the third suite, with its optical withheld effect (unobstructed = 1)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import pseudoreal

    count = round(MIE_SPHERES * (size / MIE_SIZE) ** 2)
    extent = (size - 1) * pseudoreal.PIXEL_UM
    x, y = rng.uniform(0, extent, count), rng.uniform(0, extent, count)
    z, d = rng.uniform(1900.0, 4700.0, count), rng.uniform(20.0, 30.0, count)
    index = 1.59 if case == "particle_phase" else ABSORBING_INDEX
    shape = (size, size)
    if case == "dust":
        grains = round(12 * (size / MIE_SIZE) ** 2)
        x, y = np.concatenate([x, rng.uniform(0, extent, grains)]), np.concatenate([y, rng.uniform(0, extent, grains)])
        z, d = np.concatenate([z, np.full(grains, 6000.0)]), np.concatenate([d, rng.uniform(8.0, 40.0, grains)])
    if case == "spherical_wave":
        source_um, centre = 25000.0, extent / 2
        magnification = source_um / (source_um - z)
        return pseudoreal.mie_intensity(shape, centre + magnification * (x - centre), centre + magnification * (y - centre), magnification * z, magnification * d, index)
    if case == "coherence":
        angles = [(tx, ty) for tx in (-1.8e-3, 0.0, 1.8e-3) for ty in (-1.8e-3, 0.0, 1.8e-3)]
        return np.mean([pseudoreal.mie_intensity(shape, x + z * tx, y + z * ty, z, d, index) for tx, ty in angles], axis=0)
    return pseudoreal.mie_intensity(shape, x, y, z, d, index)


def absorbing_camera(intensity: np.ndarray, case: str | None, rng: np.random.Generator, *, read_noise: float = MIE_READ_NOISE, photons: float = 120.0) -> np.ndarray:
    """The third suite's camera, with its sensor-side withheld effect (the design comment above `ABSORBING_DESIGN`; ``photons``: at the mean level for ``shot_noise``)."""
    rows, cols = intensity.shape
    image = intensity.astype(np.float64)
    yy, xx = np.mgrid[0:rows, 0:cols] / max(rows, cols)
    if case == "illumination":
        image = image * (1 - 0.35 * ((xx - 0.3) ** 2 + (yy - 0.65) ** 2))
    if case == "parasitic_fringes":
        amplitude = 0.05 * np.exp(-((xx - 0.5) ** 2 + (yy - 0.5) ** 2) / 0.5**2)
        image = image * (1 + amplitude * np.cos(2 * np.pi * (xx * np.cos(1.1) + yy * np.sin(1.1)) * max(rows, cols) / 9.0))
    if case == "sensor_blur":
        kernel = np.array([[0.02, 0.08, 0.02], [0.08, 0.6, 0.08], [0.02, 0.08, 0.02]])
        image = ndimage.convolve(image, kernel, mode="reflect")
    if case == "shot_noise":
        image = rng.poisson(image * photons) / photons
    counts = image * ABSORBING_LEVEL + rng.normal(0.0, read_noise, image.shape)
    if case == "quantization":
        return (np.clip(np.round(counts / 4.0), 0, 63) * 4).astype(np.uint8)
    return np.clip(np.round(counts), 0, 255).astype(np.uint8)


def _row(index: int, effect_id: str | None, report: dict, seconds: dict) -> dict:
    """One case's result line (the ``mie`` and ``absorbing`` suites)."""
    verdict = report["verdict"]
    own = next((e for e in report["effects"] if e["id"] == effect_id), None)
    return {
        "case": index, "withheld": effect_id, "verdict": verdict["id"], "correct": verdict["id"] == effect_id, "per_half": verdict.get("per_half"), "reason": verdict["reason"],
        "baseline_gap": round(report["gap"]["baseline"], 2), "baseline_interval": [round(v, 2) for v in report["gap"]["baseline_interval"]],
        "best": [(e["id"], round(e["evidence"]["reduction"], 1), e["evidence"]["summaries"], [round(v, 1) for v in e["evidence"]["interval"]], round(e["shrink"], 2)) for e in report["effects"][:3] if "evidence" in e],
        "shrink_of_withheld": round(own["shrink"], 2) if own else None, "tiles_to_decide": verdict["tiles_to_decide"], "known": report["known"], **seconds,
    }


def _score_line(rows: list[dict]) -> str:
    injected = [r for r in rows if r["withheld"]]
    controls = [r for r in rows if not r["withheld"]]
    hits, alarms = sum(r["correct"] for r in injected), sum(not r["correct"] for r in controls)
    return (f"top-1 {hits}/{len(injected)} (95 % interval {_wilson(hits, len(injected))[0]:.2f}-{_wilson(hits, len(injected))[1]:.2f}); "
            f"false alarms {alarms}/{len(controls)} (95 % interval {_wilson(alarms, len(controls))[0]:.2f}-{_wilson(alarms, len(controls))[1]:.2f})")


def _keep(folder: Path, index: int, row: dict, diagnosis) -> None:
    """Pickle what `_scored` needs of one case (its halves, without the simulator's kernels and fields), for `rescore`."""
    import dataclasses
    import pickle
    from types import SimpleNamespace

    halves = [dataclasses.replace(h, model=SimpleNamespace(paired=h.model.paired)) for h in diagnosis.halves]
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / f"case_{index:02d}.pkl", "wb") as file:
        pickle.dump({"row": row, "halves": halves, "candidates": [e["id"] for e in diagnosis.report["effects"]]}, file)


def absorbing(cases: list[int] | None, seed: int = 2027, keep: str | None = None) -> None:
    rows = []
    for index in cases if cases is not None else range(len(ABSORBING_DESIGN)):
        case, effect_id, size = ABSORBING_DESIGN[index]
        rng = np.random.default_rng([index, seed])
        made = time.perf_counter()
        counts = absorbing_camera(_absorbing_scene(case, size, rng), case, rng)
        made = time.perf_counter() - made
        start, cpu = time.perf_counter(), time.process_time()
        diagnosis = diagnose_hologram(counts, CONFIG)
        seconds = {"scene": case, "size": size, "seconds": round(time.perf_counter() - start, 1), "cpu_seconds": round(time.process_time() - cpu, 1), "hologram_seconds": round(made, 1)}
        row = _row(index, effect_id, diagnosis.report, seconds)
        rows.append(row)
        print(json.dumps(row), flush=True)
        if keep:
            _keep(Path(keep), index, row, diagnosis)
    print(_score_line(rows) + f"; mean {np.mean([r['seconds'] for r in rows]):.0f} s per diagnosis")
    print(_single_split_line(rows))


def rescore(folder: str) -> None:
    """Each kept case's verdict again, from its kept fits, with the current verdict code."""
    import pickle

    from napari_lbs._core._gap._diagnose import _scored

    rows = []
    for path in sorted(Path(folder).glob("case_*.pkl")):
        with open(path, "rb") as file:
            kept = pickle.load(file)  # our own files, written by `absorbing --keep`
        halves = kept["halves"]
        verdict = _scored(halves, kept["candidates"], settings=DiagnosisSettings())["verdict"]
        row = {**kept["row"], "verdict": verdict["id"], "correct": verdict["id"] == kept["row"]["withheld"], "reason": verdict["reason"], "was": kept["row"]["verdict"]}
        rows.append(row)
        print(json.dumps({k: row[k] for k in ("case", "withheld", "verdict", "was", "reason")}))
    print(_score_line(rows))


def threads(repeats: int) -> None:
    """One fit evaluation's simulated summaries at 1024² (8 tiles of 256², whole fields), on the summary pool against one thread, interleaved in one run."""
    from concurrent.futures import ThreadPoolExecutor

    from napari_lbs._core._effects import BASELINE
    from napari_lbs._core._gap import _summaries
    from napari_lbs._core._gap._fitting import _Model
    from napari_lbs._core._gap._tiling import TileLayout

    config = load_config(None)
    layout = TileLayout((1024, 1024), tuple((r, c) for r in range(0, 1024, 256) for c in range(0, 1024, 256)), 1.0)
    model = _Model(config, shape=(256, 256), count=25, settings=DiagnosisSettings(), fringe_frequency=(0.1, 0.0), layout=layout, known={"quantization": {"bits": 8.0, "saturation": 1.7}})
    baseline = {"contrast": 0.8, "sigma": 0.04, "gamma": 1.2}
    pool = _summaries._summary_pool()
    single = ThreadPoolExecutor(max_workers=1)
    model.summaries(baseline, {}, half="fit")  # simulates and caches the light once
    times = {"pool": [], "one thread": []}
    results = {}
    for _ in range(repeats):
        for name, executor in (("pool", pool), ("one thread", single)):
            _summaries._POOL[os.getpid()] = executor
            start = time.perf_counter()
            results[name] = model.summaries(baseline, {}, half="fit")
            times[name].append(time.perf_counter() - start)
    _summaries._POOL[os.getpid()] = pool
    median = {name: float(np.median(t)) for name, t in times.items()}
    print(json.dumps({"workers": pool._max_workers, "seconds per evaluation": median, "speed-up": round(median["one thread"] / median["pool"], 2), "identical": bool(np.array_equal(results["pool"], results["one thread"]))}))


def _field_summaries(counts: np.ndarray) -> tuple[np.ndarray, list]:
    """Each tile's `tile_summaries` of a hologram cut as `diagnose` cuts it (its field mean and surroundings): ((tiles, K) array, names)."""
    from napari_lbs._core._gap._summaries import tile_summaries
    from napari_lbs._core._gap._tiling import adapted_tile_px, field_surroundings

    counts = counts.astype(np.float32)
    tile = adapted_tile_px(counts.shape, CONFIG.tile.size)
    rows = [tile_summaries(counts[r : r + tile, c : c + tile], config=CONFIG, field_mean=float(counts.mean()), surroundings=field_surroundings(counts, (r, c), (tile, tile)))
            for r in range(0, counts.shape[0] - tile + 1, tile) for c in range(0, counts.shape[1] - tile + 1, tile)]
    return np.array([values for values, _ in rows]), rows[0][1]


def noise(scenes: int, photons: float) -> None:
    """How far each noise summary tells photon noise from read noise of the same variance: the same 512² absorbing scenes, 16 tiles of 128², z of the difference of means."""
    print(f"{photons:g} photons at the mean level against Gaussian read noise of the same variance, {scenes} scenes: z per noise summary")
    for seed in range(scenes):
        scene = _absorbing_scene(None, MIE_SIZE, np.random.default_rng([seed, 3]))
        rng = np.random.default_rng([seed, 4])
        poisson = absorbing_camera(scene, "shot_noise", rng, photons=photons)
        gaussian = absorbing_camera(scene, None, rng, read_noise=float(np.hypot(MIE_READ_NOISE, ABSORBING_LEVEL / np.sqrt(photons))))
        (shot, names), (read, _) = _field_summaries(poisson), _field_summaries(gaussian)
        z = (shot.mean(axis=0) - read.mean(axis=0)) / (shot.std(axis=0, ddof=1) * np.sqrt(2 / len(shot)) + 1e-12)
        print(json.dumps({"scene": seed, **{name: round(float(value), 1) for value, (name, group) in zip(z, names, strict=True) if group == "noise"}}))


def signature(case: str, size: int, scenes: int, top: int) -> None:
    from napari_lbs._core._gap._tiling import adapted_tile_px

    if case not in {c for c, _, _ in ABSORBING_DESIGN if c}:
        raise SystemExit(f"signature: unknown case {case!r}")
    tile = adapted_tile_px((size, size), CONFIG.tile.size)

    def summaries(withheld: str | None, seed: int, read_noise: float) -> tuple[np.ndarray, list]:
        scene = _absorbing_scene(withheld, size, np.random.default_rng([seed, 1]))  # the same spheres with and without
        return _field_summaries(absorbing_camera(scene, withheld, np.random.default_rng([seed, 2]), read_noise=read_noise))  # the same noise

    def tiles(withheld: str | None, read_noise: float) -> tuple[np.ndarray, list]:
        made = [summaries(withheld, seed, read_noise) for seed in range(scenes)]
        return np.concatenate([values for values, _ in made]), made[0][1]

    plain, names = tiles(None, MIE_READ_NOISE)
    spread = plain.std(axis=0) + 1e-12
    noisier = (tiles(None, 2 * MIE_READ_NOISE)[0] - plain).mean(axis=0) / spread
    withheld = (tiles(case, MIE_READ_NOISE)[0] - plain).mean(axis=0) / spread
    print(f"{case} at {size}², {scenes} scenes x {(size // tile) ** 2} tiles of {tile}²: paired mean change / tile-to-tile spread (read noise x2 beside it)")
    for i in np.argsort(-np.abs(withheld))[:top]:
        name, group = names[i]
        print(f"{withheld[i]:+7.2f}   noise x2 {noisier[i]:+7.2f}   {group:10s} {name}")


def real() -> None:
    config = load_config(None)
    start, cpu = time.perf_counter(), time.process_time()
    diagnosis = diagnose_hologram(load_sample_hologram(), config, settings=DiagnosisSettings())
    cpu = time.process_time() - cpu
    out = Path(__file__).resolve().parents[1] / "docs" / "figures" / "diagnosis-real"
    write_report(diagnosis, out, provenance={"source": "seed's real hologram (sample data)", "config": config.to_dict()})
    report = diagnosis.report
    print(f"real hologram: {time.perf_counter() - start:.0f} s wall, {cpu:.0f} s CPU (target <= 180 s on 2 idle cores); "
          f"baseline gap {report['gap']['baseline']:.2f} (90 % interval {report['gap']['baseline_interval']}); known {report['known']}; verdict {report['verdict']}")
    print("where:", json.dumps(report["gap"]["by_group"]))
    print("effects:", [(e["id"], round(e["gap_after"], 2), round(e["shrink"], 2), [round(v, 2) for v in e.get("shrink_interval", [])], e["confirmed"]) for e in report["effects"]])
    print("waterfall:", [(step["model"], round(step["gap"], 2)) for step in report["waterfall"]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("suite", "independent"):
        p = sub.add_parser(name)
        p.add_argument("--tile", type=int, default=128)
        p.add_argument("--tiles", type=int, default=16)
        p.add_argument("--particles", type=int, default=12, help="particles per tile")
        p.add_argument("--evaluations", type=int, default=60)
        if name == "suite":
            p.add_argument("--controls", type=int, default=5, help="controls; the last at the densest injection density")
            p.add_argument("--jobs", type=int, default=1, help="cases diagnosed at once (processes)")
            p.add_argument("--cases", type=int, nargs="+", help="case indices to run, in this order (default all)")
        else:
            p.add_argument("--index", type=float, default=1.59, help="refractive index of the spheres (water: 1.33)")
            p.add_argument("--supersample", type=int, default=3, help="intensity samples per pixel edge, averaged (pixel area integration)")
    p = sub.add_parser("mie")
    p.add_argument("--cases", type=int, nargs="+", help="case indices to run (default all: the effects, then the controls)")
    p.add_argument("--seed", type=int, default=2026, help="scene seed (2026: the suite; others: scenes of the same design)")
    p.add_argument("--keep", help="pickle each case's fits here, for `rescore`")
    p.add_argument("--known-effect", action="append", default=[], metavar="ID[:NAME=VALUE,...]",
                   help="what a user of these scenes knows, as `diagnose --known-effect` (the spheres: particle_phase:index_contrast=0.26,transmission=1)")
    p = sub.add_parser("absorbing")
    p.add_argument("--cases", type=int, nargs="+", help="case indices to run (default all, `ABSORBING_DESIGN`)")
    p.add_argument("--seed", type=int, default=2027, help="scene seed (2027: the suite; 8: development scenes)")
    p.add_argument("--keep", help="pickle each case's fits here, for `rescore`")
    p = sub.add_parser("rescore")
    p.add_argument("folder")
    p = sub.add_parser("signature")
    p.add_argument("case", help="a withheld case of the third suite (`ABSORBING_DESIGN`)")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--scenes", type=int, default=4)
    p.add_argument("--top", type=int, default=12)
    sub.add_parser("real")
    p = sub.add_parser("noise", help="photon against read noise of the same variance: each noise summary's z")
    p.add_argument("--scenes", type=int, default=4)
    p.add_argument("--photons", type=float, default=120.0)
    p = sub.add_parser("threads")
    p.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    if args.command == "suite":
        suite(args.tile, args.tiles, args.particles, args.evaluations, args.controls, args.jobs, args.cases)
    elif args.command == "independent":
        independent(args.tile, args.tiles, args.particles, args.evaluations, args.index, args.supersample)
    elif args.command == "mie":
        mie(args.cases, args.seed, args.keep, parse_effects(args.known_effect, flag="--known-effect"))
    elif args.command == "absorbing":
        absorbing(args.cases, args.seed, args.keep)
    elif args.command == "rescore":
        rescore(args.folder)
    elif args.command == "signature":
        signature(args.case, args.size, args.scenes, args.top)
    elif args.command == "noise":
        noise(args.scenes, args.photons)
    elif args.command == "threads":
        threads(args.repeats)
    else:
        real()


if __name__ == "__main__":
    main()
