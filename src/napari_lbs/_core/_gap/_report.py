"""The diagnosis written out: ``report.json`` (CONTRACT.md), ``report.md`` and the two figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from napari_lbs._core._gap._diagnose import Diagnosis
from napari_lbs._core._files import atomic_path, atomic_write_bytes, write_json

__all__ = ["write_report"]


def write_report(diagnosis: Diagnosis, out_dir, *, provenance: dict | None = None) -> list:
    """Write ``report.json`` (CONTRACT.md), ``report.md`` and PNG figures into ``out_dir``; return the paths."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = {**diagnosis.report, "provenance": provenance or {}}
    gap = report["gap"]
    paths = [write_json(out / "report.json", report)]

    figure = Figure(figsize=(11, 3.4), tight_layout=True)
    axes = figure.subplots(1, 3)
    groups = list(gap["by_group"])
    axes[0].bar(groups, [gap["by_group"][g] for g in groups], color="tab:blue")
    axes[0].axhline(1.0, color="k", lw=0.8, ls="--")
    axes[0].set_ylabel("distance (1 = two real tiles)")
    axes[0].set_title("where: by kind of statistic")
    axes[0].tick_params(axis="x", rotation=45)
    axes[1].plot([b["distance"] for b in gap["by_band"]], "o-", label="spatial-frequency band (low → high)")
    axes[1].plot([d["distance"] for d in gap["by_depth"]], "s-", label="depth summaries (near → far)")
    axes[1].axhline(1.0, color="k", lw=0.8, ls="--")
    axes[1].legend(fontsize=7)
    axes[1].set_title("where: by band and by depth")
    tiles = np.asarray(gap["by_region"])
    side = int(round(np.sqrt(tiles.size)))
    if side * side == tiles.size:
        image = axes[2].imshow(tiles.reshape(side, side), cmap="magma")
        figure.colorbar(image, ax=axes[2])
    else:
        axes[2].bar(range(tiles.size), tiles)
    axes[2].set_title("where: by region (each real tile)")
    with atomic_path(out / "gap_where.png") as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    paths.append(out / "gap_where.png")

    figure = Figure(figsize=(11, 3.4), tight_layout=True)
    axes = figure.subplots(1, 2)
    effects = report["effects"]
    axes[0].barh([e["id"] + ("" if e["confirmed"] else " (screened)") for e in effects][::-1], [max(e["shrink"], -1.0) for e in effects][::-1], color=["tab:green" if e["confirmed"] else "tab:gray" for e in effects][::-1])
    axes[0].axvline(0.0, color="k", lw=0.8)
    axes[0].set_xlabel("shrink of the gap on held-out tiles")
    axes[0].set_title(f"effects ranked; verdict: {report['verdict']['id']}")
    steps = report["waterfall"]
    axes[1].bar([s["model"] for s in steps], [s["gap"] for s in steps], color="tab:purple")
    axes[1].set_ylabel("gap (excess χ²)")
    axes[1].set_title("waterfall: effects added greedily")
    axes[1].tick_params(axis="x", rotation=20)
    with atomic_path(out / "gap_effects.png") as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    paths.append(out / "gap_effects.png")

    verdict = report["verdict"]
    lines = [
        "# Sim-to-real gap diagnosis",
        "",
        f"- Gap between the experiment and the seed's simulator (baseline): **{gap['baseline']:.2f}** ({gap['metric']}).",
        f"- Verdict: **{verdict['id'] or 'none named (null)'}**; shrink {100 * verdict['shrink']:.0f} % "
        f"(90 % interval {100 * verdict['interval'][0]:.0f} to {100 * verdict['interval'][1]:.0f} %), residual gap {verdict['residual']:.2f}. Why: {verdict['reason']}.",
        f"- Data that would decide: {_tiles_to_decide_text(verdict, report['tiles'])}",
        f"- Known, not diagnosed (what the file states and what you stated): {_known_text(report)}",
        f"- Time: {report['seconds']:.0f} s; tiles: {report['tiles']}.",
        "",
        "## Where the gap lies (1 = as different as two tiles of the experiment)",
        "",
        "| kind | distance |",
        "|---|---|",
        *[f"| {g} | {v:.2f} |" for g, v in gap["by_group"].items()],
        "",
        "Largest single differences:",
        "",
        *[f"- {s['name']} ({s['group']}): real {s['real']:.4g}, simulated {s['sim']:.4g}, distance {s['distance']:.1f}" for s in sorted(gap["summaries"], key=lambda s: -s["distance"])[:8]],
        "",
        "![where](gap_where.png)",
        "",
        "## Effects",
        "",
        "Evidence: the χ² an effect removes on the held-out tiles, summed over its own summaries (those it moves by at least one sampling error).",
        "",
        "| effect | confirmed (refitted) | evidence: χ² removed on its summaries (90 % interval) | gap after | shrink (90 % interval) | gap with it switched off in its own fit | screening t |",
        "|---|---|---|---|---|---|---|",
        *[
            f"| {e['id']} | {'yes' if e['confirmed'] else 'no'} | "
            f"{'{:.1f} on {} ({:.1f} to {:.1f})'.format(e['evidence']['reduction'], e['evidence']['summaries'], *e['evidence']['interval']) if 'evidence' in e else '—'} | "
            f"{e['gap_after']:.2f} | {100 * e['shrink']:.0f} %"
            f"{' ({:.0f} to {:.0f} %)'.format(*(100 * v for v in e['shrink_interval'])) if 'shrink_interval' in e else ''} | "
            f"{format(e['gap_ablated'], '.2f') if 'gap_ablated' in e else '—'} | {e['screening']['t']:.1f} |"
            for e in effects
        ],
        "",
        "![effects](gap_effects.png)",
        "",
    ]
    paths.append(out / "report.md")
    atomic_write_bytes(out / "report.md", "\n".join(lines).encode("utf-8"))
    return paths


def _tiles_to_decide_text(verdict: dict, tiles: dict) -> str:
    needed = verdict.get("tiles_to_decide")
    if needed is None:
        return "no amount of data: the best effect does not improve on the baseline or on the runner-up."
    if needed <= tiles["held_out"]:
        return f"these {tiles['held_out']} held-out tiles suffice."
    # cross-fitted, every tile is held out once; else half of them are
    in_all = needed if tiles.get("cross_fitted") else 2 * needed
    return f"about {needed} held-out tiles of {tiles['shape'][0]}x{tiles['shape'][1]} px (now {tiles['held_out']}), i.e. about {in_all} tiles in all, if the margins stay as measured."


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
