"""Data sets, label decoding, the U-Net, training, model files and prediction of the seed formulation, on tiny data.

The focus formulation has its own tests (test_focus.py)."""

import hashlib
import json
import pickle

import numpy as np
import pytest

from napari_lbs._core import (
    DatasetLayout,
    ExperimentConfig,
    HoloParams,
    InputError,
    InputProcessing,
    ParticleField,
    Stopped,
    generate_dataset,
    match_particles,
    open_dataset,
    random_particle_field,
    score_particles,
    simulate_hologram,
)
from napari_lbs._core.learning._detection import detect_particles
from napari_lbs._core.physics._synthesis import LABEL_SCALE, label_planes


def tiny_config(**volume) -> ExperimentConfig:
    return ExperimentConfig.from_dict({
        "volume": {"z_min_um": 1800.0, "z_max_um": 2200.0, "z_step_um": 100.0, **volume},
        "particles": {"per_tile": 3, "layer_step_um": 200.0},
        "tile": {"size": 48},
    })


PROCESSING = InputProcessing(HoloParams(-0.5, 0.2, 0.8), invert_experiment=True)
LAYERS = DatasetLayout(kind="layers")


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    path = tmp_path_factory.mktemp("data")
    return generate_dataset(path, tiny_config(), groups=6, processing=PROCESSING, layout=LAYERS, seed=3)


@pytest.fixture(scope="module")
def tiny_model(tiny_data, tmp_path_factory):
    from napari_lbs._core import TrainingSettings, train_model

    out = tmp_path_factory.mktemp("model") / "m.pt"
    result = train_model(tiny_data, out, settings=TrainingSettings(formulation="seed", epochs=3, batch_size=4, device="cpu", validation_groups=1, foreground_weight=20.0))
    return result


# --- data sets -------------------------------------------------------------------------------


def test_dataset_round_trip_holds_inputs_labels_truth_and_provenance(tiny_data):
    dataset = open_dataset(tiny_data.path)
    assert dataset.complete and dataset.groups == list(range(6))
    assert dataset.planes_um == [1800.0, 2000.0, 2200.0]
    inputs, labels, description = dataset.read_group(2)
    assert inputs.shape == labels.shape == (3, 48, 48) and inputs.dtype == labels.dtype == np.float32
    assert 0.0 <= inputs.min() and inputs.max() <= 1.0
    truth = description["particles"]
    assert len(truth["x_um"]) == 3
    # the labels are the truth, re-encoded: one 3x3 square of 4 x diameter per particle
    field = ParticleField(*(np.array(truth[k]) for k in ("x_um", "y_um", "z_um", "diameter_um")), (48, 48), 2.2)
    np.testing.assert_array_equal(labels, label_planes(field, dataset.planes_um))
    assert dataset.spec["processing"] == PROCESSING.to_dict() and dataset.spec["seed"] == 3
    assert dataset.config == tiny_config()


def test_generation_is_resumable_and_deterministic(tmp_path, tiny_data):
    calls = []
    stopped = generate_dataset(tmp_path, tiny_config(), groups=6, processing=PROCESSING, layout=LAYERS, seed=3, should_stop=lambda: len(calls) >= 2, progress=lambda d, t: calls.append(d))
    assert stopped.stopped and not stopped.complete and stopped.groups == [0, 1]
    assert json.loads((tmp_path / "dataset.json").read_text())["complete"] is False
    resumed = generate_dataset(tmp_path, tiny_config(), groups=6, processing=PROCESSING, layout=LAYERS, seed=3)
    assert resumed.complete
    for group in range(6):  # same bytes of data as the uninterrupted run
        a, b = resumed.read_group(group), tiny_data.read_group(group)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])


def test_generation_refuses_a_folder_made_with_other_settings(tmp_path):
    generate_dataset(tmp_path, tiny_config(), groups=1, processing=PROCESSING, seed=3)
    with pytest.raises(InputError, match="differs in seed"):
        generate_dataset(tmp_path, tiny_config(), groups=1, processing=PROCESSING, seed=4)
    with pytest.raises(InputError, match="not a napari-lbs data set"):
        open_dataset(tmp_path / "groups")


def test_processing_from_calibration_inverts_the_experiment():
    processing = InputProcessing.from_calibration({"params": {"N_R": -1.0, "N_sigma": 0.2, "gamma": 0.7}, "settings": {"mode": "seed"}})
    assert processing.invert_experiment and processing.mode == "seed" and processing.params == HoloParams(-1.0, 0.2, 0.7)
    with pytest.raises(InputError, match="gamma"):
        InputProcessing.from_calibration({"params": {"N_R": -1.0, "N_sigma": 0.2}})


# --- decoding --------------------------------------------------------------------------------


def test_perfect_labels_decode_to_the_particles():
    rng = np.random.default_rng(0)
    planes = np.arange(1800.0, 2700.0, 100.0)
    field = random_particle_field((80, 80), count=12, diameter_min_um=20, diameter_max_um=30, layers_um=planes, pixel_um=2.2, seed=rng, overlap=False)
    labels = label_planes(field, planes)
    found = detect_particles(labels, planes, pixel_um=2.2, threshold=10.0, full_value=LABEL_SCALE * 20)
    # squares of different depths that touch laterally would merge: compare only isolated ones
    metrics = score_particles(found, field.table(), lateral_tol_um=2.2, axial_tol_um=1.0)
    assert metrics["tp"] >= 10 and metrics["fp"] <= 1
    for p, t in match_particles(found, field.table(), lateral_tol_um=2.2, axial_tol_um=1.0):
        assert abs(found["diameter_um"][p] - field.diameter_um[t]) < 1e-4  # value / 4 = diameter
        # the square's centre pixel; half a pixel off where the image edge clips the square
        clipped = not 1 <= round(field.x_um[t] / 2.2) <= 78
        assert abs(found["x_um"][p] - round(field.x_um[t] / 2.2) * 2.2) <= (1.1 if clipped else 1e-6) + 1e-9


def test_detections_through_neighbouring_planes_merge_into_one_particle_at_the_peak():
    planes = np.array([1800.0, 1850.0, 1900.0, 1950.0, 2000.0])
    outputs = np.zeros((5, 40, 40), np.float32)
    for plane, strength, shift in ((1, 40.0, 0), (2, 100.0, 1), (3, 40.0, 1)):  # drifts one pixel
        outputs[plane, 19 + shift : 22 + shift, 9:12] = strength
    outputs[2, 30:33, 30:33] = 80.0  # another particle on one plane only
    found = detect_particles(outputs, planes, pixel_um=2.0, threshold=20.0, full_value=80.0)
    assert len(found["x_um"]) == 2
    first = int(np.argmin(found["x_um"]))
    assert found["z_um"][first] == pytest.approx(1900.0)  # symmetric neighbours: the peak plane exactly
    assert found["y_um"][first] == pytest.approx(21 * 2.0) and found["x_um"][first] == pytest.approx(10 * 2.0)
    assert found["diameter_um"][first] == pytest.approx(25.0) and found["score"][first] == 1.0
    assert found["planes"][first] == 3
    # an asymmetric neighbour pulls the depth towards it, by less than half a step
    outputs[3, 20:23, 9:12] = 80.0
    shifted = detect_particles(outputs, planes, pixel_um=2.0, threshold=20.0, full_value=80.0)
    z = shifted["z_um"][int(np.argmin(shifted["x_um"]))]
    assert 1900.0 < z < 1925.0


# --- network and model files -----------------------------------------------------------------


@pytest.mark.parametrize("preset", ["small", "paper"])
def test_network_is_fully_convolutional_on_odd_sizes(preset):
    import torch

    from napari_lbs._core.learning._network import build_network

    network = build_network(preset).eval()
    with torch.inference_mode():
        for shape in ((37, 45), (16, 16), (33, 64)):
            assert network(torch.zeros(2, 1, *shape)).shape == (2, 1, *shape)


def test_tiny_training_lowers_the_loss_and_keeps_the_best_model(tiny_model):
    log = tiny_model.log
    losses = [epoch["train_loss"] for epoch in log["epochs"]]
    assert len(losses) == 3 and losses[-1] < losses[0]
    assert tiny_model.model_path.is_file() and tiny_model.model_path.with_suffix(".json").is_file()
    on_disk = json.loads(tiny_model.model_path.with_suffix(".json").read_text())
    assert on_disk["best"]["sha256"] == hashlib.sha256(tiny_model.model_path.read_bytes()).hexdigest()
    assert on_disk["validation_groups"] == [5] and on_disk["training_groups"] == [0, 1, 2, 3, 4]
    best = max(log["epochs"], key=lambda e: (e["validation"]["ji"], e["validation"]["er"]))
    assert on_disk["best"]["epoch"] == best["epoch"]


def test_training_is_deterministic_and_resumes_to_the_same_weights(tiny_data, tiny_model, tmp_path):
    from napari_lbs._core import TrainingSettings, train_model

    settings = TrainingSettings(formulation="seed", epochs=3, batch_size=4, device="cpu", validation_groups=1, foreground_weight=20.0)
    batches_per_epoch = -(-5 * 3 // 4)  # 5 training groups of 3 planes, batches of 4
    done = []
    first = train_model(tiny_data, tmp_path / "a.pt", settings=settings, progress=lambda d, t: done.append(d), should_stop=lambda: len(done) > 2 * batches_per_epoch)
    assert first.stopped and len(first.log["epochs"]) == 2  # interrupted after the first batch of epoch 3
    from dataclasses import replace

    from napari_lbs._core import InputError

    with pytest.raises(InputError, match="was made with diameter_weight=4.0, this run has 2.0"):  # another loss
        train_model(tiny_data, tmp_path / "a.pt", settings=replace(settings, diameter_weight=2.0), resume=True)
    resumed = train_model(tiny_data, tmp_path / "a.pt", settings=settings, resume=True)
    assert [e["epoch"] for e in resumed.log["epochs"]] == [1, 2, 3]
    assert [e["train_loss"] for e in resumed.log["epochs"]] == [e["train_loss"] for e in tiny_model.log["epochs"]]
    assert resumed.log["best"]["epoch"] == tiny_model.log["best"]["epoch"]
    import torch

    from napari_lbs._core import load_model

    straight, continued = load_model(tiny_model.model_path), load_model(tmp_path / "a.pt")
    assert all(torch.equal(value, continued.network.state_dict()[key]) for key, value in straight.network.state_dict().items())
    assert straight.weights_sha256 == continued.weights_sha256 == resumed.log["best"]["weights_sha256"]


def test_validating_only_the_last_epochs_trains_the_same_weights(tiny_data, tiny_model, tmp_path):
    """Skipping the early validations changes which epochs are scored, not the training."""
    from napari_lbs._core import TrainingSettings, train_model

    settings = TrainingSettings(formulation="seed", epochs=3, batch_size=4, device="cpu", validation_groups=1, foreground_weight=20.0, validate_last=1)
    records = []
    result = train_model(tiny_data, tmp_path / "last.pt", settings=settings, report=records.append)
    epochs = result.log["epochs"]
    assert [("validation" in e) for e in epochs] == [False, False, True]
    assert [e["train_loss"] for e in epochs] == [e["train_loss"] for e in tiny_model.log["epochs"]]
    assert result.log["best"]["epoch"] == 3
    assert [r["epoch"] for r in records if "batch" not in r] == [1, 2, 3]


def test_averaging_the_last_epochs_keeps_their_mean_with_batch_norm_measured_again(tiny_data, tiny_model, tmp_path):
    import torch

    from napari_lbs._core import TrainingSettings, load_model, train_model

    settings = TrainingSettings(formulation="seed", epochs=3, batch_size=4, device="cpu", validation_groups=1, foreground_weight=20.0, average_last=2)
    state_path = tmp_path / "mean.last.pt"
    epoch_two = {}

    def report(record):
        if record.get("epoch") == 3 and "validation" in record:  # the state file still holds epoch 2
            epoch_two.update(torch.load(state_path, weights_only=True)["state_dict"])

    result = train_model(tiny_data, tmp_path / "mean.pt", settings=settings, report=report)
    epoch_three = torch.load(state_path, weights_only=True)["state_dict"]
    assert [e["train_loss"] for e in result.log["epochs"]] == [e["train_loss"] for e in tiny_model.log["epochs"]]  # the same training
    assert result.log["average"]["epochs"] == [2, 3] and result.log["best"]["averaged_epochs"] == [2, 3]
    kept = load_model(tmp_path / "mean.pt")
    assert kept.meta["averaged_epochs"] == [2, 3] and kept.meta["threshold"] > 0
    assert kept.weights_sha256 == result.log["best"]["weights_sha256"]
    weights = kept.network.state_dict()
    convolutions = [name for name, value in weights.items() if name.endswith("weight") and value.ndim == 4]
    assert convolutions and not torch.equal(epoch_two[convolutions[0]], epoch_three[convolutions[0]])
    for name in convolutions:
        assert torch.allclose(weights[name], (epoch_two[name].double() + epoch_three[name].double()).div(2).float(), atol=1e-7)
    # the batch norms' statistics are the mean network's own, not the epochs' mean
    running = [name for name in weights if name.endswith("running_var")]
    assert running and not torch.allclose(weights[running[0]], (epoch_two[running[0]] + epoch_three[running[0]]) / 2, rtol=1e-3)


def test_a_negative_average_is_refused_naming_it(tmp_path):
    from napari_lbs._cli import main
    from napari_lbs._core import InputError, TrainingSettings

    with pytest.raises(InputError, match="average_last: expected >= 0"):
        TrainingSettings(average_last=-1)
    with pytest.raises(SystemExit) as exit_info:
        main(["train", str(tmp_path), "--out", str(tmp_path / "m.pt"), "--average-last", "-1"])
    assert exit_info.value.code == 2


def test_averaging_resumes_to_the_same_mean_and_a_stop_keeps_the_best_epoch(tiny_data, tmp_path):
    from napari_lbs._core import TrainingSettings, load_model, train_model

    settings = TrainingSettings(formulation="seed", epochs=3, batch_size=4, device="cpu", validation_groups=1, foreground_weight=20.0, average_last=2)
    straight = train_model(tiny_data, tmp_path / "s.pt", settings=settings)
    batches_per_epoch = -(-5 * 3 // 4)
    done = []
    first = train_model(tiny_data, tmp_path / "r.pt", settings=settings, progress=lambda d, t: done.append(d), should_stop=lambda: len(done) > 2 * batches_per_epoch)
    assert first.stopped and "average" not in first.log and "averaged_epochs" not in load_model(tmp_path / "r.pt").meta
    resumed = train_model(tiny_data, tmp_path / "r.pt", settings=settings, resume=True)
    assert resumed.log["average"]["epochs"] == [2, 3]
    assert resumed.log["best"]["weights_sha256"] == straight.log["best"]["weights_sha256"]


def _stop_after(batches: int):
    """progress and should_stop callbacks asking to stop once ``batches`` batches are done; ``asked[0]`` is when."""
    import time

    asked = []

    def progress(done, total):
        if done >= batches and not asked:
            asked.append(time.monotonic())

    return progress, lambda: bool(asked), asked


def test_a_stop_in_the_first_epoch_ends_at_once_without_validating_a_part_epoch(tiny_data, tmp_path):
    import time

    from napari_lbs._core import TrainingSettings, train_model

    progress, should_stop, asked = _stop_after(3)
    records = []
    with pytest.raises(Stopped, match="before any epoch was validated: no model written"):
        train_model(tiny_data, tmp_path / "s.pt", settings=TrainingSettings(formulation="seed", epochs=5, batch_size=2, device="cpu", validation_groups=1),
                    progress=progress, should_stop=should_stop, report=records.append)
    assert time.monotonic() - asked[0] < 2.0
    assert not (tmp_path / "s.pt").exists() and not any("validation" in r for r in records)
    assert [r["batch"] for r in records] == [1, 2, 3]  # every finished batch's loss was reported


def test_a_stop_mid_epoch_keeps_the_last_validated_model(tiny_data, tmp_path):
    import time

    from napari_lbs._core import TrainingSettings, load_model, train_model

    batches = -(-5 * 3 // 2)  # 5 training groups of 3 planes, batches of 2
    progress, should_stop, asked = _stop_after(batches + 2)
    records = []
    result = train_model(tiny_data, tmp_path / "s.pt", settings=TrainingSettings(formulation="seed", epochs=5, batch_size=2, device="cpu", validation_groups=1),
                         progress=progress, should_stop=should_stop, report=records.append)
    assert time.monotonic() - asked[0] < 2.0
    assert result.stopped and result.log["stop_reason"] == "stopped by you"
    assert [e["epoch"] for e in result.log["epochs"]] == [1] and [r["epoch"] for r in records if "validation" in r] == [1]
    assert json.loads((tmp_path / "s.json").read_text())["stopped"] is True
    model = load_model(tmp_path / "s.pt")
    assert model.meta["epoch"] == 1 and model.meta["threshold"] > 0 and result.log["best"]["epoch"] == 1


def test_a_stop_during_a_validation_pass_drops_that_pass(tiny_data, tmp_path):
    from napari_lbs._core import TrainingSettings, train_model

    batches = -(-5 * 3 // 2)
    progress, should_stop, asked = _stop_after(2 * batches)  # the last batch of epoch 2: its validation sees the stop
    result = train_model(tiny_data, tmp_path / "v.pt", settings=TrainingSettings(formulation="seed", epochs=5, batch_size=2, device="cpu", validation_groups=1),
                         progress=progress, should_stop=should_stop)
    assert result.stopped and [e["epoch"] for e in result.log["epochs"]] == [1] and result.log["best"]["epoch"] == 1


def test_model_files_never_execute_code_and_bad_files_are_refused(tmp_path):
    from napari_lbs._core import load_model

    class Exploit:
        def __reduce__(self):
            return (print, ("executed",))

    (tmp_path / "evil.pt").write_bytes(pickle.dumps(Exploit()))
    with pytest.raises(InputError, match="evil.pt: not a napari-lbs model file"):
        load_model(tmp_path / "evil.pt")
    with pytest.raises(InputError, match="model file not found"):
        load_model(tmp_path / "missing.pt")


def test_a_model_for_other_optics_or_tiles_or_depths_is_refused(tiny_model):
    from napari_lbs._core import load_model
    from napari_lbs._core.learning._network import check_model_matches

    meta = load_model(tiny_model.model_path).meta
    planes = [1800.0, 2000.0]
    check_model_matches(meta, tiny_config(), planes_um=planes)
    other = tiny_config().to_dict()
    other["optics"]["wavelength_um"] = 0.532
    with pytest.raises(InputError, match="optics.wavelength_um=0.66"):
        check_model_matches(meta, ExperimentConfig.from_dict(other), planes_um=planes)
    other = tiny_config().to_dict()
    other["tile"]["size"] = 64
    with pytest.raises(InputError, match="tile.size=48"):
        check_model_matches(meta, ExperimentConfig.from_dict(other), planes_um=planes)
    with pytest.raises(InputError, match="outside the model's training range"):
        check_model_matches(meta, tiny_config(), planes_um=[1800.0, 4000.0])


# --- prediction ------------------------------------------------------------------------------


@pytest.mark.parametrize(("length", "size", "margin"), [(100, 48, 8), (48, 48, 8), (1024, 256, 32), (257, 256, 32)])
def test_tiles_overlap_and_their_kept_parts_partition_the_axis(length, size, margin):
    from napari_lbs._core.learning._prediction import tile_layout

    layout = tile_layout(length, size=size, margin=margin)
    kept = np.zeros(length, int)
    for start, keep_from, keep_to in layout:
        assert start <= keep_from < keep_to <= start + size
        kept[keep_from:keep_to] += 1
        # away from the image edge a tile keeps nothing within `margin` of its own edge
        assert keep_from == 0 or keep_from - start >= margin
        assert keep_to == length or start + size - keep_to >= margin
    assert np.all(kept == 1)
    with pytest.raises(InputError, match="larger than the image"):
        tile_layout(size - 1, size=size, margin=margin)


def test_prediction_runs_on_a_hologram_larger_than_a_tile_and_carries_provenance(tiny_model):
    from napari_lbs._core import predict_particles

    config = tiny_config()
    field = random_particle_field((100, 90), count=8, diameter_min_um=20, diameter_max_um=30, layers_um=config.layer_depths_um(), pixel_um=2.2, seed=1)
    hologram = simulate_hologram(field, wavelength_um=0.66)
    seen = []
    result = predict_particles(hologram, tiny_model.model_path, progress=lambda d, t: seen.append((d, t)))
    assert seen[-1] == (5, 5)  # one step per plane, 1800..2200 every 100
    table = result.particles
    assert set(table) >= {"x_um", "y_um", "z_um", "diameter_um", "score"}
    assert np.all((table["x_um"] >= 0) & (table["x_um"] <= 90 * 2.2)) and np.all((table["score"] >= 0) & (table["score"] <= 1))
    assert result.provenance["model_sha256"] == hashlib.sha256(tiny_model.model_path.read_bytes()).hexdigest()
    assert result.provenance["tiles"] == [4, 3, 48, 12]  # quarter-tile margin: rows start 0, 24, 48, 52; cols 0, 24, 42
    assert result.provenance["precision"] in ("float32", "bfloat16")
    assert predict_particles(hologram, tiny_model.model_path, precision="float32").provenance["precision"] == "float32"
    with pytest.raises(Stopped):
        predict_particles(hologram, tiny_model.model_path, should_stop=lambda: True)
    with pytest.raises(InputError, match="larger than the image"):
        predict_particles(hologram[:40, :90], tiny_model.model_path)


def test_detections_of_one_particle_at_distant_depths_merge_laterally_only_when_asked():
    planes = np.arange(1800.0, 2800.0, 100.0)
    outputs = np.zeros((10, 40, 40), np.float32)
    outputs[2, 10:13, 10:13] = 100.0  # one sphere seen at 2000 um ...
    outputs[7, 11:14, 10:13] = 60.0  # ... and again, weaker, 500 um deeper, one pixel off
    outputs[5, 30:33, 30:33] = 90.0  # a different particle
    separate = detect_particles(outputs, planes, pixel_um=2.0, threshold=20.0, full_value=80.0)
    assert len(separate["x_um"]) == 3
    from napari_lbs._core.learning._detection import PlaneLinker

    linker = PlaneLinker(planes, pixel_um=2.0, threshold=20.0, full_value=80.0, merge_lateral_um=10.0)
    for plane, output in enumerate(outputs):
        linker.add(plane, output)
    merged = linker.particles()
    assert len(merged["x_um"]) == 2
    assert sorted(merged["z_um"]) == pytest.approx([2000.0, 2300.0])  # the stronger detection is kept


def test_training_replaces_a_model_only_with_force(tiny_data, tmp_path):
    """An existing model or log is refused before any work unless force (or resume) says so; a link is never written through."""
    from napari_lbs._core import InputError, TrainingSettings, train_model

    mine = tmp_path / "m.json"
    mine.write_text("mine")
    with pytest.raises(InputError, match="m.json: exists; add force=True"):
        train_model(tiny_data, tmp_path / "m.pt", settings=TrainingSettings(formulation="seed", epochs=1, batch_size=4, device="cpu", validation_groups=1))
    assert mine.read_text() == "mine" and not (tmp_path / "m.pt").exists()
    (tmp_path / "l.pt").symlink_to(mine)
    with pytest.raises(InputError, match="symbolic link"):
        train_model(tiny_data, tmp_path / "l.pt", settings=TrainingSettings(formulation="seed", epochs=1, batch_size=4, device="cpu", validation_groups=1), force=True)
    assert mine.read_text() == "mine"
