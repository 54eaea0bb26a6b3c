"""Attribution: which unmodelled effect causes the gap, and how far it shrinks (`diagnose_tiles`, `diagnose_hologram`).

Fit the baseline (seed's simulator, `EFFECTS` module) to half of the real tiles, screen every
effect by regressing the standardised residual on its signature, confirm the most significant
ones (largest |t|) by adding each and refitting all parameters, score every model on the other
half (tiles never used for a fit), ablate each confirmed fit (the same parameters with the
effect switched off), rank, and name a verdict — or ``null`` with the reason (`_verdict`).
Where the held-out half is small (`DiagnosisSettings.cross_fit_below_px`), all of this is done
twice, the halves swapping roles, and the evidence is pooled over both held-out halves: every
tile is held out once.
No refit ends worse than its start on the fitting tiles. What the file states (`known_sensor`)
is put into every model as known (`diagnose_hologram(known=True)`), not diagnosed.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from napari_lbs._core._config import ExperimentConfig
from napari_lbs._core._effects import EFFECTS, check_effects
from napari_lbs._core._gap._fitting import DiagnosisSettings, _fit, _Model, _with_measured
from napari_lbs._core._gap._known import known_sensor
from napari_lbs._core._gap._statistic import gap_statistic, real_spread, where_gap
from napari_lbs._core._gap._summaries import MIN_TILE_PX, _fringe_parameters, _tiles_summaries, measured_fringe
from napari_lbs._core._gap._tiling import TileLayout, adapted_tile_px, field_surroundings
from napari_lbs._core._gap._verdict import _decision, _replicated_in_a_half, effect_evidence, resampled_gaps
from napari_lbs._core._io import InputError, as_hologram
from napari_lbs._core._progress import ProgressCallback, Steps, StopCallback

__all__ = ["Diagnosis", "diagnose_tiles", "diagnose_hologram"]


@dataclass
class Diagnosis:
    """The report (CONTRACT.md ``report.json``) plus what the figures need."""

    report: dict
    names: list
    real: np.ndarray = field(repr=False)
    baseline_sim: np.ndarray = field(repr=False)
    seconds: float = 0.0
    halves: list = field(default_factory=list, repr=False)  # each fit's `_Half`: what the verdict is scored from


def diagnose_tiles(
    real_tiles: Sequence[np.ndarray],
    config: ExperimentConfig,
    *,
    layout: TileLayout | None = None,
    known: dict | None = None,
    settings: DiagnosisSettings = DiagnosisSettings(),
    particles_per_tile: int | None = None,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> Diagnosis:
    """Diagnose the gap between real hologram tiles and the seed's simulator.

    Parameters
    ----------
    real_tiles : sequence of (rows, cols) arrays
        At least 4 tiles of the experiment (same shape, positive mean intensity).
    config : ExperimentConfig
        Optics, depths and particle sizes of the simulator.
    layout : TileLayout, optional
        Where the tiles were cut from one hologram: the simulation then makes whole fields and
        the tiles are split into fitting and held-out halves as a checkerboard. Without it,
        alternate tiles are fitted and held out, and each simulated tile is a field of its own.
        Where the held-out half holds fewer than ``settings.cross_fit_below_px`` pixels, the
        halves then swap roles and the evidence is pooled over both held-out halves
        (``report["tiles"]["cross_fitted"]``; each half's own verdict in
        ``report["verdict"]["per_half"]``).
    known : dict, optional
        ``{effect_id: params}``: effects the experiment states (e.g. the file's bit depth),
        put into every model with fixed parameters and not diagnosed.
    settings : DiagnosisSettings
    particles_per_tile : int, optional
        Particles per simulated tile; default ``per_tile`` scaled to the tile area.
    progress, should_stop
        One step per fit (baseline, screening, each confirmation, the waterfall); a stop
        raises `Stopped`.
    """
    start = time.perf_counter()
    tiles = [np.asarray(t, np.float32) for t in real_tiles]
    if len(tiles) < 4:
        raise InputError(f"real tiles: expected at least 4 tiles (half to fit, half to score), got {len(tiles)}")
    shape = tiles[0].shape
    if any(t.shape != shape for t in tiles):
        raise InputError("real tiles: expected tiles of one shape")
    means = np.array([t.mean() for t in tiles])
    if not np.all(np.isfinite(means)) or np.any(means <= 0):
        raise InputError("real tiles: expected finite intensities with a positive mean in every tile")
    known = check_effects(known or {})
    candidates = [e for e in EFFECTS if e not in known]
    count = particles_per_tile if particles_per_tile is not None else max(1, round(config.particles.per_tile * shape[0] * shape[1] / config.tile.size**2))
    fitting = layout.fitting(shape) if layout is not None else np.arange(len(tiles)) % 2 == 0
    if layout is not None:
        # the field the tiles cover, reassembled: each tile's surroundings come from it
        field = np.full(layout.field_shape, np.nan)
        for t, (r, c) in zip(tiles, layout.origins, strict=True):
            field[r : r + shape[0], c : c + shape[1]] = t
        around = [field_surroundings(field, origin, shape) for origin in layout.origins]
        field_mean = layout.field_mean
    else:
        around, field_mean = [None] * len(tiles), float(means.mean())
    # cross-fit where the held-out half is small: fit on each half, score on the other
    cross_fitted = 0 < int((~fitting).sum()) * shape[0] * shape[1] < settings.cross_fit_below_px
    confirmed = min(settings.confirm, len(candidates))
    steps = Steps((2 if cross_fitted else 1) * (2 + confirmed) + 1, progress=progress, should_stop=should_stop)
    # one cache of simulated light for both halves: their fields are the same draw
    common = {"config": config, "count": count, "settings": settings, "layout": layout, "known": known, "candidates": candidates, "steps": steps, "light": {}}
    first = _fit_half(tiles, fitting, "fit", around=around, field_mean=field_mean, refitted=None, **common)
    halves = [first, _fit_half(tiles, ~fitting, "held", around=around, field_mean=field_mean, refitted=first.refitted, **common)] if cross_fitted else [first]
    names = first.names

    scored = _scored(halves, candidates, settings=settings)
    effects_report, verdict, baseline_gap = scored["effects"], scored["verdict"], scored["baseline_gap"]

    # waterfall: baseline, + best, + best and the runner-up (greedy, refitted in every half)
    waterfall = [{"model": "baseline", "gap": float(baseline_gap)}]
    confirmed_sorted = [e for e in effects_report if e["confirmed"]]
    if confirmed_sorted:
        waterfall.append({"model": f"+{confirmed_sorted[0]['id']}", "gap": confirmed_sorted[0]["gap_after"]})
    steps.check()
    if len(confirmed_sorted) > 1:
        pair = [confirmed_sorted[0]["id"], confirmed_sorted[1]["id"]]
        joint = [_fit_pair(h, pair, evaluations=settings.evaluations) for h in halves]
        waterfall.append({
            "model": f"+{pair[0]}+{pair[1]}",
            "gap": float(gap_statistic(scored["held_real"], np.vstack([sim / h.spread for (_, sim), h in zip(joint, halves, strict=True)]), spread=np.ones(len(names)))[0]),
            "params": {effect_id: dict(joint[0][0][effect_id]) for effect_id in pair},  # the first half's joint fit, for `effects_from_report`
        })
    steps.advance()

    base_all = np.vstack([first.base_sim, first.held["baseline"][: settings.sim_tiles]])  # the first half's baseline at both halves' places (one set of fields), for "where"
    report = {
        "gap": {
            "metric": f"excess standardised chi-square over {len(names)} summaries, held-out real tiles vs simulation (0 = indistinguishable)",
            "baseline": float(baseline_gap),
            "baseline_fit": float(first.base_fit_gap),
            "baseline_interval": scored["baseline_interval"],
            "baseline_params": first.base_params,
            **where_gap(first.real, base_all, names),
        },
        "known": known,
        "effects": effects_report,
        "verdict": verdict,
        "waterfall": waterfall,
        "tiles": {
            "real": len(tiles), "fit": int(fitting.sum()), "held_out": len(scored["held_real"]), "simulated": settings.sim_tiles, "simulated_scored": settings.sim_tiles * settings.scoring_replicates, "shape": list(shape), "particles_per_tile": count,
            "split": ("checkerboard over the hologram" if layout is not None else "alternate tiles") + ("; cross-fitted: each half fitted and the other scored, every tile held out once" if cross_fitted else ""),
            "cross_fitted": bool(cross_fitted),
        },
        "settings": {"sim_tiles": settings.sim_tiles, "evaluations": settings.evaluations, "confirm": settings.confirm, "resamples": settings.resamples, "seed": settings.seed, "cross_fit_below_px": settings.cross_fit_below_px, "scoring_replicates": settings.scoring_replicates},
    }
    seconds = time.perf_counter() - start
    report["seconds"] = round(seconds, 2)
    for half in halves:
        half.model.forget_light()
    return Diagnosis(report, names, first.real, base_all, seconds, halves)


def _scored(halves: list, candidates: list, *, settings: DiagnosisSettings) -> dict:
    """Every model scored on the held-out tiles of ``halves``, pooled: the effects' report entries (ranked), the verdict, the baseline gap.

    Each half's held-out tiles and simulations are put in its own spreads (its fringe
    frequency, and so its summaries, are its own): z units, pooled over the halves; with two
    halves, the pooled verdict stands only where one half's own names it too, else another part
    of the gap that a half names, else none (`_replicated_in_a_half`; each half's in
    ``verdict["per_half"]``). Returns ``effects``, ``verdict``,
    ``baseline_gap``, ``baseline_interval`` and ``held_real`` (the pooled held-out summaries,
    in z units).
    """
    first = halves[0]
    held_real = np.vstack([h.real[~h.fitting] / h.spread for h in halves])
    held_sims = {name: np.vstack([h.held[name] / h.spread for h in halves]) for name in first.held}
    unit = np.ones(held_real.shape[1])
    gap = lambda a, b: gap_statistic(a, b, spread=unit)  # noqa: E731
    baseline_gap = gap(held_real, held_sims["baseline"])[0]
    effects_report = []
    for effect_id in candidates:
        entry = {"id": effect_id, "screening": first.screening[effect_id], "confirmed": effect_id in first.refitted, **first.entries[effect_id]}
        if len(halves) > 1 and "gap_fit" in entry:
            entry["params_other_half"] = halves[1].entries[effect_id]["params"]
        if entry["confirmed"]:
            gap_after = gap(held_real, held_sims[effect_id])[0]
            entry["gap_ablated"] = float(gap(held_real, held_sims[f"{effect_id} off"])[0])
        else:
            # the best of the coarse scan (off, weak, strong) with the baseline's parameters
            scan = [(baseline_gap, dict(EFFECTS[effect_id].neutral))] + [(gap(held_real, held_sims[f"{effect_id} scan {i}"])[0], setting) for i, setting in enumerate(first.scanned[effect_id])]
            gap_after, entry["params"] = min(scan, key=lambda pair: pair[0])
        entry["gap_after"] = float(gap_after)
        entry["shrink"] = float(1.0 - gap_after / baseline_gap) if baseline_gap > 0 else 0.0
        effects_report.append(entry)

    # evidence with its uncertainty: resample the held-out real tiles and the simulation seeds
    # resampled within each half: the design holds out each half's tiles against its own fit
    strata = ([int((~h.fitting).sum()) for h in halves], [len(h.held["baseline"]) for h in halves])
    resampling = {"spread": unit, "resamples": settings.resamples, "seed": settings.seed, "paired": first.model.paired, "strata": strata}
    draws = resampled_gaps(held_real, held_sims, **resampling)
    evidence = effect_evidence(held_real, held_sims, [e["id"] for e in effects_report if e["confirmed"]], **resampling)
    for entry in effects_report:
        if entry["confirmed"]:
            reduction = draws["baseline"] - draws[entry["id"]]
            # shrink's interval: the reduction's 90 % interval over the measured baseline gap
            low, high = np.quantile(reduction, (0.05, 0.95)) / baseline_gap if baseline_gap > 0 else (0.0, 0.0)
            entry["shrink_interval"] = [float(low), float(high)]
            own = evidence[entry["id"]]
            entry["evidence"] = {"summaries": own["summaries"], "reduction": own["reduction"], "interval": [float(v) for v in np.quantile(own["draws"], (0.05, 0.95))]}
    # ranked by the evidence the verdict is decided on (then the screened ones, by their scan)
    effects_report.sort(key=lambda e: (not e["confirmed"], -e["evidence"]["reduction"] if e["confirmed"] else e["gap_after"]))
    verdict = _decision([e for e in effects_report if e["confirmed"]], evidence, baseline_gap=baseline_gap, held_out=len(held_real), summaries=len(unit))
    if len(halves) > 1:
        # each half's verdict on its own held-out tiles: a pooled verdict neither supports is not given
        verdict = _replicated_in_a_half(verdict, [_scored([h], candidates, settings=settings)["verdict"]["id"] for h in halves], baseline_gap=baseline_gap, entries=effects_report)
    verdict.pop("also_present", None)  # the replication's input; the reason tells the user the other parts
    return {
        "effects": effects_report, "verdict": verdict, "baseline_gap": baseline_gap, "held_real": held_real,
        "baseline_interval": [float(v) for v in np.quantile(draws["baseline"], (0.05, 0.95))],
    }


@dataclass
class _Half:
    """One fit of the diagnosis: fitted on the real tiles ``fitting`` selects, scored on the others.

    ``real`` holds every real tile's summaries with this half's fringe frequency (measured on
    its fitting tiles only), ``spread`` their tile-to-tile spread; ``held`` each model's
    simulated summaries at the held-out tiles' places (raw), keyed ``"baseline"``, the effect
    id (its refit), ``"<id> off"`` (the refit with the effect switched off) and, for effects
    not refitted, ``"<id> scan <i>"`` (`scanned`); ``entries`` the report fields of this
    half's fits (``params``, ``gap_fit``).
    """

    fitting: np.ndarray
    half: str
    names: list
    real: np.ndarray
    spread: np.ndarray
    model: _Model
    measured: dict
    base_params: dict
    base_fit_gap: float
    base_sim: np.ndarray
    screening: dict
    refitted: list
    held: dict
    fitted: dict
    entries: dict
    scanned: dict


def _fit_half(tiles: list, fitting: np.ndarray, half: str, *, config: ExperimentConfig, count: int, settings: DiagnosisSettings, layout: TileLayout | None, known: dict, candidates: list, around: list, field_mean: float, refitted: list | None, steps: Steps, light: dict) -> _Half:
    """Fit the baseline to the tiles ``fitting`` selects (the layout's ``half``), screen, refit, ablate, and simulate the other tiles' places.

    ``refitted``: the effects to refit (None: the most significant in this half's screening);
    ``light``: the simulated light cache shared by the halves (`_Model`).
    """
    fringe_frequency = measured_fringe([t for t, fit in zip(tiles, fitting, strict=True) if fit])  # from the fitting tiles only
    measured = _fringe_parameters(fringe_frequency)
    real, names = _tiles_summaries(tiles, config=config, fringe_frequency=fringe_frequency, field_means=[field_mean] * len(tiles), surroundings=around)
    fit_real = real[fitting]
    spread = real_spread(real)  # the experiment's own tile-to-tile spread: the unit of every gap
    other = "held" if half == "fit" else "fit"
    model = _Model(config, shape=tiles[0].shape, count=count, settings=settings, fringe_frequency=fringe_frequency, layout=layout, known=known, light=light)
    fit = lambda ids, start: _fit(model, fit_real, ids, start=start, measured=measured, evaluations=settings.evaluations, spread=spread, half=half)  # noqa: E731

    steps.check()
    base_params, _, base_fit_gap = fit([], {})
    base_sim = model.summaries(base_params, {}, half=half)
    held = {"baseline": model.summaries(base_params, {}, half=other, scored=True)}  # every model's held-out simulation, for the resampling
    steps.advance()

    # screen: regress the standardised residual on each effect's signature (finite difference)
    steps.check()
    _, z_residual = gap_statistic(fit_real, base_sim, spread=spread)
    screening = {}
    for effect_id in candidates:
        signature_sim = model.summaries(base_params, {effect_id: _with_measured(effect_id, EFFECTS[effect_id].injections[1], measured)}, half=half)
        _, signature = gap_statistic(signature_sim, base_sim, spread=spread)  # how far the effect moves the simulation, in z units
        norm = float(signature @ signature)
        coefficient = float(z_residual @ signature) / norm if norm > 0 else 0.0
        residual = z_residual - coefficient * signature
        dof = max(len(signature) - 1, 1)
        error = np.sqrt(float(residual @ residual) / dof / norm) if norm > 0 else np.inf
        screening[effect_id] = {"coefficient": coefficient, "t": coefficient / error if error > 0 else 0.0, "explained": 1.0 - float(residual @ residual) / max(float(z_residual @ z_residual), 1e-12)}
    steps.advance()

    # Confirm the effects whose fingerprint is most significant, whichever its sign: the
    # baseline's own parameters may already have over-compensated for the missing effect.
    if refitted is None:
        refitted = sorted(candidates, key=lambda e: -abs(screening[e]["t"]))[: min(settings.confirm, len(candidates))]
    fitted, entries, scanned = {}, {}, {}
    for effect_id in candidates:
        if effect_id in refitted:
            steps.check()
            baseline_params, effect_params, fit_gap = fit([effect_id], {("baseline", k): v for k, v in base_params.items()})
            held[effect_id] = model.summaries(baseline_params, effect_params, half=other, scored=True)
            # ablation at the optimum: the same fit with the effect switched off. A refit can
            # lower the gap by moving the baseline alone (out of an over-fitted optimum of
            # the fitting tiles); only what switching the effect on adds is the effect's.
            held[f"{effect_id} off"] = model.summaries(baseline_params, {}, half=other, scored=True)
            fitted[effect_id] = (baseline_params, effect_params)
            # gap_fit: on the fitting tiles, never above the baseline's (`_fit` keeps its start)
            entries[effect_id] = {"gap_fit": float(fit_gap), "params": {**effect_params[effect_id], **{f"baseline.{k}": v for k, v in baseline_params.items()}}}
            steps.advance()
        else:
            # not refitted: a coarse scan (weak, strong) with the baseline's parameters
            scanned[effect_id] = [_with_measured(effect_id, setting, measured) for setting in EFFECTS[effect_id].injections]
            for i, setting in enumerate(scanned[effect_id]):
                held[f"{effect_id} scan {i}"] = model.summaries(base_params, {effect_id: setting}, half=other, scored=True)
            entries[effect_id] = {}
    return _Half(fitting, half, names, real, spread, model, measured, base_params, base_fit_gap, base_sim, screening, refitted, held, fitted, entries, scanned)


def _fit_pair(half: _Half, pair: list, *, evaluations: int) -> tuple[dict, np.ndarray]:
    """Refit ``pair`` together in one half, from its first effect's fit: (effect params, simulated summaries at the held-out places)."""
    start = {("baseline", k): v for k, v in half.fitted[pair[0]][0].items()}
    start.update({(pair[0], k): v for k, v in half.fitted[pair[0]][1][pair[0]].items()})
    baseline_params, effect_params, _ = _fit(half.model, half.real[half.fitting], pair, start=start, measured=half.measured, evaluations=evaluations, spread=half.spread, half=half.half)
    return effect_params, half.model.summaries(baseline_params, effect_params, half="held" if half.half == "fit" else "fit", scored=True)


def diagnose_hologram(
    hologram: np.ndarray,
    config: ExperimentConfig,
    *,
    background: np.ndarray | None = None,
    tile_px: int | None = None,
    known: bool = True,
    stated: dict | None = None,
    settings: DiagnosisSettings = DiagnosisSettings(),
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> Diagnosis:
    """Diagnose one hologram: cut it into tiles and run `diagnose_tiles` with the field's layout.

    Parameters
    ----------
    hologram : 2-D array
        As recorded (integer counts keep what the file states about the camera).
    tile_px : int, optional
        Tile edge (px). Default: the largest edge up to ``tile.size`` that cuts at least 16
        tiles (512²: 128 px), so the held-out half has 8 tiles to resolve a gap with (and
        a 512² or 1024² hologram is cross-fitted: all 16 are scored, `DiagnosisSettings.cross_fit_below_px`).
    known : bool
        Put what the file states into every model as known, not diagnosed: for integer
        counts (`known_sensor`), the bit depth and saturation as ``quantization``. Off, with
        a ``background`` (the division makes the levels uneven), or where the values use
        fewer levels than the format holds (a 6-bit image in a uint8 file), they are diagnosed.
    stated : dict, optional
        ``{effect_id: params}`` (`check_effects`): what the user knows of the experiment, e.g.
        ``{"particle_phase": {"index_contrast": 0.26, "transmission": 1.0}}`` for polystyrene
        beads in water, which the seed's opaque simulator lacks. Put into every model with
        these parameters (over what the file states), shown as known, and not diagnosed: the
        diagnosis then looks for what is still missing.
    """
    image = as_hologram(hologram)
    # the array as given keeps its dtype; an RGB one is read from its channel of integer counts
    facts = (known_sensor(hologram) or known_sensor(image)) if known else None
    if background is not None:
        image = image / np.maximum(as_hologram(background, name="background"), 1e-6)
        facts = None
    rows, cols = image.shape
    size = int(tile_px or adapted_tile_px((rows, cols), config.tile.size))
    if size < MIN_TILE_PX:
        raise InputError(f"tile: expected at least {MIN_TILE_PX} pixels (the frequency bands need them), got {size}")
    if size > min(rows, cols):
        raise InputError(f"tile: a {size}-pixel tile is larger than the hologram ({rows}x{cols})")
    origins = tuple((r, c) for r in range(0, rows - size + 1, size) for c in range(0, cols - size + 1, size))
    if len(origins) < 4:
        raise InputError(f"tile: {size}-pixel tiles give {len(origins)} tiles of the {rows}x{cols} hologram; expected at least 4 (use a smaller tile)")
    tiles = [image[r : r + size, c : c + size] for r, c in origins]
    field_mean = float(np.mean([t.mean() for t in tiles]))
    # the sensor's levels in the simulation's unit (the tiles' mean intensity is 1 there)
    # sensor_image spreads 2^bits - 1 levels over [0, saturation]: one count a step only when that is the full scale
    # (a pile-up below full scale, e.g. clipping at 200 of 255, is in `facts` but not simulated)
    # values coarser than the format (`known_sensor`'s ``coarse``): the file does not state the bit depth, diagnose it
    known_effects = {"quantization": {"bits": float(facts["bits"]), "saturation": facts["full_scale"] / field_mean}} if facts and not facts["coarse"] else {}
    stated = check_effects(stated or {})
    known_effects.update(stated)
    covered = ((rows // size) * size, (cols // size) * size)  # the field the tiles cover
    diagnosis = diagnose_tiles(tiles, config, layout=TileLayout(covered, origins, field_mean), known=known_effects, settings=settings, progress=progress, should_stop=should_stop)
    diagnosis.report["known_sensor"] = facts if facts else {"source": "none: not integer counts, a background was divided out, or switched off"}
    diagnosis.report["stated"] = stated  # what the user stated (in ``known`` too), apart from what the file states
    return diagnosis
