"""How sure a verdict is: the share of resampled frames on which each of its decisions comes out the same.

A verdict is a set of decisions, each a sign test over the held-out tiles (`_nested._gain`):
each selected effect kept against the model without it, each effect left out not added to
the final model, each selected effect ahead of a rival in its place (at the rivals' own
level), photon noise named or not, transparent or opaque particles.
Resampling the tiles by a Bayesian bootstrap (Dirichlet(1) weights; Rubin, *Ann. Statist.* 9,
130 (1981)) and taking each decision again at the same level gives the probability that the
frame, drawn again, would give the same verdict — bootstrap model-selection frequencies
(Efron, *J. Am. Statist. Assoc.* 109, 991 (2014)). A decision taken on a bare margin (14 of
16 tiles at a level of z 3) holds in about half the draws; one every tile agrees on, in all.

The whiteness of photon noise's slope is a regression over the same tiles: each draw refits
it on its weighted tiles (`_nested.whiteness_draws`), and photon noise is taken on a draw
where its slope reads white and its sign test passes. The converter's levels (a share of the
noise) are no test over the tiles and are left as they are. A blur whose origin
the depth groups chose (the line through the groups' blurs) is counted as any named effect: the
tiles must still gain from it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["Decision", "verdict_probability"]


@dataclass(frozen=True)
class Decision:
    """One sign test of a verdict: per-tile differences and the outcome the verdict took.

    ``differences``: per held-out tile, the better model's log-likelihood less the worse's
    (nats), or any per-tile score whose sign votes. ``outcome``: +1 where the verdict took the
    effect (z at or above the level and, where ``needs_gain``, the summed difference
    positive), −1 where it took the opposite (z at or below minus the level: only for
    ``three_way`` tests, as particle optics' opaque), 0 where it took neither. ``level_z``:
    the test's own level where it is not the verdict's (a selected effect against a rival in
    its place is decided at a z of 2). ``gate``: for a test taken only where a condition on
    the same tiles holds (photon noise, only where its slope reads white), the condition on
    each draw: ``gate(weights)`` is a (draws,) bool array, and the effect is taken on a draw
    where both the sign test and the gate hold. ``views``: further sign tests of the same
    question over other units (the particles' optics through focus votes sphere by sphere),
    each ``(votes, tile of each vote)``; a unit takes its tile's weight, and the decision's z
    is the views' z summed with the tiles' and divided by the root of their number
    (Stouffer's combination of independent tests).
    """

    name: str
    differences: np.ndarray
    outcome: int
    needs_gain: bool = True
    three_way: bool = False
    level_z: float | None = None
    gate: Callable[[np.ndarray], np.ndarray] | None = None
    views: tuple[tuple[np.ndarray, np.ndarray], ...] = ()


def _sign_z(votes: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Each draw's sign-test z of ``votes`` (one per tile, or one per unit with its tile's weight: ``weights`` (draws, votes))."""
    gaining = weights.shape[1] * weights @ (votes > 0)  # each vote weighted by its tile's draw, one vote apiece on even weights
    losing = weights.shape[1] * weights @ (votes < 0)
    either = gaining + losing
    return np.divide(gaining - losing, np.sqrt(either), out=np.zeros_like(either), where=either > 0)


def _outcomes(decision: Decision, weights: np.ndarray, level_z: float) -> np.ndarray:
    """Each draw's outcome of ``decision`` (+1, 0, −1) at ``level_z``, the tiles weighted by each row of ``weights``."""
    differences = np.asarray(decision.differences, dtype=np.float64)
    z = _sign_z(differences, weights)
    if decision.views:
        # Stouffer's sum of the views' z: each a sign test of its own units, clustered by tile
        tiles = weights.shape[1]
        for votes, tile_of in decision.views:
            # a unit's weight is its tile's, scaled so that even weights count each unit once
            z = z + _sign_z(np.asarray(votes, np.float64), weights[:, np.asarray(tile_of, int)] * tiles / max(len(votes), 1))
        z = z / np.sqrt(1 + len(decision.views))
    level_z = level_z if decision.level_z is None else decision.level_z
    taken = z >= level_z
    if decision.needs_gain:
        taken &= weights @ differences > 0
    if decision.gate is not None:
        taken &= np.asarray(decision.gate(weights), dtype=bool)
    outcome = taken.astype(int)
    if decision.three_way:
        outcome[z <= -level_z] = -1
    return outcome


def verdict_probability(decisions: list[Decision], *, level_z: float, draws: int = 2000, seed: int = 0) -> dict:
    """The share of Bayesian-bootstrap draws of the tiles in which every decision comes out as the verdict took it.

    Parameters
    ----------
    decisions : list of Decision
        The verdict's sign tests, each over the same tiles in the same order.
    level_z : float
        The sign test's level (`SceneDiagnosisSettings.level_z`).
    draws, seed : int
        The bootstrap's draws and its generator's seed (the same seed, the same probability).

    Returns
    -------
    dict
        ``probability`` (the verdict's, in [0, 1]; 1 where there is no decision) and
        ``decisions``: each decision's name, outcome and the share of draws it holds in.
    """
    if not decisions:
        return {"probability": 1.0, "decisions": []}
    tiles = {np.asarray(d.differences).size for d in decisions}
    if len(tiles) != 1:
        raise ValueError(f"verdict_probability: every decision must vote over the same tiles, got {sorted(tiles)}")
    weights = np.random.default_rng(seed).dirichlet(np.ones(tiles.pop()), size=draws)
    same = np.ones(draws, bool)
    held = []
    for decision in decisions:
        agrees = _outcomes(decision, weights, level_z) == decision.outcome
        same &= agrees
        held.append({"name": decision.name, "outcome": decision.outcome, "holds": float(agrees.mean())})
    return {"probability": float(same.mean()), "decisions": held}
