import json
import subprocess
import sys

import numpy as np
import pytest

from napari_lbs._core import InputError, match_particles, score_particles, write_particles
from napari_lbs._core.learning._metrics import depth_errors_um, diameter_errors_um, seed_scores


def table(*rows):
    rows = np.array(rows, dtype=float).reshape(-1, 4)
    return {"x_um": rows[:, 0], "y_um": rows[:, 1], "z_um": rows[:, 2], "diameter_um": rows[:, 3]}


def test_duplicates_count_once_one_to_one_but_repeatedly_for_the_seed():
    truth = table([100, 100, 2000, 25])
    pred = table([101, 100, 2000, 25], [100, 102, 2050, 25], [99, 100, 1950, 25])
    metrics = score_particles(pred, truth)
    assert (metrics["tp"], metrics["fp"], metrics["fn"]) == (1, 2, 0)
    assert metrics["er"] == 1.0 and metrics["ji"] == pytest.approx(1 / 3)
    seed = seed_scores(pred, truth)
    assert (seed["tp"], seed["fp"], seed["fn"]) == (3, 0, 0) and seed["ji"] == 1.0


def test_depth_and_diameter_errors_are_those_of_the_one_to_one_matches():
    truth = table([100, 100, 2000, 25], [500, 500, 3000, 20])
    pred = table([500, 501, 3040, 23.5], [101, 100, 1990, 27], [900, 900, 2000, 25])  # the last matches nothing
    assert sorted(depth_errors_um(pred, truth)) == pytest.approx([-10.0, 40.0])
    assert sorted(diameter_errors_um(pred, truth)) == pytest.approx([2.0, 3.5])
    assert diameter_errors_um(table(), truth).size == 0


def test_exact_tolerance_matches_and_just_beyond_does_not():
    truth = table([0, 0, 2000, 25])
    assert score_particles(table([22, 0, 2150, 25]), truth)["tp"] == 1
    assert score_particles(table([22.001, 0, 2000, 25]), truth)["tp"] == 0
    assert score_particles(table([0, 0, 2150.01, 25]), truth)["tp"] == 0


def test_assignment_maximises_matches_where_greedy_would_not():
    # Prediction 0 is nearest truth 0 but is the only one that can reach truth 1.
    truth = table([0, 0, 2000, 25], [20, 0, 2000, 25])
    pred = table([5, 0, 2000, 25], [-15, 0, 2000, 25])
    assert sorted(match_particles(pred, truth)) == [(0, 1), (1, 0)]
    assert score_particles(pred, truth)["tp"] == 2


def test_empty_prediction_and_empty_truth():
    truth = table([0, 0, 2000, 25], [50, 0, 2000, 25])
    none = table()
    assert score_particles(none, truth) == {"tp": 0, "fp": 0, "fn": 2, "n_truth": 2, "n_pred": 0, "er": 0.0, "ji": 0.0}
    assert score_particles(truth, none) == {"tp": 0, "fp": 2, "fn": 0, "n_truth": 0, "n_pred": 2, "er": 1.0, "ji": 0.0}
    assert score_particles(none, none)["ji"] == 1.0
    with pytest.raises(InputError, match="tolerances"):
        score_particles(truth, truth, lateral_tol_um=0)


def test_evaluate_cli_prints_contract_json(tmp_path):
    write_particles(tmp_path / "truth.csv", table([100, 100, 2000, 25], [300, 100, 3000, 22]))
    write_particles(tmp_path / "pred.csv", table([101, 100, 2010, 24], [500, 500, 4000, 20]))
    result = subprocess.run([sys.executable, "-m", "napari_lbs._cli", "evaluate", str(tmp_path / "pred.csv"), str(tmp_path / "truth.csv"), "--json"], capture_output=True, text=True)
    assert result.returncode == 0
    metrics = json.loads(result.stdout)
    assert {k: metrics[k] for k in ("tp", "fp", "fn", "n_truth", "n_pred")} == {"tp": 1, "fp": 1, "fn": 1, "n_truth": 2, "n_pred": 2}
    assert metrics["er"] == 0.5 and metrics["ji"] == pytest.approx(1 / 3)
    missing = subprocess.run([sys.executable, "-m", "napari_lbs._cli", "evaluate", str(tmp_path / "nope.csv"), str(tmp_path / "truth.csv"), "--json"], capture_output=True, text=True)
    assert missing.returncode == 2 and "nope.csv" in missing.stderr
