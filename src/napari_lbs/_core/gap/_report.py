"""The diagnosis written out: ``report.json`` (docs/formats.md), ``report.md`` and the two figures."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from napari_lbs._core.foundation import atomic_path, atomic_write_bytes, check_target, json_safe, write_json

if TYPE_CHECKING:  # for the annotations only
    from napari_lbs._core.gap._scene_diagnosis import SceneDiagnosis, SceneDiagnosisSettings

__all__ = ["parameter_text", "write_report"]


_FILES = ("report.json", "report.md", "gap_where.png", "gap_effects.png")


def write_report(diagnosis: SceneDiagnosis, out_dir, *, settings: SceneDiagnosisSettings | None = None, provenance: dict | None = None, force: bool = False) -> list:
    """Write ``report.json`` (docs/formats.md), ``report.md`` and PNG figures into ``out_dir``; return the paths.

    Parameters
    ----------
    diagnosis : SceneDiagnosis
        Its ``report``, ``tile_map`` and ``seconds``.
    out_dir : path
        The folder (made where missing).
    settings : SceneDiagnosisSettings, optional
        The settings the diagnosis ran with (default: the defaults): recorded as the report's
        ``settings`` and drawn as the levels a decision needs.
    provenance : dict, optional
        What made the report (recorded as its ``provenance``).
    force : bool
        Replace existing files of those names (never a link, FIFO, device or folder): every
        name is checked before anything is written.
    """
    from napari_lbs._core.gap._scene_diagnosis import SceneDiagnosisSettings

    out = Path(out_dir)
    for name in _FILES:
        check_target(out / name, force=force)
    out.mkdir(parents=True, exist_ok=True)
    levels = settings or SceneDiagnosisSettings()
    report = {**diagnosis.report, "seconds": diagnosis.seconds, "settings": json_safe(asdict(levels)), "provenance": provenance or {}}
    paths = [write_json(out / "report.json", report, force=force)]
    with atomic_path(out / "gap_where.png", force=force) as temporary:
        _where_figure(report, np.asarray(diagnosis.tile_map, float), levels).savefig(temporary, dpi=110, format="png")
    paths.append(out / "gap_where.png")
    with atomic_path(out / "gap_effects.png", force=force) as temporary:
        _effects_figure(report, levels).savefig(temporary, dpi=110, format="png")
    paths.append(out / "gap_effects.png")
    atomic_write_bytes(out / "report.md", "\n".join(_summary(report, levels)).encode("utf-8"), force=force)
    paths.append(out / "report.md")
    return paths


def _figure(size: tuple[float, float], columns: int, widths=None):
    """A matplotlib figure (no display needed) and its row of axes."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    figure = Figure(figsize=size, layout="constrained")
    return figure, figure.subplots(1, columns, width_ratios=widths)


def _value(value) -> float:
    """``value`` as a float, NaN where it is missing (None) or not finite."""
    return float(value) if value is not None and np.isfinite(value) else float("nan")


def _text(value, spec: str = ".3g") -> str:
    """``value`` formatted by ``spec``, or a dash where it is missing."""
    number = _value(value)
    return "—" if np.isnan(number) else format(number, spec)


def parameter_text(effect: dict) -> str:
    """A report effect's parameters as ``name value ± error, ...`` (the errors to two significant figures).

    A parameter whose ``params_err`` is null (on a bound of its fit) reads ``(no error
    bar)``; an effect without ``params_err`` (read, not fitted: the converter's bits) shows
    its values alone. Empty where the effect has no parameters.
    """
    errors = effect.get("params_err")
    parts = []
    for name, value in effect["params"].items():
        text = f"{name} {_text(value)}"
        if errors is not None:
            error = errors.get(name)
            text += " (no error bar)" if np.isnan(_value(error)) else f" ± {_text(error, '.2g')}"
        parts.append(text)
    return ", ".join(parts)


def _where_figure(report: dict, tile_map: np.ndarray, levels: SceneDiagnosisSettings):
    """Where: each tile's unexplained share (with the level the catalog explains a frame at), the residual's power by band, and by the particles' depth."""
    gap = report["gap"]
    by_depth = [group for group in gap.get("by_depth") or [] if group["pixels"]]
    if by_depth:
        figure, (tiles, bands, depths) = _figure((15, 4.0), 3, widths=(1.0, 1.35, 1.0))
    else:
        figure, (tiles, bands) = _figure((11, 4.0), 2, widths=(1.0, 1.35))
    shown = tile_map[np.isfinite(tile_map)]
    top = max(float(shown.max()) if shown.size else 0.0, 1.5 * levels.structure_level)
    image = tiles.imshow(tile_map, cmap="magma", vmin=0.0, vmax=top)
    bar = figure.colorbar(image, ax=tiles)
    bar.set_label("unexplained share of the tile's structure")
    bar.ax.axhline(levels.structure_level, color="tab:cyan", lw=2)
    bar.ax.text(1.05, levels.structure_level / top, " level", transform=bar.ax.transAxes, color="tab:cyan", fontsize=7, va="center", clip_on=False)
    if tile_map.shape[0] <= 8:
        for (row, col), share in np.ndenumerate(tile_map):
            if np.isfinite(share):
                tiles.text(col, row, f"{share:.2g}", ha="center", va="center", fontsize=8, color="white" if share < 0.6 * top else "black")
    tiles.set_xticks(range(tile_map.shape[1]))
    tiles.set_yticks(range(tile_map.shape[0]))
    tiles.set_xlabel("tile column")
    tiles.set_ylabel("tile row")
    tiles.set_title(f"where: {tile_map.shape[0]} × {tile_map.shape[1]} tiles of {gap['tile_px']} px", fontsize=10)
    by_band = gap["by_band"]
    names = [f"{low:g}–{high:g}" for low, high in (b["cycles_per_px"] for b in by_band)]
    place = np.arange(len(by_band))
    bands.bar(place - 0.2, [_value(b["share_of_power"]) for b in by_band], 0.4, color="tab:gray", label="all of its power")
    bands.bar(place + 0.2, [_value(b["structured"]) for b in by_band], 0.4, color="tab:orange", label="structured (above its white floor)")
    bands.set_xticks(place, names)
    bands.set_xlabel("spatial frequency band (cycles per pixel)")
    bands.set_ylabel("share of the held-out residual's power")
    bands.set_title("what is left: the residual by frequency band", fontsize=10)
    bands.legend(fontsize=8)
    if by_depth:
        depth_mm = [group["z_um"] / 1000.0 for group in by_depth]
        depths.plot(depth_mm, [_value(group["baseline"]) for group in by_depth], "o-", color="tab:gray", label="the scene alone")
        depths.plot(depth_mm, [_value(group["after"]) for group in by_depth], "o-", color="tab:orange", label="with the named effects")
        depths.set_ylim(bottom=0.0)
        depths.set_xlabel("particles' depth (mm; a group each)")
        depths.set_ylabel("unexplained share of the structure about them")
        depths.set_title("what is left, by the particles' depth", fontsize=10)
        depths.legend(fontsize=8)
    return figure


def _effects_figure(report: dict, levels: SceneDiagnosisSettings):
    """Which and how much: each effect's held-out z with the selection level, and the gap with each effect added."""
    effects = report["effects"][::-1]  # best at the top
    names = [e["id"] for e in effects]
    colours = ["tab:red" if e["selected"] else "tab:gray" for e in effects]
    figure, (which, how_much) = _figure((11, 4.4), 2)
    z = [_value(e.get("z")) for e in effects]
    which.barh(names, np.nan_to_num(z), color=colours)
    for row, (value, effect) in enumerate(zip(z, effects, strict=True)):
        if np.isnan(value):  # no likelihood: the levels of integer counts (quantization), or not fitted
            note = ("read from the counts' levels: " + ("named" if effect["selected"] else "not named")) if "levels" in effect else "not fitted"
            which.text(0, row, " " + note, va="center", fontsize=7)
    which.axvline(levels.level_z, color="k", lw=0.8, ls="--", label=f"selection level z = {levels.level_z:g}")
    which.axvline(0, color="k", lw=0.5)
    which.set_xlabel("held-out gain z (a sign test over the held-out tiles)")
    which.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    which.set_title(f"which: {_named(report['verdict'])} (red: selected)", fontsize=10)
    gap = report["gap"]
    how_much.barh(names, [_value(e.get("gap_after")) for e in effects], color=colours)
    how_much.axvline(gap["baseline"], color="k", lw=0.8, ls="--", label="the scene alone")
    how_much.axvline(levels.structure_level, color="tab:cyan", lw=1.2, ls=":", label="the catalog explains a frame below")
    how_much.set_xlabel("unexplained share with the effect added")
    how_much.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncols=2)
    how_much.set_title("how much: the gap with each effect", fontsize=10)
    return figure


def _optics_lines(optics: dict, level_z: float) -> list[str]:
    """``report.md``'s particle optics: the decision, each view's votes and errors, the sizes."""
    spectrum, focus = optics.get("power_spectrum") or {}, optics.get("through_focus") or {}
    lines = [f"- {optics['particles']} of the scene's particles rendered as opaque spheres and as transparent ones, through a camera blur of "
             f"{_text(optics.get('camera_blur_px'))} px: **{optics['model']}** (combined z {_text(optics['z'], '.2f')}; named from ±{level_z:g}).",
             f"- Index contrast n_p − n_m {_text(optics.get('index_contrast'))} (the spectrum's best transparent model); diameter "
             f"{_text(optics['diameter_median_um'])} µm (quartiles {_range(optics['diameter_quartiles_um'])} µm)."]
    if spectrum:
        lines.append(f"- Fine rings' spectrum: the transparent model predicts {spectrum['transparent_better']} held-out tiles better and "
                     f"{spectrum['transparent_worse']} worse (z {_text(spectrum['z'], '.2f')}); mean squared log ratio (slope: near 1 for the "
                     "model the frame holds): " + "; ".join(f"{'opaque' if name == 'opaque' else 'transparent ' + name} {_text(value)} "
                                                           f"(slope {_text(spectrum['slope'].get(name))})" for name, value in spectrum["heldout_error"].items()) + ".")
    if focus:
        lines.append(f"- Through focus: {focus['transparent_better']} of {focus['spheres']} spheres within the config's sizes are nearer a "
                     f"transparent model, {focus['transparent_worse']} nearer the opaque one (z {_text(focus['z'], '.2f')}; nearest contrast "
                     f"{_text(focus.get('index_contrast'))}); mean summed squared difference of the axis profiles: "
                     + "; ".join(f"{'opaque' if name == 'opaque' else 'transparent ' + name} {_text(value)}" for name, value in focus["profile_distance"].items()) + ".")
    return lines


def _summary(report: dict, levels: SceneDiagnosisSettings) -> list[str]:
    """``report.md``'s lines: the verdict and why, each effect, the particles' optics, what is left, what was not tested."""
    verdict, gap, optics = report["verdict"], report["gap"], report["particle_optics"]
    lines = [
        "# Sim-to-real gap diagnosis",
        "",
        f"- Verdict: **{_named(verdict)}** ({verdict['reason']}).",
        f"- Probability of the verdict: {_text(verdict.get('probability'), '.2f')} (the share of the tiles' bootstrap draws on which each of its "
        f"sign tests comes out the same).",
        f"- The catalog {'explains' if verdict['catalog_explains'] else 'does not explain'} the frame.",
        f"- Gap ({gap['metric']}): "
        + (f"{_text(gap['baseline_recorded_frame'])} with the scene alone on the recorded frame, " if gap.get("baseline_recorded_frame") is not None else "")
        + f"{_text(gap['baseline'])} with the scene alone{' on the frame without the window' if gap.get('baseline_recorded_frame') is not None else ''}, "
        f"{_text(verdict['residual'])} with the verdict (shrink {_text(100 * _value(verdict['shrink']), '.0f')} %).",
        f"- Data: {gap['particles']} particles' optics tested, {gap['tiles']} tiles of {gap['tile_px']} px; {_text(report.get('seconds'), '.0f')} s.",
        "",
    ]
    frames = report.get("frames") or []
    if len(frames) > 1:
        lines += [
            f"## Frames ({len(frames)} diagnosed; the verdict names what a majority of them names, the rest of this report is the first's)",
            "",
            "| frame | verdict | catalog explains | unexplained share |",
            "|---|---|---|---|",
            *[f"| {f['name']} | {f['verdict'] or '—'} | {'yes' if f['catalog_explains'] else 'no'} | {_text(f['residual'])} |" for f in frames],
            "",
        ]
    lines += [
        f"## Effects (best first; selected from held-out z {levels.level_z:g})",
        "",
        "| effect | selected | z | held-out gain (nats) | gap after | shrink | parameters |",
        "|---|---|---|---|---|---|---|",
        *[
            f"| {e['id']} | {'yes' if e['selected'] else 'no'}{_dust_named(e)} | {_text(e.get('z'), '.2f')} | {_text(e.get('heldout_gain_nats'), '.4g')} | {_text(e.get('gap_after'))} | "
            f"{_text(100 * _value(e.get('shrink')), '.0f')} % | " + (parameter_text(e) or "—") + " |"
            for e in report["effects"]
        ],
        "",
        "![effects](gap_effects.png)",
        "",
        *_noise_lines(report["effects"]),
        *_blur_lines(report.get("blur_by_depth"), levels),
        *_spectrum_lines(report.get("spectrum_width")),
        *_dust_lines(report.get("dust_layer")),
        *_scene_lines(report.get("scene"), levels),
        "## Particle optics (opaque against transparent spheres, by their fine rings' spectrum and through focus)",
        "",
        *_optics_lines(optics, levels.level_z),
        "",
        "## What is left",
        "",
        f"- Unexplained share of the frame's structure (median over the {gap['tiles']} held-out tiles): {_text(verdict['residual'])}; "
        f"the catalog explains a frame up to {levels.structure_level:g}.",
        f"- Fixed line pattern: the variance of the residual's column means is {_text(gap['line_pattern']['columns'], '.2f')} times, "
        f"of its row means {_text(gap['line_pattern']['rows'], '.2f')} times what white noise gives them (a pattern above {levels.line_level:g}).",
        *_directional_lines(gap.get("directional_blur"), levels.level_z),
        "",
        "| band (cycles per pixel) | share of the residual's power | structured share |",
        "|---|---|---|",
        *[f"| {b['cycles_per_px'][0]:g}–{b['cycles_per_px'][1]:g} | {_text(b['share_of_power'])} | {_text(b['structured'])} |" for b in gap["by_band"]],
        "",
        *_depth_lines(gap.get("by_depth")),
        "![where](gap_where.png)",
        "",
        "## Not tested",
        "",
        *[f"- `{name}`: {why}." for name, why in report["not_tested"].items()],
        "",
    ]
    return lines


def _noise_lines(effects: list) -> list[str]:
    """The report's lines on the camera's noise: photon noise's whiteness (`shot_noise_test`) and the frame's levels (`levels_test`)."""
    from napari_lbs._core.gap._levels import SHARE_LEVEL
    from napari_lbs._core.gap._nested import WHITE_RATIO

    by_id = {e["id"]: e for e in effects}
    lines = []
    shot = by_id.get("shot_noise", {})
    if shot.get("band_ratios"):
        blur = _value(shot.get("noise_blur_px"))
        if blur > 0:
            lines.append(f"- Photon noise's slope in a band pass over its slope in the high pass, per colour of the tiles: "
                         f"{', '.join(_text(r, '.2f') for r in shot['band_ratios'])}, nearer noise blurred by the camera's fitted {blur:.2f} px; "
                         f"named within a factor of {WHITE_RATIO:g} of it.")
        else:
            lines.append(f"- Photon noise's slope in the finest filter (a second difference along each axis) over its slope in the high pass, per colour of "
                         f"the tiles: {', '.join(_text(r, '.2f') for r in shot.get('fine_ratios') or ())}, nearer white noise (1); named within a factor of "
                         f"{WHITE_RATIO:g} of it (in a band pass: {', '.join(_text(r, '.2f') for r in shot['band_ratios'])}, which what the fits leave raises).")
    levels = by_id.get("quantization", {}).get("levels") or {}
    if levels.get("integer"):
        lines.append(f"- Levels: a converter step of {levels['step_counts']} count{'' if levels['step_counts'] == 1 else 's'}, its noise {_text(levels['noise_share'], '.2g')} of the white floor's; "
                     f"{_text(100 * _value(levels['saturated_share']), '.2f')} % of the pixels at the container's top, the light cut there "
                     f"{_text(levels.get('saturation_noise_share'), '.2g')} of the floor (each named from {SHARE_LEVEL:g}).")
    return lines + ([""] if lines else [])


def _directional_lines(directional: dict | None, level_z: float) -> list[str]:
    """The report's line on a blur that differs by direction (none for a report without the test)."""
    if not directional:
        return []
    return [f"- Blur by direction (motion, astigmatism; outside the catalog): held-out gain {_text(directional['gain_nats'], '.0f')} nats, "
            f"sign test z {_text(directional['z'], '.2f')} (found from {level_z:g}); the long axis's variance exceeds the short one's by "
            f"{_text(directional['variance_difference_px2'], '.2f')} px² at {_text(float(np.degrees(directional['angle_rad'])), '.0f')}° from the x axis."]


def _depth_lines(by_depth: list | None) -> list[str]:
    """The unexplained share about each depth group's particles, before and after the selected effects (`gap.by_depth`)."""
    if not by_depth:
        return []
    return [
        "| particles' depth (mm) | particles | unexplained share about them, before the effects | after |",
        "|---|---|---|---|",
        *[f"| {group['z_um'] / 1000:.2f} | {group['particles']} | {_text(group['baseline'])} | {_text(group['after'])} |" for group in by_depth],
        "",
    ]


def _blur_lines(profile: dict | None, levels: SceneDiagnosisSettings) -> list[str]:
    """The blur's depth profile (`blur_by_depth`), where a blur was selected: each depth group's σ and the line through them."""
    if not profile:
        return []
    origin = " and ".join(profile["origin"]) or "undecided between the sensor and the source"
    return [
        "## The blur by depth (a sensor blurs every depth alike, a source's size more at depth)",
        "",
        f"- σ² = σ_sensor² + (θ·z / pixel)², fitted to the groups' σ²: σ_sensor {_text(profile['sensor_sigma_px'])} px "
        f"(t {_text(profile['t_sensor'], '.1f')}, z {_text(profile.get('z_sensor'), '.1f')}), θ {_text(profile['theta_mrad'])} mrad "
        f"(t {_text(profile['t_source'], '.1f')}, z {_text(profile.get('z_source'), '.1f')}) on {profile.get('dof', '—')} degrees of freedom; "
        f"named from z {levels.level_z:g}: **{origin}**.",
        "",
        "| depth (mm) | σ (px), tiles of one colour | σ (px), the other |",
        "|---|---|---|",
        *[f"| {depth / 1000:.2f} | {_text(first)} | {_text(second)} |" for depth, first, second in zip(profile["depths_um"], *profile["sigma_px"], strict=True)],
        "",
    ]


def _spectrum_lines(test: dict | None) -> list[str]:
    """The named blur against a spectrum's width in its place (`spectrum_width`), where a blur was named."""
    if not test:
        return []
    outcome = "**coherence as a spectrum's width takes its place**" if test["named"] else "the named blur stays"
    return ["## The blur against a spectrum's width (an LED's: fringes washed out with their order and depth)", "",
            f"- In place of {' and '.join(test['replaces'])}: held-out gain {_text(test['gain_nats'], '.4g')} nats, z {_text(test['z'], '.1f')}, "
            f"full width {_text(test['bandwidth_nm'])} nm; {outcome} (from z 3 with a positive gain).", ""]


def _dust_named(effect: dict) -> str:
    """The selected column's note where a window's dust named the effect: its own z, from the tiles holding its grains (the row's z is the straight fringe's)."""
    return f" (a window's dust: z {effect['dust_z']:.2f} from its grains' tiles)" if effect.get("dust_z") is not None else ""


def _dust_lines(dust: dict | None) -> list[str]:
    """The look for a dusty window (`dust_layer`), where it ran: the layer's grains, depth and tiles, and whether it was named."""
    if not dust or not (dust.get("searched") or dust.get("in_layer")):
        return []
    if not dust.get("in_layer"):
        return ["## Dust on a window outside the volume", "", f"- Searched in what the model leaves: {dust.get('grains', 0)} significant grains; none named.", ""]
    params = dust.get("params") or {}
    in_scene = sum(bool(v) for v in (dust.get("layer_grains") or {}).get("in_scene", []))
    return [
        "## Dust on a window outside the volume",
        "",
        f"- {dust['in_layer']} of {dust['grains']} significant grains lie in one plane {dust['depth_um'] / 1000:.2f} mm away, on "
        f"{dust['tiles_with_grains']} tiles (named from 3): **{'named' if dust['named'] else 'not named'}**."
        + (f" {in_scene} of them were fitted among the scene's particles{', which leave its table' if dust['named'] else ''}." if in_scene else ""),
        f"- The window's rings: first Fresnel zone {_text(params.get('dust_zone_px'))} px, {_text(params.get('dust_per_mpx'))} grains a megapixel "
        f"in the frame (grains outside it send rings in too), median radius {_text(params.get('dust_grain_px'))} px.",
        "",
    ]


def _scene_lines(scene: dict | None, levels: SceneDiagnosisSettings) -> list[str]:
    """The scene's numbers (`scene_population`): count, density, sizes, depths, index contrasts and the small scatterers."""
    if not scene:
        return []
    small = scene["small_scatterers"]

    def spread(values, scale: float = 1.0, fmt: str = ".4g") -> str:
        return f"median {_text(values[2] * scale, fmt)} (quartiles {_text(values[1] * scale, fmt)}–{_text(values[3] * scale, fmt)})" if values else "—"

    return [
        "## The scene (the frame's particles as their fits measured them)",
        "",
        f"- {scene['particles']} particles fitted ({_text(scene['per_mm2'], '.3g')} per mm² of the frame): {scene['in_size_range']} within the "
        f"config's sizes, {scene['below_size_range']} below, {scene['above_size_range']} above.",
        f"- Within the sizes: diameter {spread(scene['diameter_um'])} µm; index contrast {spread(scene['index_contrast'])} "
        f"(each fit starts at {_text(levels.refine.index_contrast)} and keeps to the phase-delay valley it starts in).",
        f"- Depth {spread(scene['z_um'], 1e-3, '.3g')} mm.",
        f"- Small scatterers (below the config's sizes): {small['count']}, {_text(small['per_256px_tile'], '.2g')} per 256-pixel tile"
        + (f", {_text(small['diameter_um'][0], '.3g')}–{_text(small['diameter_um'][1], '.3g')} µm" if small["diameter_um"] else "") + ".",
        "",
    ]


def _named(verdict: dict) -> str:
    """What a verdict names: its effects, the effects it is undecided between, or nothing."""
    return verdict["id"] or ("undecided between " + " and ".join(verdict["undecided"]) if verdict["undecided"] else "nothing named")


def _range(pair) -> str:
    """``low to high``, or a dash where there is none."""
    return f"{_text(pair[0])} to {_text(pair[1])}" if pair else "—"
