"""The scene-conditioned diagnosis (`diagnose_scene`) scored on a withheld-effect suite, and run on the built-in real hologram.

``suite DIR``: every hologram of a folder written by ``withheld_suite.py make`` is
diagnosed; a case is right when the verdict names exactly the effects withheld in it
(nothing for a control). A case holding an effect outside the catalog (its ``outside``, in
the outside sets) is right when the verdict says the catalog does not explain it
(``catalog_explains`` false) or is undecided, and wrong when the catalog is said to explain
it, whatever is named. Printed per case: the verdict, the selected effects' z, the structured
share, the particle optics' z, the seconds, the outside effects; then the score, the outside
cases' score, the controls' false alarms and the load average before and after; each named
effect's parameters that the case sets exactly (an etalon's, photon noise's) against their
estimates, in units of the reported error bar, and how many lie within two. ``real``:
the built-in hologram's report. ``--grid N``: the held-out checkerboard's tiles per side
(`SceneDiagnosisSettings.grid`), written to the result; ``--workers N``: fitting processes
(default one per available core, as ``napari-lbs diagnose``).

    python benchmarks/withheld_suite.py make development /tmp/dev
    python benchmarks/bench_scene_diagnosis.py suite /tmp/dev --out benchmarks/results/diagnosis/scene_development.json
    python benchmarks/bench_scene_diagnosis.py real --out benchmarks/results/diagnosis/scene_real.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

from napari_lbs._core import ExperimentConfig, load_sample_hologram, read_hologram
from napari_lbs._core.foundation import available_threads
from napari_lbs._core.gap import SceneDiagnosisSettings, diagnose_scene
from withheld_suite import vignetting_divisor


def _case_line(name: str, report: dict, seconds: float) -> dict:
    effects = {e["id"]: e for e in report["effects"]}
    return {
        "case": name,
        "verdict": report["verdict"]["id"],
        "p_verdict": _rounded(report["verdict"]["probability"]),
        # the posterior of the verdict's model of the mean (photon noise and the converter's levels are tested beside it)
        "posterior_verdict": _rounded(report["posterior"].get("+".join(sorted(e for e in (report["verdict"]["id"] or "").split("+") if e and e not in ("shot_noise", "quantization"))) or "null")),
        "catalog_explains": report["verdict"]["catalog_explains"],
        "structured_share": round(report["verdict"]["residual"], 4),
        "directional_blur": {k: round(float(v), 3) for k, v in report["gap"].get("directional_blur", {}).items()},
        "z": {k: (None if v["z"] is None else round(float(v["z"]), 2)) for k, v in effects.items()},
        "particles": report["gap"]["particles"],
        "optics": _optics_line(report["particle_optics"]),
        "dust": {k: _rounded(v) if isinstance(v, float) else v for k, v in report.get("dust_layer", {}).items() if k in ("searched", "named", "grains", "in_layer", "depth_um", "tiles_with_grains")},
        "levels": {k: _rounded(v) for k, v in effects["quantization"].get("levels", {}).items()},
        "photon_band_ratios": [_rounded(v) for v in effects["shot_noise"].get("band_ratios", [])],
        "photon_fine_ratios": [_rounded(v) for v in effects["shot_noise"].get("fine_ratios", [])],
        "photon_noise_blur_px": _rounded(effects["shot_noise"].get("noise_blur_px")),
        "params": {k: {name: [_rounded(value), _rounded(v.get("params_err", {}).get(name))] for name, value in v["params"].items()}
                   for k, v in effects.items() if v["params"]},
        "seconds": round(seconds, 1),
    }


def _optics_line(optics: dict) -> dict:
    """The particle optics' call, its combined z and each view's z and index contrast."""
    views = {name: {"z": _rounded(optics[name]["z"]), "index_contrast": optics[name].get("index_contrast")}
             for name in ("power_spectrum", "through_focus") if name in optics}
    return {"model": optics["model"], "z": _rounded(optics["z"]), "index_contrast": optics.get("index_contrast"), **views}


def _rounded(value) -> float | None:
    return None if value is None else float(f"{value:.5g}")


def _truths(effects: dict, size: int) -> dict:
    """The catalog parameters a case's withheld effects set exactly (the suite's etalon and photon noise are the catalog's models).

    Photons count per unit of the frame's mean light, which the diagnosis divides the frame
    by: the suite's are per unit of unobstructed light on the axis, which a vignetting
    lowers on average.
    """
    truths = {}
    fringe = effects.get("parasitic_fringes", {})
    if "etalon" in fringe:
        truths["parasitic_fringes"] = {"amplitude": fringe["etalon"], "period_px": fringe["period_px"], "angle_rad": fringe["angle_rad"],
                                       "phase_rad": fringe.get("phase_rad", 0.0)}
    if "shot_noise" in effects:
        light = float(np.mean(1.0 / vignetting_divisor((size, size), effects["illumination"]))) if "illumination" in effects else 1.0
        truths["shot_noise"] = {"log10_photons": float(np.log10(effects["shot_noise"]["photons"] * light))}
    return truths


def _recovered(line: dict, effects: dict, size: int) -> list:
    """Each exactly known parameter of a named effect against its estimate: the error in units of the reported error bar."""
    named = set((line["verdict"] or "").split("+"))
    rows = []
    for effect, truths in _truths(effects, size).items():
        for name, truth in truths.items():
            value, error = line["params"].get(effect, {}).get(name, [None, None])
            if effect not in named or value is None or not error:
                continue
            difference = value - truth
            if name == "phase_rad":
                difference = (difference + np.pi) % (2 * np.pi) - np.pi
            rows.append({"effect": effect, "param": name, "truth": truth, "value": value, "err": error, "z": round(difference / error, 2)})
    return rows


def suite(folder: Path, settings: SceneDiagnosisSettings) -> dict:
    design = json.loads((folder / "design.json").read_text())
    config = ExperimentConfig()
    lines, right, alarms, controls, outside_right, outside_cases = [], 0, 0, 0, 0, 0
    for case in design["cases"]:
        path = folder / case["file"]
        if not path.is_file():
            continue
        started = time.perf_counter()
        report = diagnose_scene(read_hologram(path), config, settings=settings).report
        line = _case_line(case["name"], report, time.perf_counter() - started)
        named = sorted((line["verdict"] or "").split("+")) if line["verdict"] else []
        line["expected"] = case["expected"]
        line["recovered"] = _recovered(line, case.get("effects", {}), case["size"])
        line["outside"] = case.get("outside", [])  # designs written before the outside sets have none
        line["undecided"] = report["verdict"]["undecided"]
        if line["outside"]:
            # the catalog cannot explain it: right when that is said (or the verdict is undecided),
            # wrong when the catalog is said to explain it, whatever effects are named
            line["right"] = not line["catalog_explains"] or bool(line["undecided"])
            line["names_expected"] = set(case["expected"]) <= set(named)  # the catalog effects beside the outside one
            outside_cases += 1
            outside_right += line["right"]
        else:
            line["right"] = named == sorted(case["expected"])
            if not case["expected"]:
                controls += 1
                alarms += bool(named)
        right += line["right"]
        lines.append(line)
        print(json.dumps(line), flush=True)
    recovered = [row for line in lines for row in line["recovered"]]
    confident = [line for line in lines if (line["p_verdict"] or 0.0) >= 0.8]  # the target: of the verdicts given at P >= 0.8, >= 90 % right
    return {"suite": design["suite"], "cases": lines, "right": right, "of": len(lines), "control_false_alarms": alarms, "controls": controls,
            "outside_right": outside_right, "outside_cases": outside_cases, "confident": len(confident), "confident_right": sum(line["right"] for line in confident),
            "within_2_errors": sum(abs(row["z"]) <= 2 for row in recovered), "known_parameters": len(recovered)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["suite", "real"])
    parser.add_argument("folder", nargs="?")
    parser.add_argument("--out", required=True)
    parser.add_argument("--grid", type=int, default=SceneDiagnosisSettings().grid, help="tiles per side of the held-out checkerboard")
    parser.add_argument("--workers", type=int, default=available_threads(), help="fitting processes (default: one per available core, as the CLI's)")
    args = parser.parse_args()
    default = SceneDiagnosisSettings(grid=args.grid)
    settings = dataclasses.replace(default, refine=dataclasses.replace(default.refine, workers=args.workers))
    load = [os.getloadavg()[0]]
    if args.what == "suite":
        result = suite(Path(args.folder), settings)
    else:
        started = time.perf_counter()
        diagnosis = diagnose_scene(load_sample_hologram(), ExperimentConfig(), settings=settings)
        result = {"report": json.loads(diagnosis.to_json()), "tile_map": np.round(diagnosis.tile_map, 3).tolist(), "seconds": round(time.perf_counter() - started, 1)}
        print(json.dumps(_case_line("built-in", result["report"], result["seconds"])))
    load.append(os.getloadavg()[0])
    result["load_average"] = load
    result["grid"] = args.grid
    result["workers"] = args.workers
    Path(args.out).write_text(json.dumps(result, indent=1, default=float))
    if args.what == "suite":
        outside = f"; outside the catalog {result['outside_right']}/{result['outside_cases']} right" if result["outside_cases"] else ""
        print(f"{result['right']}/{result['of']} right{outside}; {result['control_false_alarms']} false alarms in {result['controls']} controls; "
              f"{result['confident_right']}/{result['confident']} right of the verdicts at P >= 0.8; "
              f"{result['within_2_errors']}/{result['known_parameters']} known parameters within 2 error bars; load {load}")


if __name__ == "__main__":
    main()
