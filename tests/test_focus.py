"""The focus formulation: stack data sets, heat/offset/diameter targets, 3-D peak decoding,
one particle per peak, the focal loss on a tiny set, model files old and new, prediction."""

import io
import json

import numpy as np
import pytest

from napari_lbs._core import (
    DatasetLayout,
    ExperimentConfig,
    HoloParams,
    InputError,
    InputProcessing,
    generate_dataset,
    random_particle_field,
    simulate_hologram,
)
from napari_lbs._core.learning._detection import PeakDecoder, suppress
from napari_lbs._core.learning._heatmaps import FocusSpec, focus_targets

CONTEXT = (-2, -1, 0, 1, 2)


def tiny_config() -> ExperimentConfig:
    return ExperimentConfig.from_dict({
        "volume": {"z_min_um": 1800.0, "z_max_um": 2200.0, "z_step_um": 100.0},
        "particles": {"per_tile": 3, "layer_step_um": 200.0},
        "tile": {"size": 48},
    })


STACK = DatasetLayout(kind="stack", context_planes=2)
PROCESSING = InputProcessing(HoloParams(-0.5, 0.2, 0.8), invert_experiment=True)


@pytest.fixture(scope="module")
def stack_data(tmp_path_factory):
    return generate_dataset(tmp_path_factory.mktemp("stack"), tiny_config(), groups=6, processing=PROCESSING, layout=STACK, seed=5)


@pytest.fixture(scope="module")
def focus_model(stack_data, tmp_path_factory):
    from napari_lbs._core import TrainingSettings, train_model

    settings = TrainingSettings(epochs=3, batch_size=4, device="cpu", validation_groups=1, patch_size=32, context=CONTEXT)
    return train_model(stack_data, tmp_path_factory.mktemp("focus") / "f.pt", settings=settings)


# --- data ------------------------------------------------------------------------------------


def test_stack_layout_stores_the_volume_plus_context_at_continuous_depths(stack_data):
    assert stack_data.planes_um == [1600.0, 1700.0, 1800.0, 1900.0, 2000.0, 2100.0, 2200.0, 2300.0, 2400.0]
    inputs, labels, description = stack_data.read_group(1)
    assert inputs.shape == (9, 48, 48) and inputs.dtype == np.float16 and labels.dtype == np.float32
    depths = np.concatenate([np.asarray(stack_data.read_group(g)[2]["particles"]["z_um"]) for g in stack_data.groups])
    assert np.all((depths >= 1800.0) & (depths <= 2200.0))
    assert len(np.unique(depths)) == len(depths)  # not on layers: every particle its own depth
    assert stack_data.layout == STACK


def test_layer_depths_on_request_and_workers_do_not_change_the_set(tmp_path):
    layered = DatasetLayout(kind="stack", context_planes=2, depths="layers")
    one = generate_dataset(tmp_path / "a", tiny_config(), groups=3, layout=layered, seed=1)
    two = generate_dataset(tmp_path / "b", tiny_config(), groups=3, layout=layered, seed=1, workers=2)
    for group in range(3):
        a, b = one.read_group(group), two.read_group(group)
        np.testing.assert_array_equal(a[0], b[0])
        assert set(a[2]["particles"]["z_um"]) <= {1800.0, 2000.0, 2200.0}


# --- targets ---------------------------------------------------------------------------------


def test_targets_peak_on_the_nearest_plane_with_offset_and_diameter():
    particles = {"x_um": np.array([22.0]), "y_um": np.array([44.0]), "z_um": np.array([2030.0]), "diameter_um": np.array([24.0])}
    common = {"step_um": 100.0, "pixel_um": 2.2, "shape": (40, 40), "diameter_scale_um": 30.0, "spec": FocusSpec(context=CONTEXT)}
    on = focus_targets(particles, plane_um=2000.0, **common)
    assert np.argwhere(on.positive).tolist() == [[20, 10]]  # row = 44 / 2.2, col = 22 / 2.2
    assert on.heat[20, 10] == 1.0 and on.offset[20, 10] == pytest.approx(0.3) and on.diameter[20, 10] == pytest.approx(0.8)
    assert on.heat[20, 11] == pytest.approx(np.exp(-0.3**2 / 2) * np.exp(-0.5))  # Gaussian of one pixel, one plane
    beside = focus_targets(particles, plane_um=2100.0, **common)  # 0.7 planes away: a near negative
    assert not beside.positive.any() and beside.heat[20, 10] == pytest.approx(np.exp(-0.7**2 / 2))
    far = focus_targets(particles, plane_um=2400.0, **common)
    assert not far.heat.any()
    # a crop shifts the pixel; a particle between two planes belongs to exactly one of them
    cropped = focus_targets(particles, plane_um=2000.0, origin_px=(10, 5), **common)
    assert np.argwhere(cropped.positive).tolist() == [[10, 5]]
    halfway = dict(particles, z_um=np.array([2050.0]))
    owners = [focus_targets(halfway, plane_um=z, **common).positive.any() for z in (2000.0, 2100.0)]
    assert owners == [False, True]


# --- decoding --------------------------------------------------------------------------------


def _blob(shape, row, col, peak, sigma=1.2):
    r, c = np.indices(shape)
    return (peak * np.exp(-((r - row) ** 2 + (c - col) ** 2) / (2 * sigma**2))).astype(np.float32)


def test_hand_made_heatmaps_decode_to_the_exact_particles():
    planes = np.arange(1800.0, 2600.0, 100.0)
    shape = (40, 50)
    truth = [(3, 12.0, 30.0, 0.25, 21.0, 0.9), (5, 30.0, 8.0, -0.4, 28.5, 0.7)]  # plane, row, col, offset, diameter, peak
    decoder = PeakDecoder(planes, pixel_um=2.0, step_um=100.0)
    for plane in range(len(planes)):
        probability = np.zeros(shape, np.float32)
        offset = np.zeros(shape, np.float32)
        diameter = np.zeros(shape, np.float32)
        for p, row, col, off, d, peak in truth:
            weight = np.exp(-((plane - p) ** 2) / 2.0)  # the response fades over neighbouring planes
            probability = np.maximum(probability, _blob(shape, row, col, peak * weight))
            offset[int(row), int(col)] = off
            diameter[int(row), int(col)] = d
        decoder.add(plane, probability, offset, diameter)
    found = suppress(decoder.candidates(), threshold=0.5, lateral_um=10.0, axial_um=200.0)
    assert len(found["x_um"]) == 2
    order = np.argsort(found["z_um"])
    for index, (p, row, col, off, d, peak) in zip(order, truth, strict=True):
        assert found["x_um"][index] == pytest.approx(col * 2.0, abs=1e-4)
        assert found["y_um"][index] == pytest.approx(row * 2.0, abs=1e-4)
        assert found["z_um"][index] == pytest.approx(planes[p] + off * 100.0)
        assert found["diameter_um"][index] == pytest.approx(d)
        assert found["score"][index] == pytest.approx(peak)


def test_non_maximum_suppression_keeps_one_particle_per_peak():
    candidates = {
        "x_um": np.array([10.0, 12.0, 10.0, 60.0]),
        "y_um": np.array([10.0, 11.0, 10.0, 10.0]),
        "z_um": np.array([2000.0, 2150.0, 2900.0, 2000.0]),
        "diameter_um": np.array([25.0, 25.0, 25.0, 25.0]),
        "score": np.array([0.9, 0.6, 0.8, 0.4]),
    }
    kept = suppress(candidates, threshold=0.3, lateral_um=10.0, axial_um=300.0)
    # the second is the first seen again 150 um deeper: dropped; the third is 900 um away: its own particle
    assert sorted(kept["score"].tolist()) == [0.4, 0.8, 0.9]
    assert sorted(suppress(candidates, threshold=0.3, lateral_um=10.0, axial_um=np.inf)["score"].tolist()) == [0.4, 0.9]
    assert suppress(candidates, threshold=0.5, lateral_um=10.0, axial_um=300.0)["score"].tolist() == [0.9, 0.8]  # sorted by depth
    assert len(suppress(candidates, threshold=0.95, lateral_um=10.0, axial_um=300.0)["x_um"]) == 0


def test_suppression_at_a_threshold_is_suppression_at_a_lower_one_cut_at_it():
    # the validation scores every threshold from one suppression at the lowest
    from napari_lbs._core.learning._formulations import FOCUS_THRESHOLDS, _at_least

    rng = np.random.default_rng(3)
    n = 400
    candidates = {"x_um": rng.uniform(0, 200, n), "y_um": rng.uniform(0, 200, n), "z_um": rng.uniform(0, 60, n),
                  "diameter_um": rng.uniform(0.5, 3, n), "score": rng.uniform(0.05, 0.6, n)}
    for axial_um in (1.0, 2.5, np.inf):
        lowest = suppress(candidates, threshold=FOCUS_THRESHOLDS[0], lateral_um=8.0, axial_um=axial_um)
        for threshold in (0.07, 0.23, 0.31, 0.55):
            direct = suppress(candidates, threshold=threshold, lateral_um=8.0, axial_um=axial_um)
            cut = _at_least(lowest, threshold)
            assert {name: values.tolist() for name, values in direct.items()} == {name: values.tolist() for name, values in cut.items()}


def test_the_validation_finds_a_threshold_between_the_tenths():
    # peaks crowded between 0.2 and 0.3: the true ones at 0.26-0.29, the false at 0.21-0.24
    from napari_lbs._core.learning import _formulations

    formulation = _formulations._FocusFormulation.__new__(_formulations._FocusFormulation)
    formulation.lateral_um, formulation.step_um = 0.25, 0.5
    truth = {"x_um": np.array([5.0, 15.0, 25.0]), "y_um": np.array([5.0, 5.0, 5.0]), "z_um": np.array([20.0, 30.0, 40.0]), "diameter_um": np.array([1.0, 1.0, 1.0])}
    candidates = {"x_um": np.array([5.0, 15.0, 25.0, 40.0, 50.0]), "y_um": np.array([5.0, 5.0, 5.0, 30.0, 30.0]), "z_um": np.array([20.0, 30.0, 40.0, 20.0, 30.0]),
                  "diameter_um": np.ones(5), "score": np.array([0.26, 0.27, 0.29, 0.22, 0.24])}
    formulation.dataset = type("Groups", (), {"read_group": staticmethod(lambda group: (None, None, {"particles": truth}))})()
    formulation.candidates = lambda network, stack: candidates
    metrics = formulation.validate(None, [0], lambda: False)
    # 0.25 and 0.26 tie at JI 1, which has no binomial error: the upper edge of the two
    assert metrics["threshold"] == 0.26 and (metrics["tp"], metrics["fp"], metrics["fn"]) == (3, 0, 0)
    assert metrics["peak_threshold"] == 0.25 and metrics["peak_ji"] == 1.0
    assert metrics["median_abs_dz_um"] == 0.0
    assert any(m["threshold"] == 0.2 for m in metrics["by_threshold"]) and any(m["threshold"] == metrics["threshold"] for m in metrics["by_threshold"])


def test_the_kept_threshold_is_the_upper_edge_of_the_peak_within_a_standard_error():
    from napari_lbs._core.learning._formulations import _upper_edge

    # JI 0.8 of 100 counted: a binomial error of 0.04, so 0.79 and 0.77 are the peak's plateau, 0.70 is not
    assert _upper_edge([0.5, 0.80, 0.79, 0.77, 0.70, 0.78], 1, counted=100) == 3
    # a dip below the plateau ends the walk even when a later threshold comes back within it
    assert _upper_edge([0.80, 0.70, 0.79], 0, counted=100) == 0
    # ten times the counts: an error of 0.0126, and only 0.79 is within it
    assert _upper_edge([0.5, 0.80, 0.79, 0.77, 0.70], 1, counted=1000) == 2
    assert _upper_edge([0.9], 0, counted=0) == 0


def test_a_plateau_or_a_peak_on_the_last_plane_is_still_one_particle():
    planes = [1800.0, 1900.0, 1950.0]
    decoder = PeakDecoder(planes, pixel_um=2.0, step_um=50.0)
    zero = np.zeros((20, 20), np.float32)
    flat = zero.copy()
    flat[5, 5] = flat[5, 6] = 0.8  # two equal pixels
    decoder.add(0, zero, zero, zero)
    decoder.add(1, zero, zero, zero)
    decoder.add(2, flat, zero, zero + 20.0)
    found = suppress(decoder.candidates(), threshold=0.5, lateral_um=10.0, axial_um=100.0)
    assert len(found["x_um"]) == 1 and found["z_um"][0] == 1950.0 and found["x_um"][0] == pytest.approx(11.0)


# --- training, model files, prediction -------------------------------------------------------


def test_focal_loss_falls_on_a_tiny_set_and_validation_chooses_the_decoding(focus_model):
    log = focus_model.log
    losses = [epoch["train_loss"] for epoch in log["epochs"]]
    assert len(losses) == 3 and losses[-1] < losses[0]
    best = log["best"]
    assert 0 < best["threshold"] < 1 and "axial_um" in best
    assert log["dataset"]["layout"]["kind"] == "stack"


def test_the_loss_rewards_a_peak_at_the_particle_and_punishes_far_false_positives(stack_data):
    import torch

    from napari_lbs._core.learning._formulations import _FocusFormulation
    from napari_lbs._core.learning._training_settings import TrainingSettings

    formulation = _FocusFormulation(stack_data, [0, 1], TrainingSettings(context=CONTEXT, patch_size=32))
    heat = torch.zeros(1, 8, 8)
    heat[0, 4, 4] = 1.0
    heat[0, 4, 5] = 0.6
    positive = heat == 1.0
    targets = (heat, torch.zeros(1, 8, 8), torch.full((1, 8, 8), 0.8), positive.float())

    def loss_for(logit_map):
        prediction = torch.stack([logit_map, torch.zeros(1, 8, 8), torch.full((1, 8, 8), 1.0)], dim=1)
        return float(formulation.loss(prediction, targets))

    background = torch.full((1, 8, 8), -6.0)
    right = background.clone()
    right[0, 4, 4] = 6.0
    far_false = right.clone()
    far_false[0, 0, 0] = 6.0
    near_false = right.clone()
    near_false[0, 4, 5] = 6.0
    assert loss_for(right) < loss_for(background)
    assert loss_for(right) < loss_for(near_false) < loss_for(far_false)  # a near negative costs less


def test_diameters_are_positive_and_scores_are_probabilities(focus_model):
    from napari_lbs._core import load_model, predict_particles

    config = tiny_config()
    field = random_particle_field((100, 90), count=8, diameter_min_um=20, diameter_max_um=30, layers_um=(1800.0, 2200.0), continuous=True, pixel_um=2.2, seed=1)
    hologram = simulate_hologram(field, wavelength_um=0.66)
    seen = []
    model = load_model(focus_model.model_path)
    assert model.formulation == "focus" and model.meta["context"] == list(CONTEXT)
    import torch

    with torch.no_grad():  # a network that sees particles everywhere: many peaks to check
        model.network.head.bias[0] = 3.0
        model.network.head.bias[2] = -8.0  # raw diameters far below zero before the softplus
    model.meta["threshold"] = 0.5
    result = predict_particles(hologram, model, config, progress=lambda d, t: seen.append((d, t)))
    assert seen[-1] == (14, 14)  # 9 planes back-propagated (5 and the context reach of 2 on each side), then 5 through the network
    table = result.particles
    assert len(table["x_um"]) > 0
    assert np.all(table["diameter_um"] >= 0) and np.all((table["score"] > 0) & (table["score"] <= 1))
    assert np.all((table["z_um"] >= 1800.0 - 100.0) & (table["z_um"] <= 2200.0 + 100.0))
    assert result.provenance["formulation"] == "focus" and result.provenance["context"] == list(CONTEXT)
    other = ExperimentConfig.from_dict({**config.to_dict(), "volume": {"z_min_um": 1800.0, "z_max_um": 2200.0, "z_step_um": 50.0}})
    with pytest.raises(InputError, match="volume.z_step_um: the model was trained on planes 100 µm apart"):
        predict_particles(hologram, model, other)


def test_a_lower_threshold_keeps_the_same_detections_and_more(focus_model):
    """A score threshold below the model's: every detection of the model's threshold, plus the weaker peaks; the provenance says which was used."""
    import torch

    from napari_lbs._core import load_model, predict_particles

    field = random_particle_field((100, 90), count=8, diameter_min_um=20, diameter_max_um=30, layers_um=(1800.0, 2200.0), continuous=True, pixel_um=2.2, seed=1)
    hologram = simulate_hologram(field, wavelength_um=0.66)
    model = load_model(focus_model.model_path)
    with torch.no_grad():
        model.network.head.bias[0] = 3.0  # a network that sees particles everywhere: peaks of many scores
    trained = model.meta["threshold"]
    loose = predict_particles(hologram, model, tiny_config(), threshold=0.1)
    assert loose.provenance["threshold"] == 0.1 and loose.provenance["model_threshold"] == trained
    model.meta["threshold"] = float(np.median(loose.particles["score"]))
    strict = predict_particles(hologram, model, tiny_config())
    assert strict.provenance["threshold"] == strict.provenance["model_threshold"] == model.meta["threshold"]
    kept = loose.particles["score"] >= model.meta["threshold"]
    assert 0 < kept.sum() < len(kept)
    for name in ("x_um", "y_um", "z_um", "score"):
        np.testing.assert_array_equal(np.sort(loose.particles[name][kept]), np.sort(strict.particles[name]))
    with pytest.raises(InputError, match="threshold: expected a positive score"):
        predict_particles(hologram, model, tiny_config(), threshold=0.0)


def test_the_focus_formulation_refuses_a_layers_data_set(tmp_path):
    from napari_lbs._core import TrainingSettings, train_model

    layers = generate_dataset(tmp_path / "l", tiny_config(), groups=2, layout=DatasetLayout(kind="layers"))
    with pytest.raises(InputError, match="needs a data set of the stack layout"):
        train_model(layers, tmp_path / "m.pt", settings=TrainingSettings(device="cpu", validation_groups=1))
    with pytest.raises(InputError, match="context planes"):
        generated = generate_dataset(tmp_path / "s", tiny_config(), groups=2, layout=DatasetLayout(context_planes=1))
        train_model(generated, tmp_path / "m.pt", settings=TrainingSettings(device="cpu", validation_groups=1, context=CONTEXT))


def test_a_time_budget_stops_training_with_a_validated_model(stack_data, tmp_path):
    from napari_lbs._core import TrainingSettings, load_model, train_model

    result = train_model(stack_data, tmp_path / "t.pt", settings=TrainingSettings(epochs=50, batch_size=2, device="cpu", validation_groups=1, patch_size=32, context=CONTEXT, minutes=0.02))
    assert result.stopped and len(result.log["epochs"]) < 50
    assert load_model(tmp_path / "t.pt").meta["epoch"] == result.log["best"]["epoch"]


def test_model_files_load_without_code_and_old_files_keep_their_formulation(focus_model, tmp_path):
    import torch

    from napari_lbs._core import load_model

    payload = torch.load(io.BytesIO(focus_model.model_path.read_bytes()), weights_only=True)  # plain tensors and strings
    assert payload["version"] == 2 and json.loads(payload["meta"])["formulation"] == "focus"
    # a version-1 file (before the focus formulation) has no formulation: it is the seed's, and loads as such
    from napari_lbs._core.learning._network import build_network

    network = build_network("small")
    meta = {"preset": "small", "widths": [8, 16, 32, 64, 64], "tile_size": 48, "config": tiny_config().to_dict()}
    buffer = io.BytesIO()
    torch.save({"format": "napari-lbs-model", "version": 1, "state_dict": network.state_dict(), "meta": json.dumps(meta)}, buffer)
    (tmp_path / "v1.pt").write_bytes(buffer.getvalue())
    assert load_model(tmp_path / "v1.pt").formulation == "seed"
    buffer = io.BytesIO()
    torch.save({"format": "napari-lbs-model", "version": 2, "state_dict": network.state_dict(), "meta": json.dumps(meta | {"formulation": "magic"})}, buffer)
    (tmp_path / "bad.pt").write_bytes(buffer.getvalue())
    with pytest.raises(InputError, match="unknown formulation 'magic'"):
        load_model(tmp_path / "bad.pt")


def test_tile_normalisation_is_each_tiles_own_at_its_centre_and_stays_in_range():
    from napari_lbs._core.calibration._calibrate import experimental_planes
    from napari_lbs._core.learning._prediction import tile_layout, tile_normalisation

    rng = np.random.default_rng(4)
    raw = rng.gamma(4.0, 0.25, (3, 80, 70)).astype(np.float32)
    raw[:, :, 40:] *= 3.0  # tiles with other statistics on the right
    size = 33  # odd: each tile's centre is a pixel
    layout = (tile_layout(80, size=size, margin=4), tile_layout(70, size=size, margin=4))
    for invert, mode in ((True, "robust"), (False, "seed")):
        normalised = raw.copy()
        tile_normalisation(normalised, layout, size, invert=invert, mode=mode)
        assert normalised.min() >= 0.0 and normalised.max() <= 1.0
        for r, _, _ in layout[0]:
            for c, _, _ in layout[1]:
                own = experimental_planes(raw[:, r : r + size, c : c + size], invert=invert, mode=mode)
                np.testing.assert_allclose(normalised[:, r + size // 2, c + size // 2], own[:, size // 2, size // 2], atol=1e-5)
    # one tile: exactly the tile's own normalisation everywhere
    single = raw[:, :32, :32].copy()
    tile_normalisation(single, ([(0, 0, 32)], [(0, 0, 32)]), 32, invert=True, mode="robust")
    np.testing.assert_allclose(single, experimental_planes(raw[:, :32, :32], invert=True, mode="robust"), atol=1e-6)


def test_the_inference_network_folds_batch_norm_without_changing_the_outputs():
    import torch

    from napari_lbs._core.learning._network import build_network, inference_network

    torch.manual_seed(0)
    network = build_network("small", in_channels=9, out_channels=3).eval()
    for norm in (m for m in network.modules() if isinstance(m, torch.nn.BatchNorm2d)):  # statistics far from the identity
        norm.running_mean.uniform_(-1.0, 1.0), norm.running_var.uniform_(0.2, 3.0), norm.weight.data.uniform_(0.5, 1.5), norm.bias.data.uniform_(-0.5, 0.5)
    fused = inference_network(network)
    inputs = torch.rand(2, 9, 64, 48)
    with torch.inference_mode():
        expected, got = network(inputs), fused(inputs)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    assert torch.allclose(got, expected, atol=1e-5, rtol=1e-5) and expected.abs().max() > 0.1
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in network.modules()) == 2 * len(network.widths) * 2 - 2  # the original keeps its norms


def test_bfloat16_runs_the_network_close_to_float32_with_float32_outputs():
    import torch

    from napari_lbs._core.learning._network import build_network, inference_network

    torch.manual_seed(0)
    network = build_network("small", in_channels=9, out_channels=3).eval()
    inputs = torch.rand(2, 9, 64, 48)
    with torch.inference_mode():
        expected = network(inputs)
        network.precision = "bfloat16"
        got = network(inputs)
    assert got.dtype == torch.float32 and inference_network(network).precision == "bfloat16"
    assert not torch.equal(got, expected)  # the body really ran in bfloat16
    assert (got - expected).abs().max() < 0.05 * expected.abs().max()


def test_precision_auto_follows_the_hardware_and_unknown_values_are_refused(monkeypatch):
    import torch

    from napari_lbs._core import TrainingSettings
    from napari_lbs._core.learning._network import resolve_precision

    cpu = torch.device("cpu")
    assert [resolve_precision(name, cpu) for name in ("float32", "bfloat16")] == ["float32", "bfloat16"]
    for native, expected in ((False, "float32"), (True, "bfloat16")):
        for probe in ("_is_amx_tile_supported", "_is_avx512_bf16_supported"):
            monkeypatch.setattr(torch.cpu, probe, lambda native=native: native, raising=False)
        assert resolve_precision("auto", cpu) == expected
    with pytest.raises(InputError, match="precision: expected one of auto, float32, bfloat16, got 'half'"):
        resolve_precision("half", cpu)
    with pytest.raises(InputError, match="precision"):
        TrainingSettings(precision="half")
