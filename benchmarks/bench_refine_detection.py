"""Detection and sizing with and without Lorenz–Mie refinement, on pseudo-real holograms.

For each hologram the network's proposals (`predict_particles` down to
`REFINE_PROPOSAL_FRACTION` of the model's threshold) are refined by `refine_particles`
(default `RefineSettings`, the hologram divided by its mean), as ``napari-lbs predict
--refine`` does (a proposal below the model's threshold that the fit could not refine
leaves the table); the network's table (the proposals at its threshold) and the refined one
are scored one-to-one against the truth (`score_particles`): ER, JI, TP/FP/FN, median |Δz| and |Δd| of the matches, the fitted
index contrast of the matches (polystyrene 1.59 in water 1.33: 0.26), which of the
network's false positives the fit dropped and which true positives it dropped wrongly, and
the time per particle (wall and core seconds, beside the network's own time in the same run),
and the refined table of the spheres' material alone (`same_material` at 0.26, as
``napari-lbs predict --material 0.26``). With ``--residual`` the refined table also holds the
particles the network then finds in its residual (`residual_particles`), as ``predict
--refine`` gives it; the fit's own table is scored beside it (``fit only``).

Holograms (`pseudoreal`: Lorenz–Mie polystyrene spheres in water, 1024², 8-bit camera),
made in the holograms folder when missing:

- ``real_density``: 100 spheres of 20–30 µm (seed 7);
- ``real_density_distractors``: the same 100 spheres, plus unlabelled debris (index 1.45,
  3–12 µm) and spheres beyond the window's edge whose fringes reach into it;
- ``wide_sizes``: 100 spheres of 16–36 µm, beyond the 20–30 µm the network trains on (seed 23);
- ``4x_density``: 400 spheres of 20–30 µm (seed 8).

These four are the development set (``--set development``, the default). The frozen test
set (``--set frozen``) is made the same way from other seeds — ``frozen_real_density``,
``frozen_distractors`` (seed 107), ``frozen_wide_sizes`` (seed 123) and
``frozen_2.5x_density`` (250 spheres, seed 108) — and only ever scores a design chosen on
the development set.

Usage::

    OMP_NUM_THREADS=1 NAPARI_LBS_THREADS=1 python benchmarks/bench_refine_detection.py \\
        --model MODEL.pt --holograms FOLDER [--set frozen] [--only real_density ...] [--rounds 2] [--residual]
"""

from __future__ import annotations

import argparse
import datetime
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pseudoreal

from napari_lbs._core import (
    RefineSettings,
    load_config,
    load_model,
    predict_particles,
    read_hologram,
    read_particles,
    refine_particles,
    same_material,
    score_particles,
    write_particles,
)
from napari_lbs._core.foundation._files import write_json
from napari_lbs._core.learning._metrics import match_particles
from napari_lbs._core.pipeline import REFINE_PROPOSAL_FRACTION
from napari_lbs._core.refine._scene import residual_particles

INDEX_CONTRAST = round(pseudoreal.N_PARTICLE - pseudoreal.N_MEDIUM, 3)
WIDE_SIZES_UM = (16.0, 36.0)
DISTRACTORS = {"impurities": 50, "margin_px": 128}  # as benchmarks/bench_pseudoreal.py
HOLOGRAMS = {  # name: (spheres, seed, how)
    "real_density": (100, 7, "plain"),
    "real_density_distractors": (100, 7, "distractors"),
    "wide_sizes": (100, 23, "wide"),
    "4x_density": (400, 8, "plain"),
    # the frozen test set: written before its first run, never used to choose anything
    "frozen_real_density": (100, 107, "plain"),
    "frozen_distractors": (100, 107, "distractors"),
    "frozen_wide_sizes": (100, 123, "wide"),
    "frozen_2.5x_density": (250, 108, "plain"),
}
SETS = {"development": [n for n in HOLOGRAMS if not n.startswith("frozen_")], "frozen": [n for n in HOLOGRAMS if n.startswith("frozen_")]}


def wide_sizes(count: int, *, seed: int, size: int = 1024, z_air_um: tuple[float, float] = (1900.0, 4700.0)) -> tuple[np.ndarray, dict]:
    """`pseudoreal.pseudo_real`'s scene with diameters uniform in `WIDE_SIZES_UM`."""
    rng = np.random.default_rng(seed)
    extent = (size - 1) * pseudoreal.PIXEL_UM
    table = {
        "x_um": rng.uniform(0, extent, count),
        "y_um": rng.uniform(0, extent, count),
        "z_um": rng.uniform(*z_air_um, count),
        "diameter_um": rng.uniform(*WIDE_SIZES_UM, count),
    }
    intensity = pseudoreal.mie_intensity((size, size), table["x_um"], table["y_um"], table["z_um"], table["diameter_um"])
    return pseudoreal.camera(intensity, rng=rng), table


def hologram(folder: Path, name: str) -> tuple[np.ndarray, dict]:
    """The hologram ``name`` of `HOLOGRAMS` and its truth, made (temp name, then rename) when missing."""
    import tifffile

    count, seed, how = HOLOGRAMS[name]
    image_path, truth_path = folder / f"{name}.tif", folder / f"{name}_truth.csv"
    if not (image_path.is_file() and truth_path.is_file()):
        start = time.perf_counter()
        if how == "wide":
            image, truth = wide_sizes(count, seed=seed)
        else:
            image, truth = pseudoreal.pseudo_real(count, seed=seed, **(DISTRACTORS if how == "distractors" else {}))
        write_particles(truth_path, truth, force=True)  # made again with its image
        partial = image_path.with_name(image_path.name + ".partial.tif")
        tifffile.imwrite(partial, image)
        os.replace(partial, image_path)
        print(f"{name}: {count} Lorenz-Mie spheres made in {time.perf_counter() - start:.0f} s", flush=True)
    return read_hologram(image_path), read_particles(truth_path)


def _core_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _median(values) -> float | None:
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]  # rows the fit did not refine have no index
    return float(np.median(values)) if values.size else None


def score(table: dict, truth: dict) -> tuple[dict, np.ndarray]:
    """One-to-one scores of ``table`` and its (table row, truth row) matches."""
    metrics = score_particles(table, truth)
    pairs = np.array(match_particles(table, truth), dtype=np.int64).reshape(-1, 2)
    p, t = pairs[:, 0], pairs[:, 1]
    z_error = np.asarray(table["z_um"])[p] - np.asarray(truth["z_um"])[t]
    d_error = np.asarray(table["diameter_um"])[p] - np.asarray(truth["diameter_um"])[t]
    row = {
        "er": metrics["er"], "ji": metrics["ji"], "tp": metrics["tp"], "fp": metrics["fp"], "fn": metrics["fn"],
        "median_abs_dz_um": _median(np.abs(z_error)), "median_abs_dd_um": _median(np.abs(d_error)),
        "median_dd_um": _median(d_error), "p90_abs_dd_um": float(np.percentile(np.abs(d_error), 90)) if d_error.size else None,
    }
    if "index_contrast" in table:
        index = np.asarray(table["index_contrast"], dtype=np.float64)[p]
        row["median_index_contrast"] = _median(index)
        row["median_abs_index_error"] = _median(np.abs(index - INDEX_CONTRAST))
    return row, pairs


def evaluate(name: str, image: np.ndarray, truth: dict, model, config, *, tables: Path | None = None, rounds: int = RefineSettings().rounds,
             look_in_residual: bool = False) -> dict:
    import pandas as pd

    start, core = time.perf_counter(), _core_seconds()
    # as predict --refine: proposals down to a fraction of the model's threshold; the network's
    # own table is their rows at its threshold (one suppression, strongest first, for both)
    proposals = predict_particles(image, model, config, device="cpu", threshold=REFINE_PROPOSAL_FRACTION * float(model.meta["threshold"])).particles
    predict_s, predict_core_s = time.perf_counter() - start, _core_seconds() - core
    proposals = {k: np.asarray(v) for k, v in proposals.items()}
    at_threshold = proposals["score"] >= float(model.meta["threshold"])
    network = {k: v[at_threshold] for k, v in proposals.items()}
    count = len(proposals["x_um"])
    frame = pd.DataFrame(proposals)
    frame["network_row"] = np.arange(count)
    normalised = np.asarray(image, dtype=np.float64) / float(np.mean(image))  # as predict --refine
    start, core = time.perf_counter(), _core_seconds()
    refined_frame = refine_particles(normalised, frame, config, settings=RefineSettings(rounds=rounds))
    refine_s, refine_core_s = time.perf_counter() - start, _core_seconds() - core
    # as predict --refine: a proposal below the model's threshold stays only where the fit refined it
    refined_frame = refined_frame[refined_frame["refined"].astype(bool) | (refined_frame["score"] >= float(model.meta["threshold"]))].reset_index(drop=True)
    refined = {c: refined_frame[c].to_numpy() for c in refined_frame.columns}
    residual = None
    if look_in_residual:
        # as predict --refine: the network's proposals in the residual of the refined table, refined there
        start, core = time.perf_counter(), _core_seconds()
        threshold = REFINE_PROPOSAL_FRACTION * float(model.meta["threshold"])
        found = residual_particles(image, refined_frame, config, propose=lambda residual_image: predict_particles(
            residual_image, model, config, device="cpu", threshold=threshold).particles)
        union = pd.concat([refined_frame, found.assign(network_row=-1)], ignore_index=True)
        residual = {"found": len(found), "seconds": time.perf_counter() - start, "core_seconds": _core_seconds() - core,
                    "fit_only": score(refined, truth)[0],
                    "rows": [{c: float(found[c][i]) for c in ("x_um", "y_um", "z_um", "diameter_um", "index_contrast", "fit_residual")} for i in range(len(found))]}
        refined = {c: union[c].to_numpy() for c in union.columns}

    before, net_pairs = score(network, truth)
    after, ref_pairs = score(refined, truth)
    # as predict --material: the spheres' material kept, the rest set apart
    member = same_material(refined, index_contrast=INDEX_CONTRAST)
    gated, _ = score({c: v[member] for c, v in refined.items()}, truth)
    matched = np.zeros(len(member), dtype=bool)
    matched[ref_pairs[:, 0]] = True
    net_ids = np.flatnonzero(at_threshold)  # the network table's rows among the proposals
    kept = set(refined["network_row"].astype(int).tolist()) - {-1}  # the proposals the fit kept (-1: found in its residual)
    net_tp = set(net_ids[net_pairs[:, 0]].tolist())
    net_fp = set(net_ids.tolist()) - net_tp
    below = set(range(count)) - set(net_ids.tolist())
    ref_tp_rows = set(refined["network_row"][ref_pairs[:, 0]].astype(int).tolist())
    truth_of = {int(net_ids[r]): int(t) for r, t in net_pairs.tolist()}
    refined_row = {int(r): i for i, r in enumerate(refined["network_row"].astype(int))}

    def describe(row: int) -> dict:
        """A proposal: its guess, its fit and the truth the network's table matched it to (if any), for the rows refinement changed."""
        i = refined_row.get(row)
        entry = {"network": {c: float(proposals[c][row]) for c in ("x_um", "y_um", "z_um", "diameter_um", "score")}}
        if i is not None:
            entry["refined"] = {c: float(refined[c][i]) for c in ("x_um", "y_um", "z_um", "diameter_um", "index_contrast", "fit_residual")}
        if row in truth_of:
            entry["truth"] = {c: float(truth[c][truth_of[row]]) for c in ("x_um", "y_um", "z_um", "diameter_um")}
        return entry

    moved = sorted((net_tp & kept) - ref_tp_rows)
    result = {
        "hologram": name, "truth": len(truth["x_um"]), "detections": len(net_ids), "proposals": count, "kept": len(kept),
        "not_fitted": int(np.sum(~refined["refined"].astype(bool))),
        "network": before, "refined": after, "material": gated,
        "other_material": int(np.sum(~member)), "other_material_tp": int(np.sum(~member & matched)),
        "other_material_rows": [{c: float(refined[c][i]) for c in ("x_um", "y_um", "z_um", "diameter_um", "index_contrast", "index_err")}
                                for i in np.flatnonzero(~member)],
        "fp_dropped": len(net_fp - kept), "fp_kept": len(net_fp & kept),
        "tp_dropped": len(net_tp - kept),
        "tp_lost_by_moving": len((net_tp & kept) - ref_tp_rows),  # kept, but refit beyond the match tolerance
        "fp_turned_tp": len(net_fp & ref_tp_rows),
        "below_threshold_kept": len(below & kept), "below_threshold_tp": len(below & ref_tp_rows),
        "moved_tp": [describe(r) for r in moved], "kept_fp": [describe(r) for r in sorted(net_fp & kept)],
        "index_contrast_of_kept_fp": sorted(float(v) for v in refined["index_contrast"][[r in net_fp for r in refined["network_row"].astype(int)]]),
        "predict_s": predict_s, "predict_core_s": predict_core_s, "refine_s": refine_s, "refine_core_s": refine_core_s,
        "refine_s_per_particle": refine_s / max(count, 1), "refine_core_s_per_particle": refine_core_s / max(count, 1),
        "refine_over_predict": refine_s / predict_s,
    }
    if residual is not None:
        result["residual"] = residual
    if tables is not None:
        tables.mkdir(parents=True, exist_ok=True)
        write_particles(tables / f"{name}_network.csv", network, force=True)  # each run's tables replace the last run's
        write_particles(tables / f"{name}_refined.csv", refined, force=True)
    return result


def _line(label: str, s: dict) -> str:
    index = f" n-n_m {s['median_index_contrast']:.3f}" if "median_index_contrast" in s else ""
    dz = "-" if s["median_abs_dz_um"] is None else f"{s['median_abs_dz_um']:.1f}"
    dd = "-" if s["median_abs_dd_um"] is None else f"{s['median_abs_dd_um']:.2f}"
    return f"  {label:8s} ER {100 * s['er']:6.2f} % JI {s['ji']:.3f} TP {s['tp']:3d} FP {s['fp']:3d} FN {s['fn']:3d} |dz| {dz} um |dd| {dd} um{index}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", required=True, type=Path, help="trained model (.pt)")
    parser.add_argument("--holograms", required=True, type=Path, help="folder of the holograms and their *_truth.csv (missing ones are made)")
    parser.add_argument("--set", choices=list(SETS), default="development", help="the development holograms or the frozen test set")
    parser.add_argument("--only", nargs="+", choices=list(HOLOGRAMS), help="holograms to run (default: the set's, in the listed order)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "refine" / f"detection_{datetime.date.today().isoformat()}.json")
    parser.add_argument("--tables", type=Path, help="folder for each hologram's network and refined tables (CSV)")
    parser.add_argument("--rounds", type=int, default=RefineSettings().rounds, help="fitting rounds (RefineSettings.rounds)")
    parser.add_argument("--residual", action="store_true", help="also the particles found in the residual of the refined table (residual_particles)")
    args = parser.parse_args(argv)
    args.holograms.mkdir(parents=True, exist_ok=True)
    config = load_config(None)
    model = load_model(args.model, device="cpu")
    report = {"model": str(args.model), "holograms": str(args.holograms), "threads": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "NAPARI_LBS_THREADS")},
              "index_contrast_truth": INDEX_CONTRAST, "rounds": args.rounds, "results": []}
    for name in args.only or SETS[args.set]:
        image, truth = hologram(args.holograms, name)
        load_before = os.getloadavg()
        result = evaluate(name, image, truth, model, config, tables=args.tables, rounds=args.rounds, look_in_residual=args.residual)
        result["load_average"] = [load_before, os.getloadavg()]
        report["results"].append(result)
        print(f"{name}: {result['truth']} spheres, {result['detections']} detections ({result['proposals']} proposals), {result['kept']} kept by the fit "
              f"({result['not_fitted']} not refined: outside the hologram or no fit inside the bounds)", flush=True)
        print(_line("network", result["network"]), flush=True)
        print(_line("refined", result["refined"]), flush=True)
        print(_line("material", result["material"]) + f" ({result['other_material']} of another material set apart, {result['other_material_tp']} of them matched)",
              flush=True)
        print(f"  FP dropped {result['fp_dropped']}/{result['fp_dropped'] + result['fp_kept']}, TP dropped {result['tp_dropped']}, "
              f"TP moved out of tolerance {result['tp_lost_by_moving']}, FP turned TP {result['fp_turned_tp']}, "
              f"proposals below the threshold kept {result['below_threshold_kept']} ({result['below_threshold_tp']} TP); "
              f"refine {result['refine_s_per_particle']:.2f} s/particle wall, {result['refine_core_s_per_particle']:.2f} core-s/particle, "
              f"{result['refine_over_predict']:.0f}x the network's {result['predict_s']:.1f} s; load {load_before[0]:.2f}", flush=True)
        if "residual" in result:
            print(_line("fit only", result["residual"]["fit_only"]) + f" (the refined rows above add the {result['residual']['found']} particles found in its "
                  f"residual in {result['residual']['seconds']:.1f} s)", flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.out, report)
    print(f"-> {args.out}", flush=True)


if __name__ == "__main__":
    main()
