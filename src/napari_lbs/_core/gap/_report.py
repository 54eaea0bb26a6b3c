"""The diagnosis written out: ``report.json`` (docs/formats.md), ``report.md`` and the two figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from napari_lbs._core.gap._diagnose import Diagnosis
from napari_lbs._core.foundation import atomic_path, atomic_write_bytes, check_target, write_json

__all__ = ["write_report"]


_FILES = ("report.json", "report.md", "gap_where.png", "gap_effects.png")


def write_report(diagnosis: Diagnosis, out_dir, *, provenance: dict | None = None, force: bool = False) -> list:
    """Write ``report.json`` (docs/formats.md), ``report.md`` and PNG figures into ``out_dir``; return the paths.

    An existing file of those names is replaced only with ``force`` (and never a link, FIFO,
    device or folder): every name is checked before anything is written.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    out = Path(out_dir)
    for name in _FILES:
        check_target(out / name, force=force)
    out.mkdir(parents=True, exist_ok=True)
    report = {**diagnosis.report, "provenance": provenance or {}}
    gap = report["gap"]
    paths = [write_json(out / "report.json", report, force=force)]

    figure = Figure(figsize=(11, 3.4), tight_layout=True)
    axes = figure.subplots(1, 3)
    axes[0].plot([np.nan if b["told_apart"] is None else b["told_apart"] for b in gap["by_band"]], "o-", color="tab:blue")
    axes[0].set_xticks(range(len(gap["by_band"])), [b["band"].split()[2].split("-")[0] for b in gap["by_band"]], rotation=45, fontsize=7)
    axes[0].set_xlabel("spatial-frequency band from (cycles/px)")
    axes[0].set_ylabel("told apart: 2 (C2ST accuracy − 0.5)")
    axes[0].set_ylim(0, 1)
    axes[0].set_title("where: by frequency band")
    axes[1].plot([d["depth_um"] for d in gap["by_depth"]], [np.nan if d["told_apart"] is None else d["told_apart"] for d in gap["by_depth"]], "s-", color="tab:orange")
    axes[1].set_xlabel("back-propagation depth (µm)")
    axes[1].set_ylim(0, 1)
    axes[1].set_title("where: by depth")
    image = axes[2].imshow(diagnosis.tile_map, cmap="magma", vmin=0.0, vmax=1.0)
    bar = figure.colorbar(image, ax=axes[2])
    bar.set_label("P(tile is the experiment's), held out")
    axes[2].set_title(f"where: by tile ({report['tiles']['tile_px']} px tiles)")
    axes[2].set_xlabel("tile column")
    axes[2].set_ylabel("tile row")
    with atomic_path(out / "gap_where.png", force=force) as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    paths.append(out / "gap_where.png")

    figure = Figure(figsize=(11, 3.6), tight_layout=True)
    axes = figure.subplots(1, 2)
    posterior = list(report["posterior"].items())[:10]
    axes[0].barh([k for k, _ in posterior][::-1], [v for _, v in posterior][::-1], color="tab:green")
    axes[0].axvline(report["settings"]["level"], color="k", lw=0.8, ls="--")
    axes[0].set_xlim(0, 1)
    axes[0].set_xlabel("posterior probability of the model")
    axes[0].set_title(f"which: verdict {report['verdict']['id'] or 'none named'}")
    effects = report["effects"]
    axes[1].barh([e["id"] for e in effects][::-1], [e["gap_after"] for e in effects][::-1], color="tab:purple")
    axes[1].axvline(gap["baseline"], color="k", lw=0.8, ls="--", label="baseline (nothing added)")
    axes[1].set_xlabel("gap with the effect added (MMD²)")
    axes[1].legend(fontsize=7)
    axes[1].set_title("how much: the gap with each effect")
    with atomic_path(out / "gap_effects.png", force=force) as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    paths.append(out / "gap_effects.png")

    verdict = report["verdict"]
    named = verdict["id"] or ("nothing missing" if not verdict["undecided"] else "undecided between " + " and ".join(verdict["undecided"]))
    lines = [
        "# Sim-to-real gap diagnosis",
        "",
        f"- Verdict: **{named}** ({verdict['reason']}).",
        f"- Gap between the experiment and the seed's simulator: **{gap['baseline']:.2f}** (90 % interval {gap['baseline_interval'][0]:.2f} to {gap['baseline_interval'][1]:.2f}; {gap['metric']}).",
        f"- With the verdict added: {verdict['residual']:.2f} (shrink {100 * verdict['shrink']:.0f} %)." if verdict["id"] else "- Nothing added.",
        f"- The catalog {'explains' if verdict['catalog_explains'] else 'does not explain'} the gap.",
        f"- Known, not diagnosed (what the file states and what you stated): {_known_text(report)}",
        f"- Data: {report['tiles']['frames']} frame(s), {report['tiles']['per_frame']} tiles of {report['tiles']['tile_px']} px each; "
        f"diagnoser {report['diagnoser']['key']} ({report['diagnoser']['simulations']} simulations); {report['seconds']:.0f} s.",
        "",
        "## Posterior (which model: nothing missing, one effect, or two)",
        "",
        "| model | probability |",
        "|---|---|",
        *[f"| {k} | {v:.3f} |" for k, v in report["posterior"].items() if v >= 0.005],
        "",
        "## Effects",
        "",
        "| effect | P(present) | gap after | shrink | parameters (median; 90 % interval) |",
        "|---|---|---|---|---|",
        *[
            f"| {e['id']} | {e['probability']:.2f} | {e['gap_after']:.2f} | {100 * e['shrink']:.0f} % | "
            + ", ".join(f"{k} {v:.3g}" + (f" ({e['intervals'][k][0]:.3g} to {e['intervals'][k][1]:.3g})" if k in e["intervals"] else "") for k, v in e["params"].items()) + " |"
            for e in effects
        ],
        "",
        "![effects](gap_effects.png)",
        "",
        "## Where the gap lies",
        "",
        "Most unlike the simulation: " + "; ".join(f"tile at x {t['x_px']} px, y {t['y_px']} px (P {t['probability']:.2f})" for t in gap["tiles"]["most_unlike"]) + ".",
        "",
        "![where](gap_where.png)",
        "",
    ]
    paths.append(out / "report.md")
    atomic_write_bytes(out / "report.md", "\n".join(lines).encode("utf-8"), force=force)
    return paths


def _known_text(report: dict) -> str:
    known = report.get("known") or {}
    sensor = report.get("known_sensor", {})
    if not known:
        if sensor.get("coarse"):
            return (f"nothing: the {sensor['source']} uses {100 * sensor['levels_used']:.0f} % of the levels within its range "
                    f"(about {sensor['effective_bits']:.1f} bits of its {sensor['bits']}), so the bit depth is diagnosed, not taken from the format.")
        return "nothing."
    stated = report.get("stated") or {}
    from_file = "; ".join(f"{effect_id} {params}" for effect_id, params in known.items() if effect_id not in stated)
    parts = [from_file + (f" (from the {sensor['source']})" if "source" in sensor else "")] if from_file else []
    parts += ["; ".join(f"{effect_id} {known[effect_id]}" for effect_id in stated) + " (stated by you)"] if stated else []
    return "; ".join(parts) + "."
