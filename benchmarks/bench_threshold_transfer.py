"""Which detection threshold transfers from synthetic validation to holograms of another forward model.

A trained network's detections are kept above a threshold chosen on its synthetic validation
groups. Two rules, both computed here by validating each network again under the current code:

* **peak** — the threshold of the best validation JI (the rule before the one-standard-error
  rule);
* **kept** — the highest threshold reached from the peak upwards without the validation JI
  falling one binomial standard error below the peak (`napari_lbs._core.learning._formulations`).

Each network's table (`predict_particles`, no refinement) is made once at the decoder's floor
(0.05) and scored at both thresholds and at every hundredth, on holograms of an independent
Lorenz–Mie model:

* ``lensless`` networks (the demo's recipe): `bench_pseudoreal.py`'s holograms with the seed
  `LENSLESS_SEED` — the real density's 100 spheres, alone and with distractors — default
  tolerances (22 µm lateral, 150 µm axial);
* ``microscope`` networks (`bench_microscopy_lbs.py`'s recipe): that benchmark's ``frozen-3``
  frames (six pylorenzmie frames of 20–50 spheres), pooled, with its tolerances (0.5 µm, 2 µm).

Frozen design, written before the first run and not changed after it: the networks are the
demo recipe's epochs 4 and 5 for training seeds 0 and 1 (the data set of ``napari-lbs demo``,
seed 0) and the microscope recipe's epochs 1, 2 and 3 (training seed 0) — eleven (network,
test set) pairs. The kept rule is adopted when its JI is higher than the peak rule's in more
pairs than it is lower, and lower by more than 0.02 in none.

The networks, every validated epoch of a training written as its own model file (``epochs``
mode; the demo's data set is ``napari-lbs demo``'s ``data`` folder, the microscope's
``bench_microscopy_lbs.py``'s ``data_g96``), then the scoring:

    python benchmarks/bench_threshold_transfer.py epochs DEMO_DATA /tmp/demo-s1 --epochs 5 --seed 1 --validate-last 2
    python benchmarks/bench_threshold_transfer.py epochs MICRO_DATA /tmp/micro-s0 --epochs 3 --seed 0
    python benchmarks/bench_threshold_transfer.py score --work /tmp/threshold-transfer \\
        --lensless DEMO_DATA E4.pt E5.pt ... --microscope MICRO_DATA E1.pt ... --out F.json
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

LENSLESS_SEED = 20261214
THRESHOLDS = tuple(round(0.05 + 0.01 * step, 2) for step in range(91))


def validated(model: Path, data: Path) -> dict:
    """The model's network validated again on its data set's validation groups under the current rule."""
    import torch

    from napari_lbs._core import TrainingSettings, load_model, open_dataset
    from napari_lbs._core.learning import _formulations

    from napari_lbs._core.learning._training import split_groups

    loaded = load_model(model)
    dataset = open_dataset(data)
    training, validation = split_groups(dataset, validation_groups=loaded.meta["settings"]["validation_groups"])
    settings = TrainingSettings(context=tuple(loaded.meta["context"]))
    formulation = _formulations._FocusFormulation(dataset, training[:1], settings, torch.device("cpu"))
    metrics = formulation.validate(loaded.network, validation, lambda: False)
    return {key: metrics[key] for key in ("threshold", "ji", "peak_threshold", "peak_ji", "axial_um")}


def write_epoch_models(data: Path, out_dir: Path, *, epochs: int, seed: int, validate_last: int, average_last: int = 0) -> list[Path]:
    """Train as `train_model` does and write every validated epoch's network as ``epochN.pt`` (its own kept threshold in it).

    ``kept.pt`` is the model `train_model` keeps (with ``average_last``, the epochs' mean).

    `train_model` keeps one model; the network object is taken from the formulation that builds
    it, and each validated epoch's weights are copied in the ``report`` callback (called right
    after that epoch's validation).
    """
    import io

    import torch

    from napari_lbs._core import TrainingSettings, train_model
    from napari_lbs._core.learning import _formulations

    held, states = {}, {}
    build = _formulations._FocusFormulation.network

    def network(self):
        held["network"] = build(self)
        return held["network"]

    def report(record: dict) -> None:
        if "validation" in record:
            states[record["epoch"]] = ({k: v.detach().cpu().clone() for k, v in held["network"].state_dict().items()}, record["validation"])

    out_dir.mkdir(parents=True, exist_ok=True)
    kept = out_dir / "kept.pt"
    _formulations._FocusFormulation.network = network
    try:
        train_model(data, kept, settings=TrainingSettings(epochs=epochs, seed=seed, device="cpu", validate_last=validate_last, average_last=average_last),
                    force=True, report=report)
    finally:
        _formulations._FocusFormulation.network = build
    payload = torch.load(kept, weights_only=True)
    paths = []
    for epoch, (state, validation) in sorted(states.items()):
        meta = {k: v for k, v in json.loads(payload["meta"]).items() if k != "averaged_epochs"} | {
            "epoch": epoch, "threshold": validation["threshold"], "axial_um": validation["axial_um"],
            "validation": {k: v for k, v in validation.items() if k != "by_threshold"}}
        buffer = io.BytesIO()
        torch.save({**payload, "state_dict": state, "meta": json.dumps(meta)}, buffer)
        paths.append(out_dir / f"epoch{epoch}.pt")
        paths[-1].write_bytes(buffer.getvalue())
    return paths


def curve(tables: list[tuple[dict, dict]], **tolerances: float) -> dict[float, dict]:
    """Pooled TP/FP/FN and JI at every threshold of `THRESHOLDS` of tables made at the decoder's floor (``tolerances``: `score_particles`' own where not given)."""
    from napari_lbs._core import score_particles

    out = {}
    for threshold in THRESHOLDS:
        totals = np.zeros(3, int)
        for table, truth in tables:
            keep = table["score"] >= threshold - 1e-9
            metrics = score_particles({k: v[keep] for k, v in table.items()}, truth, **tolerances)
            totals += [metrics["tp"], metrics["fp"], metrics["fn"]]
        out[threshold] = {"tp": int(totals[0]), "fp": int(totals[1]), "fn": int(totals[2]), "ji": float(totals[0] / max(totals.sum(), 1))}
    return out


def model_curve(model: Path, holograms: list[tuple[np.ndarray, dict]], tolerances: dict) -> dict[float, dict]:
    """`curve` of the model's tables (`predict_particles`, no refinement) made once at the decoder's floor."""
    from napari_lbs._core import predict_particles

    tables = [({k: np.asarray(v) for k, v in predict_particles(hologram, model, device="cpu", threshold=THRESHOLDS[0]).particles.items()}, truth)
              for hologram, truth in holograms]
    return curve(tables, **tolerances)


def test_sets(work: Path, *, lensless_seed: int = LENSLESS_SEED, microscope_set: str = "frozen-3") -> dict[str, list[tuple[str, list[tuple[np.ndarray, dict]], dict]]]:
    """Per setup: (name, [(hologram, truth)], tolerances): pseudo-real holograms of ``lensless_seed``, the microscope set ``microscope_set``."""
    import bench_microscopy_lbs
    import bench_pseudoreal

    from napari_lbs._core import read_hologram, read_particles

    lensless_dir = work / "lensless"
    lensless_dir.mkdir(parents=True, exist_ok=True)
    count = bench_pseudoreal.DENSITIES["real density"]
    lensless = [
        ("real density", [bench_pseudoreal._hologram(lensless_dir, "real_density", count, seed=lensless_seed)], {}),
        ("with distractors", [bench_pseudoreal._hologram(lensless_dir, "real_density_distractors", count, seed=lensless_seed, distractors=bench_pseudoreal.WITH_DISTRACTORS)], {}),
    ]
    frames = [(read_hologram(image), {k: np.asarray(v) for k, v in read_particles(truth).items()}) for image, truth in bench_microscopy_lbs.frames_of(microscope_set, work / "microscope")]
    tolerances = {"lateral_tol_um": bench_microscopy_lbs.LATERAL_TOL_UM, "axial_tol_um": bench_microscopy_lbs.AXIAL_TOL_UM}
    return {"lensless": lensless, "microscope": [(microscope_set, frames, tolerances)]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    modes = parser.add_subparsers(dest="mode", required=True)
    epochs = modes.add_parser("epochs", help="train and write every validated epoch's model")
    epochs.add_argument("data", type=Path)
    epochs.add_argument("out_dir", type=Path)
    epochs.add_argument("--epochs", type=int, required=True)
    epochs.add_argument("--seed", type=int, default=0)
    epochs.add_argument("--validate-last", type=int, default=0)
    score = modes.add_parser("score", help="score the models at the peak and the kept threshold")
    score.add_argument("--work", type=Path, required=True, help="test holograms cached here")
    score.add_argument("--lensless", nargs="+", default=[], metavar="DATA_OR_MODEL", help="the demo's data set folder, then its models")
    score.add_argument("--microscope", nargs="+", default=[], metavar="DATA_OR_MODEL", help="the microscope data set folder, then its models")
    score.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.mode == "epochs":
        for path in write_epoch_models(args.data, args.out_dir, epochs=args.epochs, seed=args.seed, validate_last=args.validate_last):
            print(path, flush=True)
        return
    from napari_lbs._core.foundation import process_threads

    load_before = os.getloadavg()
    sets = test_sets(args.work)
    rows, better, worse = [], 0, 0
    for setup, given in (("lensless", args.lensless), ("microscope", args.microscope)):
        if not given:
            continue
        data, models = Path(given[0]), [Path(m) for m in given[1:]]
        for model in models:
            rule = validated(model, data)
            for name, holograms, tolerances in sets[setup]:
                started = time.perf_counter()
                by_threshold = model_curve(model, holograms, tolerances)
                peak, kept = by_threshold[round(rule["peak_threshold"], 2)], by_threshold[round(rule["threshold"], 2)]
                best = max(by_threshold, key=lambda t: by_threshold[t]["ji"])
                better += kept["ji"] > peak["ji"]
                worse += kept["ji"] < peak["ji"]
                row = {"setup": setup, "model": str(model), "test": name, "validation": rule, "peak": peak, "kept": kept,
                       "best_on_test": {"threshold": best, **by_threshold[best]}, "seconds": round(time.perf_counter() - started, 1),
                       "by_threshold": {f"{t:.2f}": v for t, v in by_threshold.items()}}
                rows.append(row)
                print(f"{setup} {model} {name}: peak {rule['peak_threshold']:.2f} JI {peak['ji']:.3f} ({peak['tp']}/{peak['fp']}/{peak['fn']}); "
                      f"kept {rule['threshold']:.2f} JI {kept['ji']:.3f} ({kept['tp']}/{kept['fp']}/{kept['fn']}); best on test {best:.2f} JI {by_threshold[best]['ji']:.3f}", flush=True)
    largest_drop = max((r["peak"]["ji"] - r["kept"]["ji"] for r in rows), default=0.0)
    verdict = {"higher": better, "lower": worse, "pairs": len(rows), "largest_drop": largest_drop, "adopted": better > worse and largest_drop <= 0.02}
    print(json.dumps(verdict), flush=True)
    result = {"rows": rows, "verdict": verdict, "threads": process_threads(), "load_before": load_before, "load_after": os.getloadavg()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
