"""The verdict's probability: a Bayesian bootstrap of its sign tests over the tiles."""

import numpy as np
import pytest

from napari_lbs._core.gap._confidence import Decision, verdict_probability


def _votes(gaining: int, tiles: int = 16, *, nats: float = 100.0) -> np.ndarray:
    return np.where(np.arange(tiles) < gaining, nats, -nats)


def test_a_decision_every_tile_agrees_on_always_holds_and_one_on_the_level_in_about_half_the_draws():
    assert verdict_probability([Decision("all", _votes(16), 1)], level_z=3.0)["probability"] == 1.0
    # 14 of 16 tiles is z 3.0 exactly: a draw holds it when the gaining tiles weigh at least 14/16, Beta(14, 2) about its mean
    on_the_level = verdict_probability([Decision("margin", _votes(14), 1)], level_z=3.0)["probability"]
    assert 0.35 < on_the_level < 0.65
    # an effect left out at 8 of 16 (z 0) stays left out in nearly every draw
    assert verdict_probability([Decision("out", _votes(8), 0)], level_z=3.0)["probability"] > 0.99


def test_the_verdict_holds_where_all_its_decisions_do_and_the_same_seed_gives_the_same_share():
    decisions = [Decision("kept", _votes(14), 1), Decision("left out", _votes(12), 0)]
    both = verdict_probability(decisions, level_z=3.0)
    alone = [verdict_probability([d], level_z=3.0)["probability"] for d in decisions]
    assert both["probability"] <= min(alone) and [d["holds"] for d in both["decisions"]] == pytest.approx(alone)
    assert verdict_probability(decisions, level_z=3.0) == both


def test_a_summed_loss_overrules_the_tiles_where_the_gain_is_needed_and_three_way_tests_keep_their_sign():
    # 15 tiles gain a nat each, one loses a thousand: the sign test passes, the sum does not
    differences = np.where(np.arange(16) < 15, 1.0, -1000.0)
    assert verdict_probability([Decision("kept", differences, 1)], level_z=3.0)["probability"] < 0.1
    assert verdict_probability([Decision("votes", differences, 1, needs_gain=False)], level_z=3.0)["probability"] > 0.6
    # opaque particles (every tile votes against transparent ones) are outcome -1 of a three-way test
    assert verdict_probability([Decision("optics", -_votes(16), -1, needs_gain=False, three_way=True)], level_z=3.0)["probability"] == 1.0
    assert verdict_probability([Decision("optics", -_votes(16), 0, needs_gain=False, three_way=True)], level_z=3.0)["probability"] == 0.0


def test_no_decision_is_certainty_and_tests_over_different_tiles_are_refused():
    assert verdict_probability([], level_z=3.0) == {"probability": 1.0, "decisions": []}
    with pytest.raises(ValueError, match="same tiles"):
        verdict_probability([Decision("a", _votes(16), 1), Decision("b", _votes(30, tiles=64), 1)], level_z=3.0)


def test_a_rival_beaten_at_its_own_level_is_redrawn_at_that_level():
    # 12 of 16 tiles is z 2.0: on the rivals' level about half the draws keep the selected
    # effect ahead; read at the verdict's level of 3 it would never have been decided
    rival = Decision("sensor_blur rather than coherence", _votes(12), 1, needs_gain=False, level_z=2.0)
    assert 0.35 < verdict_probability([rival], level_z=3.0)["probability"] < 0.65
    assert verdict_probability([Decision("same votes, the verdict's level", _votes(12), 1, needs_gain=False)], level_z=3.0)["probability"] < 0.2


def test_the_verdict_rests_on_each_rival_it_beat_unless_the_depth_groups_told_the_blurs_apart():
    from types import SimpleNamespace

    from napari_lbs._core.gap._scene_diagnosis import _decisions

    def fit(gaining: int) -> SimpleNamespace:
        return SimpleNamespace(loglik=np.where(np.arange(16) < gaining, 1.0, 0.0))

    # sensor_blur chosen; coherence gained alone too and, in its place, loses on 12 of 16 tiles
    fits = {"baseline": fit(0), "sensor_blur": fit(16), "coherence": fit(4), "coherence+sensor_blur": fit(8)}
    steps = [{"given": [], "gains": {"sensor_blur": {"gain_nats": 9.0, "z": 4.0}, "coherence": {"gain_nats": 5.0, "z": 4.0},
                                     "illumination": {"gain_nats": -1.0, "z": -1.0}}, "added": "sensor_blur"}]
    selection = SimpleNamespace(chosen=("sensor_blur",), fits=fits, steps=steps, undecided=())
    shot = {"white": False, "log10_photons": None}
    names = [d.name for d in _decisions(selection, shot, None, False, None, level_z=3.0)]
    assert "sensor_blur rather than coherence" in names and not [n for n in names if "illumination" in n and "rather" in n]
    told_apart = {"origin": ["sensor_blur"]}
    assert "sensor_blur rather than coherence" not in [d.name for d in _decisions(selection, shot, None, False, told_apart, level_z=3.0)]


def test_a_gated_decision_is_taken_only_on_the_draws_its_gate_holds_on():
    # photon noise: every tile gains, but its slope reads white on about half the draws only
    def half(weights: np.ndarray) -> np.ndarray:
        return weights[:, 0] > np.median(weights[:, 0])

    named = verdict_probability([Decision("shot_noise", _votes(16), 1, gate=half)], level_z=3.0)["probability"]
    left_out = verdict_probability([Decision("shot_noise", _votes(16), 0, gate=half)], level_z=3.0)["probability"]
    assert 0.45 < named < 0.55 and named + left_out == pytest.approx(1.0)


def test_a_verdict_that_names_no_particle_optics_is_sure_only_where_the_tiles_call_them_opaque():
    """The simulator's opaque particles are the verdict's claim where it names no optics: tiles
    that call them opaque all round make it sure, an optics test left undecided makes it doubtful."""
    from types import SimpleNamespace

    from napari_lbs._core.gap._confidence import verdict_probability
    from napari_lbs._core.gap._scene_diagnosis import _decisions

    selection = SimpleNamespace(chosen=(), fits={"baseline": SimpleNamespace(loglik=np.zeros(16))}, steps=[], undecided=())
    shot = {"white": False, "log10_photons": None}
    opaque = -np.ones(16)  # every tile: the opaque model predicts the fine rings better
    undecided = np.where(np.arange(16) < 9, 1.0, -1.0)  # 9 tiles for transparent, 7 for opaque: z 0.5
    sure = verdict_probability(_decisions(selection, shot, (opaque, ()), False, None, level_z=3.0), level_z=3.0)["probability"]
    doubtful = verdict_probability(_decisions(selection, shot, (undecided, ()), False, None, level_z=3.0), level_z=3.0)["probability"]
    assert sure > 0.99 and doubtful < 0.05, (sure, doubtful)


def test_a_view_over_other_units_is_combined_by_stouffer_and_drawn_with_its_units_tiles():
    """Tiles below the level (z 2.0) and 25 spheres of which 23 vote the same way (z 4.2): (2.0 + 4.2) / √2 = 4.4, above the level in most draws;
    the spheres alone in one tile weigh as that tile does, so a draw that lightens the tile lightens them."""
    tiles = _votes(12)  # (12 - 4) / 4 = 2.0
    spheres = np.where(np.arange(25) < 23, 1.0, -1.0)
    spread = np.arange(25) % 16  # every tile holds a sphere or two
    combined = verdict_probability([Decision("optics", tiles, 1, needs_gain=False, three_way=True, views=((spheres, spread),))], level_z=3.0)
    alone = verdict_probability([Decision("optics", tiles, 1, needs_gain=False, three_way=True)], level_z=3.0)
    assert alone["probability"] < 0.2 and combined["probability"] > 0.8
    # the same votes piled into one tile: the draws that weigh that tile down take the spheres' z with it
    piled = verdict_probability([Decision("optics", tiles, 1, needs_gain=False, three_way=True, views=((spheres, np.zeros(25, int)),))], level_z=3.0)
    assert piled["probability"] < combined["probability"] - 0.2
