"""How sure a verdict is: the share of resampled frames on which each of its decisions comes out the same.

A verdict is a set of decisions, each a sign test over the held-out tiles (`_nested.gain_and_z`):
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

__all__ = ["Decision", "combined_z", "sign_z", "verdict_probability"]


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


def sign_z(votes, weights: np.ndarray | None = None):
    """The sign test's z of ``votes``: ``(for - against) / √(for + against)``, 0 where none votes.

    ``weights``: (draws, votes), each vote's weight on each draw, summing to 1 over a draw;
    gives the (draws,) z of each draw. Without it, the observed z (a float): every vote
    weighs one.
    """
    votes = np.asarray(votes, dtype=np.float64)
    if weights is None:  # counted, so that a z on the level is exactly on it
        gaining, losing = int(np.sum(votes > 0)), int(np.sum(votes < 0))
        return float((gaining - losing) / np.sqrt(gaining + losing)) if gaining + losing else 0.0
    gaining = weights.shape[1] * weights @ (votes > 0)  # each vote weighted by its draw, one vote apiece on even weights
    losing = weights.shape[1] * weights @ (votes < 0)
    either = gaining + losing
    return np.divide(gaining - losing, np.sqrt(either), out=np.zeros_like(either), where=either > 0)


def combined_z(differences, views=(), weights: np.ndarray | None = None):
    """The z of a decision's sign test over the tiles and its ``views`` (`Decision`), combined by Stouffer's sum.

    ``weights``: (draws, tiles), the tiles' bootstrap weights; a view's unit takes its tile's
    weight, scaled so that even weights count each unit once. Without it, the observed z
    (a float).
    """
    if weights is None:
        return float((sign_z(differences) + sum(sign_z(votes) for votes, _ in views)) / np.sqrt(1 + len(views)))
    z = sign_z(differences, weights)
    if not views:
        return z
    tiles = weights.shape[1]
    for votes, tile_of in views:
        z = z + sign_z(votes, weights[:, np.asarray(tile_of, int)] * tiles / max(len(votes), 1))
    return z / np.sqrt(1 + len(views))


def _outcomes(decision: Decision, weights: np.ndarray, level_z: float) -> np.ndarray:
    """Each draw's outcome of ``decision`` (+1, 0, −1) at ``level_z``, the tiles weighted by each row of ``weights``."""
    differences = np.asarray(decision.differences, dtype=np.float64)
    z = combined_z(differences, decision.views, weights)
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
