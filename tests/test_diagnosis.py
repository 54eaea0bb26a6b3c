"""Gap diagnosis as amortized inference: the forest, the posterior, the two-sample test, the cache, the refusals.

A small setup (a 256² sensor read as 4 × 4 tiles of 64 px, a few effects) keeps every
diagnoser here under a minute on 2 cores; the full-size figures are in benchmarks/bench_diagnosis.py.
"""

import json

import numpy as np
import pytest
import tifffile

from napari_lbs._core import ExperimentConfig, InputError, read_hologram
from napari_lbs._core.physics._effects import optical_hologram, sensor_image
from napari_lbs._core.gap import DiagnosisSettings, amortized_diagnoser, c2st, diagnose_hologram, mmd, forest_posterior, known_sensor, load_diagnoser, write_report
from napari_lbs._core.gap._amortized import forest_answers
from napari_lbs._core.gap._amortized import _simulate
from napari_lbs._core.gap._forest import ForestArrays, train_forest
from napari_lbs._core.gap._scenarios import ScenarioPrior, TileGrid, draw_scenario, simulate_tiles
from napari_lbs._core.foundation._progress import Stopped
from napari_lbs._core.physics._synthesis import random_particle_field

CONFIG = ExperimentConfig()
GRID = TileGrid((256, 256), 64)
SMALL = ScenarioPrior(candidates=("illumination", "sensor_blur", "shot_noise"), none=0.25, one=0.75, strength=(0.6, 1.0), density=(0.7, 1.5))
TRUTH = {"contrast": 0.9, "sigma": 0.02, "gamma": 1.0}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A diagnoser of the small setup, trained once for this module (and its cache folder)."""
    cache = tmp_path_factory.mktemp("diagnosers")
    settings = DiagnosisSettings(simulations=160, trees=60, jobs=1, cache_dir=str(cache))
    return amortized_diagnoser(CONFIG, GRID, SMALL, settings=settings), settings


def hologram(effects=None, *, seed=0, shape=(256, 256), count=16):
    rng = np.random.default_rng(seed)
    field = random_particle_field(shape, count=count, diameter_min_um=20, diameter_max_um=30, layers_um=CONFIG.layer_depths_um(), pixel_um=2.2, seed=rng)
    image = sensor_image(optical_hologram(field, {}, wavelength_um=0.66), TRUTH, effects or {}, noise=rng.standard_normal(shape).astype(np.float32))
    return np.clip(np.round(image * 140), 0, 255).astype(np.uint8)


def test_the_forest_as_arrays_answers_as_scikit_learn_does_and_refuses_inconsistent_arrays():
    from sklearn.ensemble import RandomForestClassifier

    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 6)).astype(np.float32)
    y = np.stack([x[:, 0] > 0, x[:, 1] + x[:, 2] > 0.5], axis=1)
    forest = train_forest(x, y, trees=20, seed=3)
    reference = RandomForestClassifier(n_estimators=20, min_samples_leaf=2, max_features="sqrt", random_state=3).fit(x, y.astype(np.int8))
    expected = np.stack([p[:, 1] for p in reference.predict_proba(x[:50])], axis=1)
    np.testing.assert_allclose(forest.predict(x[:50]), expected, atol=1e-6)
    assert forest.leaves(x[:5]).shape == (5, 20)
    arrays = forest.arrays()
    np.testing.assert_array_equal(ForestArrays.from_arrays(arrays).predict(x[:9]), forest.predict(x[:9]))
    arrays["forest_left"] = arrays["forest_left"] + 10**6
    with pytest.raises(ValueError, match="out of range"):
        ForestArrays.from_arrays(arrays)
    cyclic = forest.arrays()
    inner = int(np.flatnonzero(cyclic["forest_left"] >= 0)[0])
    cyclic["forest_left"][inner] = inner  # a node its own child: evaluation would never end
    with pytest.raises(ValueError, match="cycle"):
        ForestArrays.from_arrays(cyclic)


def test_one_forest_learns_the_model_and_each_effect_and_the_posterior_sums_to_one():
    from types import SimpleNamespace

    present = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 1]], bool)
    assert forest_answers(present).astype(int).tolist() == [[0, 0, 0, 1, 0, 0, 0, 0], [1, 0, 0, 0, 1, 0, 0, 0], [0, 1, 1, 0, 0, 0, 0, 1]]
    # the forest says: two effects (0.7), most likely b and c
    answers = np.array([[0.2, 0.9, 0.8, 0.1, 0.1, 0.1, 0.0, 0.7]])
    fake = SimpleNamespace(candidates=("a", "b", "c"), forest=SimpleNamespace(predict=lambda x: answers))
    presence, model = forest_posterior(fake, np.zeros(4))
    assert presence == pytest.approx({"a": 0.2, "b": 0.9, "c": 0.8})
    assert sum(model.values()) == pytest.approx(1.0) and max(model, key=model.get) == "b+c" and model["null"] == pytest.approx(0.1)
    assert model["b+c"] > model["a+b"] > model["a+c"] * 0.99 and model["c"] == 0.0


def test_c2st_is_chance_for_two_samples_of_one_distribution_and_near_one_for_different_ones():
    rng = np.random.default_rng(1)
    same = [c2st(rng.normal(size=(64, 10)), rng.normal(size=(64, 10)), seed=s)["accuracy"] for s in range(5)]
    assert abs(np.mean(same) - 0.5) < 0.08
    apart = c2st(rng.normal(size=(64, 10)), rng.normal(size=(64, 10)) + 1.5, seed=0)
    assert apart["accuracy"] > 0.95 and apart["interval"][0] > 0.85 and apart["real_probability"].shape == (64,)


def test_two_samples_of_one_simulator_are_not_told_apart_and_a_blurred_one_is():
    from napari_lbs._core.gap._features import set_summaries
    from napari_lbs._core.gap._scenarios import Scenario

    def tiles(effects, seed):
        scenario = Scenario((), effects, dict(TRUTH), {}, 1.0)
        out = []
        for k in range(4):
            out += simulate_tiles(scenario, CONFIG, GRID, np.random.default_rng([seed, k]))
        return set_summaries(out, config=CONFIG)[0]

    first, second, blurred = tiles({}, 1), tiles({}, 2), tiles({"sensor_blur": {"sigma_px": 1.5}}, 3)
    same, apart = c2st(first, second), c2st(first, blurred)
    assert abs(same["accuracy"] - 0.5) < 0.15 and apart["accuracy"] > 0.9
    assert mmd(first, blurred)["value"] > 5 * max(mmd(first, second)["value"], 0.01)


def test_mmd_is_near_zero_for_one_distribution_and_grows_with_the_difference():
    rng = np.random.default_rng(2)
    same = mmd(rng.normal(size=(64, 10)), rng.normal(size=(96, 10)))
    near, far = (mmd(rng.normal(size=(64, 10)), rng.normal(size=(96, 10)) + shift)["value"] for shift in (0.5, 2.0))
    assert abs(same["value"]) < 0.02 and same["interval"][0] <= same["value"] <= same["interval"][1]
    assert far > near > 0.05


def test_a_scenario_has_its_nuisances_and_particle_phase_means_transparent_particles():
    from napari_lbs._core.gap._scenarios import OPAQUE, TRANSPARENT

    rng = np.random.default_rng(2)
    prior = ScenarioPrior(candidates=("particle_phase", "sensor_blur"))
    seen = {"transparent": 0, "opaque spheres": 0, "discs": 0}
    for _ in range(200):
        scenario = draw_scenario(prior, rng)
        spheres = scenario.effects.get("particle_phase")
        if "particle_phase" in scenario.present:
            assert spheres["transmission"] >= TRANSPARENT
            seen["transparent"] += 1
        elif spheres:
            assert spheres["transmission"] <= OPAQUE
            seen["opaque spheres"] += 1
        else:
            seen["discs"] += 1
        assert len(scenario.present) <= 2 and 0.5 <= scenario.baseline["contrast"] <= 1.2
    assert min(seen.values()) > 20
    # the tiles of a scenario: the grid's tiles, each at its place on the sensor
    tiles = simulate_tiles(draw_scenario(SMALL, np.random.default_rng(3)), CONFIG, GRID, np.random.default_rng(4))
    assert len(tiles) == 16 and all(t.shape == (64, 64) and np.isfinite(t).all() for t in tiles)


def test_the_diagnoser_names_the_effect_of_fresh_simulations_from_its_own_prior(small):
    diagnoser, _ = small
    right = 0
    trials = 40
    for index in range(10_000, 10_000 + trials):  # simulations the forest never saw
        _, features, _, present, _ = _simulate((index, CONFIG, GRID, SMALL, 0))
        _, posterior = forest_posterior(diagnoser, features)
        best = max(posterior, key=posterior.get)
        right += best == ("+".join(present) if present else "null")
    assert right / trials >= 0.95


def test_the_same_input_gives_the_same_posterior_whatever_the_seed_and_the_cache_is_reused(small, monkeypatch):
    diagnoser, settings = small
    image = hologram({"sensor_blur": {"sigma_px": 1.5}}, seed=5)
    # the module's diagnoser is the small setup's; a hologram's own setup has the whole catalog,
    # so the small prior is put in by hand here
    import napari_lbs._core.gap._diagnose as diagnose_module

    monkeypatch.setattr(diagnose_module, "catalog_candidates", lambda known: SMALL.candidates)
    monkeypatch.setattr(diagnose_module, "ScenarioPrior", lambda **kw: SMALL)
    import napari_lbs._core.gap._amortized as amortized

    def no_training(*args, **kwargs):
        raise AssertionError("the cached diagnoser was not reused")

    monkeypatch.setattr(amortized, "_simulations", no_training)
    first = diagnose_hologram(image, CONFIG, settings=settings).report
    again = diagnose_hologram(image, CONFIG, settings=DiagnosisSettings(**{**settings.__dict__, "seed": 7})).report
    assert first["posterior"] == again["posterior"] and first["verdict"]["id"] == again["verdict"]["id"] == "sensor_blur"
    assert first["diagnoser"]["key"] == diagnoser.key
    assert first["effects"][0]["id"] == "sensor_blur" and "sigma_px" in first["effects"][0]["params"]


def test_a_config_change_makes_another_diagnoser_and_a_stop_caches_nothing(small, tmp_path):
    _, settings = small
    other = ExperimentConfig.from_dict({**CONFIG.to_dict(), "optics": {**CONFIG.to_dict()["optics"], "wavelength_um": 0.532}})
    calls = []

    def stop():
        calls.append(1)
        return len(calls) > 3

    quick = DiagnosisSettings(simulations=20, trees=10, jobs=1, cache_dir=str(tmp_path))
    with pytest.raises(Stopped):
        amortized_diagnoser(other, GRID, SMALL, settings=quick, should_stop=stop)
    assert not list(tmp_path.glob("*.npz"))
    made = amortized_diagnoser(other, GRID, SMALL, settings=quick)
    assert made.key != small[0].key and len(list(tmp_path.glob("diagnoser-*.npz"))) == 1


def test_a_corrupt_or_foreign_cache_file_is_refused_in_one_line_and_never_executed(small, tmp_path):
    diagnoser, settings = small
    path = next(p for p in __import__("pathlib").Path(settings.cache_dir).glob(f"diagnoser-{diagnoser.key}.npz"))
    assert load_diagnoser(path).key == diagnoser.key
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a cache")
    evil = tmp_path / "evil.npz"
    np.savez(evil, meta=np.array([{"format": "napari-lbs diagnoser 1"}], dtype=object))  # needs pickle to read
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    for bad in (garbage, evil, truncated):
        with pytest.raises(InputError) as refused:
            load_diagnoser(bad)
        assert "\n" not in str(refused.value) and bad.name in str(refused.value)


@pytest.mark.parametrize(("dtype", "top", "bits"), [(np.uint8, 200, 8), (np.uint8, 255, 8), (np.uint16, 4095, 12), (np.uint16, 60000, 16)])
def test_known_bit_depth_is_read_from_integer_files(tmp_path, dtype, top, bits):
    rng = np.random.default_rng(0)
    counts = rng.integers(1, top + 1, (64, 64)).astype(dtype)
    counts[0, 0] = top
    path = tmp_path / "holo.tif"
    tifffile.imwrite(path, counts)
    for image in (counts, read_hologram(path)):  # the integer array, and the float32 the CLI reads
        facts = known_sensor(image)
        assert facts["bits"] == bits and facts["full_scale"] == 2**bits - 1
    clipped = np.minimum(counts, dtype(top // 2))  # a clipped camera piles its brightest pixels up at one value
    assert known_sensor(clipped)["saturation"] == top // 2
    assert known_sensor(rng.random((64, 64)).astype(np.float32)) is None  # a float simulation states nothing
    assert known_sensor(counts)["levels_used"] > 0.9 and not known_sensor(counts)["coarse"]


def test_values_coarser_than_the_file_format_are_found_coarse():
    image = hologram(seed=3).astype(np.float32) / 140
    six_bits = (np.clip(np.round(image * 35), 0, 63) * 4).astype(np.uint8)  # a 6-bit image in a uint8 file: every 4th level
    facts = known_sensor(six_bits)
    assert facts["coarse"] and facts["levels_used"] <= 0.3 and abs(facts["effective_bits"] - 6.0) < 0.3
    assert not known_sensor(np.clip(np.round(image * 140), 0, 255).astype(np.uint8))["coarse"]


def test_a_diagnosis_pools_frames_states_what_is_known_and_writes_strict_json(small, tmp_path, monkeypatch):
    _, settings = small
    import napari_lbs._core.gap._diagnose as diagnose_module

    seen = {}

    def small_prior(**kwargs):
        seen.update(kwargs)
        return SMALL

    monkeypatch.setattr(diagnose_module, "catalog_candidates", lambda known: SMALL.candidates)
    monkeypatch.setattr(diagnose_module, "ScenarioPrior", small_prior)
    frames = np.stack([hologram(seed=s) for s in (1, 2)])
    beads = {"particle_phase": {"index_contrast": 0.26, "transmission": 1.0}}
    diagnosis = diagnose_hologram(frames, CONFIG, stated=beads, settings=settings)
    report = diagnosis.report
    # the file's 8 bits and the stated beads go into every simulation, and are not candidates
    assert seen["bits"] == 8.0 and seen["known"] == beads and report["stated"] == beads and report["known"]["quantization"] == {"bits": 8.0}
    assert report["tiles"]["frames"] == 2 and sum(report["posterior"].values()) == pytest.approx(1.0)
    assert report["verdict"].keys() >= {"id", "shrink", "residual", "undecided", "catalog_explains", "probability"}
    assert diagnosis.tile_map.shape == (4, 4)
    report["effects"][0]["shrink"] = float("nan")  # whatever a computation leaves, the file stays strict JSON
    paths = write_report(diagnosis, tmp_path / "r")
    text = (tmp_path / "r" / "report.json").read_text()
    json.loads(text, parse_constant=lambda name: pytest.fail(f"report.json holds {name}"))
    assert all(p.exists() for p in paths) and (tmp_path / "r" / "gap_effects.png").stat().st_size > 1000
    # written again: refused without force, nothing touched; replaced with it; a link is never written through
    (tmp_path / "r" / "report.md").write_text("mine")
    with pytest.raises(InputError, match="report.json: exists; add force=True"):
        write_report(diagnosis, tmp_path / "r")
    assert (tmp_path / "r" / "report.md").read_text() == "mine"
    assert write_report(diagnosis, tmp_path / "r", force=True) == paths and (tmp_path / "r" / "report.md").read_text() != "mine"
    (tmp_path / "linked").mkdir()
    (tmp_path / "linked" / "gap_where.png").symlink_to(tmp_path / "r" / "report.md")
    with pytest.raises(InputError, match="symbolic link"):
        write_report(diagnosis, tmp_path / "linked", force=True)
    assert not (tmp_path / "linked" / "report.json").exists()
    assert not diagnose_hologram(frames[0], CONFIG, known=False, settings=settings).report["known"]


@pytest.mark.parametrize("image", [np.zeros((256, 256), np.float32), np.full((256, 256), 7.0, np.float32), -np.random.default_rng(0).random((256, 256)).astype(np.float32)])
def test_diagnose_refuses_images_that_are_no_intensity_in_one_line(image):
    with pytest.raises(InputError) as refused:
        diagnose_hologram(image, CONFIG)
    assert "\n" not in str(refused.value)


def test_diagnose_refuses_small_holograms_frames_of_different_shapes_and_unknown_effects():
    with pytest.raises(InputError, match="at least 64 pixels"):
        diagnose_hologram(hologram(shape=(200, 200)), CONFIG)
    with pytest.raises(InputError, match="frame 1"):
        diagnose_hologram([hologram(), hologram(shape=(256, 320))], CONFIG)
    with pytest.raises(InputError, match="unknown effect id 'beads'"):
        diagnose_hologram(hologram(), CONFIG, stated={"beads": {}})
    with pytest.raises(InputError, match="simulations"):
        DiagnosisSettings(simulations=3)


def test_tiles_are_summarised_on_threads_as_each_would_be_alone_also_after_a_fork():
    import multiprocessing

    from napari_lbs._core.gap import tile_summaries
    from napari_lbs._core.gap._summaries import _tiles_summaries

    rng = np.random.default_rng(4)
    tiles = [1.0 + 0.1 * rng.standard_normal((64, 64)) for _ in range(5)]
    means, around = [1.0, 1.1, None, 0.9, 1.0], [None, np.ones((128, 128)), None, None, np.full((128, 128), 1.2)]
    alone = np.stack([tile_summaries(t, config=CONFIG, fringe_frequency=(0.1, 0.0), field_mean=m, surroundings=a)[0] for t, m, a in zip(tiles, means, around, strict=True)])
    together, names = _tiles_summaries(tiles, config=CONFIG, fringe_frequency=(0.1, 0.0), field_means=means, surroundings=around)
    assert np.array_equal(together, alone) and names == tile_summaries(tiles[0], config=CONFIG)[1]
    # a child forked after the pool started gets threads of its own (else it would wait for ever)
    with multiprocessing.get_context("fork").Pool(1) as pool:
        child = pool.apply_async(_tiles_summaries, (tiles,), {"config": CONFIG, "fringe_frequency": (0.1, 0.0), "field_means": means, "surroundings": around}).get(timeout=60)
    assert np.array_equal(child[0], alone)
