"""Evidence with its uncertainty: bootstrap of the held-out gaps (`resampled_gaps`) and the verdict (`_decision`)."""

from __future__ import annotations

import numpy as np
from scipy import stats

__all__ = ["resampled_gaps"]

# A verdict needs the best effect to remove at least this much excess χ² on held-out tiles
# (refitting a null model to noise removes less: the controls of the suite), both against the
# baseline and against its own fit with the effect switched off, and this share of the gap.
_VERDICT_MIN_REDUCTION = 0.5
_VERDICT_MIN_SHRINK = 0.3


def resampled_gaps(real: np.ndarray, sims: dict, *, spread: np.ndarray, resamples: int, seed: int = 0, paired: bool = False) -> dict:
    """Each model's gap on bootstrap resamples of what the gap depends on.

    Parameters
    ----------
    real : (n_real, K) array
        Summaries of the real tiles the gap is measured on.
    sims : dict of (n_sim, K) arrays
        Each model's simulated summaries; row i of every model comes from the same simulated
        field and noise (common random numbers), so one draw of simulation seeds serves all.
    spread : (K,) array
        The per-summary unit (`real_spread`), held fixed.
    resamples : int
        Bootstrap draws: real tiles and simulation seeds, each drawn with replacement, paired
        across models (differences between models keep their correlation).
    paired : bool
        Row i of ``real`` and of every simulation lie at one place of the field (`_Model.paired`):
        draw each place once for both, so that what depends on the place (a vignetting's tilt)
        is not counted as sampling noise.

    Returns
    -------
    dict of (resamples,) arrays, one per model.
    """
    rng = np.random.default_rng([seed, 17])
    n_real, n_sim = len(real), len(next(iter(sims.values())))
    real_draw = rng.integers(0, n_real, (resamples, n_real))
    sim_draw = real_draw if paired else rng.integers(0, n_sim, (resamples, n_sim))
    real_means = real[real_draw].mean(axis=1)
    scale = spread * np.sqrt(1.0 / n_real + 1.0 / n_sim)
    return {name: np.maximum(0.0, np.mean(np.minimum(((real_means - sim[sim_draw].mean(axis=1)) / scale) ** 2, 1e4), axis=1) - 1.0) for name, sim in sims.items()}


def _decision(entries: list, draws: dict, *, baseline_gap: float, held_out: int) -> dict:
    """The verdict from the confirmed effects' held-out gaps and their bootstrap draws (see `diagnose_tiles`).

    An effect is named only when (a) its reduction of the gap, against the baseline and against
    its own fit with the effect switched off, is at least ``_VERDICT_MIN_REDUCTION`` and
    ``_VERDICT_MIN_SHRINK`` of the baseline, and its lower confidence bound is above 0; and
    (b) its lead over the runner-up has a lower confidence bound above 0. Bounds are one-sided
    at 95 %, Bonferroni-corrected for the number of effects compared (the best of several is
    picked). ``tiles_to_decide``: held-out tiles at which the weaker of the two margins would
    reach its bound, if margin / bootstrap error grows as sqrt(tiles).
    """
    ranked = sorted(entries, key=lambda e: e["gap_after"])
    alpha = 0.05 / max(len(ranked), 1)
    z_needed = float(stats.norm.ppf(1.0 - alpha))
    verdict = {"id": None, "shrink": 0.0, "residual": float(baseline_gap), "interval": [0.0, 0.0], "runner_up": None, "confidence": 1.0 - alpha}
    if not ranked:
        return {**verdict, "reason": "no effect was refitted", "tiles_to_decide": None}
    best = ranked[0]
    against = np.minimum(draws["baseline"], draws[f"{best['id']} off"])
    reduction = against - draws[best["id"]]
    point_reduction = min(baseline_gap, best["gap_ablated"]) - best["gap_after"]
    margins = [(point_reduction, reduction)]
    runner = ranked[1] if len(ranked) > 1 else None
    if runner is not None:
        margins.append((runner["gap_after"] - best["gap_after"], draws[runner["id"]] - draws[best["id"]]))
    ratios = [point / max(float(np.std(samples)), 1e-12) for point, samples in margins]
    tiles = [int(np.ceil(held_out * (z_needed / ratio) ** 2)) if ratio > 0 else None for ratio in ratios]
    tiles_to_decide = None if None in tiles else max(tiles)
    verdict.update({"runner_up": runner["id"] if runner else None, "tiles_to_decide": tiles_to_decide})
    low_reduction = float(np.quantile(reduction, alpha))
    if point_reduction < _VERDICT_MIN_REDUCTION or best["shrink"] < _VERDICT_MIN_SHRINK or low_reduction <= 0:
        verdict["reason"] = f"gap within what {held_out} held-out tiles can resolve: " + (
            f"the best effect, {best['id']}, removes {point_reduction:.2f} of {baseline_gap:.2f} (lower bound {low_reduction:.2f})"
            if point_reduction > 0
            else f"no refitted effect lowers the gap of {baseline_gap:.2f}"
        )
        return verdict
    if runner is not None and float(np.quantile(margins[1][1], alpha)) <= 0:
        verdict["reason"] = f"two effects indistinguishable: {best['id']} ({best['gap_after']:.2f}) and {runner['id']} ({runner['gap_after']:.2f}) on {held_out} held-out tiles"
        return verdict
    verdict.update({"id": best["id"], "shrink": best["shrink"], "residual": best["gap_after"], "interval": best["shrink_interval"]})
    verdict["reason"] = f"{best['id']} removes {point_reduction:.2f} of {baseline_gap:.2f} (lower bound {low_reduction:.2f}) and leads {runner['id'] if runner else 'nothing'}"
    return verdict
