"""Prediction of the ``focus`` formulation: the streamed stack gives the tables of the whole-stack
path, windows wider than the network's reach give the whole image's particles, and the planes
held at once stay the context's whatever the depth."""

import weakref

import numpy as np
import pytest
import torch

from napari_lbs._core import ExperimentConfig, HoloParams, InputProcessing, random_particle_field, simulate_hologram
from napari_lbs._core.learning._prediction import tile_layout, window_layout

CONTEXT = (-2, -1, 0, 1, 2)


def tiny_config(**volume) -> ExperimentConfig:
    return ExperimentConfig.from_dict({
        "volume": {"z_min_um": 1800.0, "z_max_um": 2200.0, "z_step_um": 100.0, **volume},
        "particles": {"per_tile": 3, "layer_step_um": 200.0},
        "tile": {"size": 48},
    })


@pytest.fixture(scope="module")
def focus_model_path(tmp_path_factory):
    from napari_lbs._core import DatasetLayout, TrainingSettings, generate_dataset, train_model

    folder = tmp_path_factory.mktemp("windows")
    processing = InputProcessing(HoloParams(-0.5, 0.2, 0.8), invert_experiment=True)
    data = generate_dataset(folder / "data", tiny_config(), groups=4, processing=processing, layout=DatasetLayout(kind="stack", context_planes=2), seed=5)
    settings = TrainingSettings(epochs=1, batch_size=4, device="cpu", validation_groups=1, patch_size=32, context=CONTEXT)
    return train_model(data, folder / "f.pt", settings=settings).model_path


def eager_model(path, *, bias: float):
    """The model with its centre logit raised: a network that sees particles in many places, so the tables compared are long."""
    from napari_lbs._core import load_model

    model = load_model(path)
    with torch.no_grad():
        model.network.head.bias[0] = bias
    model.meta["threshold"] = 0.5
    return model


def hologram_of(shape, seed=1):
    field = random_particle_field(shape, count=12, diameter_min_um=20, diameter_max_um=30, layers_um=(1800.0, 2200.0), continuous=True, pixel_um=2.2, seed=seed)
    return simulate_hologram(field, wavelength_um=0.66)


def assert_same_tables(a: dict, b: dict, *, atol: float = 0.0) -> None:
    assert set(a) == set(b) and len(a["x_um"]) == len(b["x_um"]) > 0
    for name in a:
        np.testing.assert_allclose(a[name], b[name], rtol=0, atol=atol, err_msg=name)


def assert_same_detections(a: dict, b: dict, *, atol: float, undecided) -> None:
    """Every detection of each table is one of the other's within ``atol`` in every column, but a few (at most 1 %) whose score ``undecided`` says rounding decides."""
    from scipy.spatial import cKDTree

    assert set(a) == set(b) and len(a["x_um"]) > 0 and len(b["x_um"]) > 0
    names = sorted(a)
    for one, other in ((a, b), (b, a)):
        mine, theirs = (np.stack([table[name] for name in names], axis=1) for table in (one, other))
        distance, nearest = cKDTree(theirs).query(mine, p=np.inf)
        alone = distance > atol
        assert alone.sum() <= 0.01 * len(mine) and all(undecided(score) for score in one["score"][alone])
        np.testing.assert_allclose(mine[~alone], theirs[nearest[~alone]], rtol=0, atol=atol)


@pytest.mark.parametrize(("length", "most", "margin"), [(1024, 640, 32), (4096, 640, 32), (1000, 640, 32), (200, 64, 12), (190, 96, 12), (1030, 256, 32), (100, 640, 12), (640, 640, 32)])
def test_windows_partition_the_axis_on_the_pooling_grid_with_margins(length, most, margin):
    windows = window_layout(length, most=most, margin=margin)
    kept = [(keep_from, keep_to) for _, _, keep_from, keep_to in windows]
    assert kept[0][0] == 0 and kept[-1][1] == length and all(a[1] == b[0] for a, b in zip(kept[:-1], kept[1:]))
    edges = {stop - start for start, stop, _, _ in windows[:-1]}
    assert len(edges) <= 1 and all(edge % 16 == 0 and edge <= -(-most // 16) * 16 for edge in edges)
    for start, stop, keep_from, keep_to in windows:
        assert start % 16 == 0 and 0 <= start < stop <= length
        assert start == 0 or keep_from - start >= margin  # the kept pixels stay a margin away from a cut
        assert stop == length or stop - keep_to >= margin
    if most >= length:
        assert windows == [(0, length, 0, length)]
    if (length, most) == (1024, 640):  # two windows of 544 where 256² tiles needed five a side
        assert len(windows) == 2 and len(tile_layout(1024, size=256, margin=32)) == 5


def test_the_streamed_stack_gives_the_tables_of_the_whole_stack(focus_model_path, monkeypatch):
    """The previous path, all planes back-propagated and normalised first, then the network on the
    whole image, against the streamed one, in one batch of planes and one plane at a time."""
    from napari_lbs._core import backpropagate, predict_particles
    from napari_lbs._core.physics import _optics
    from napari_lbs._core.learning._detection import PeakDecoder, suppress
    from napari_lbs._core.learning._network import focus_maps, inference_network
    from napari_lbs._core.learning._prediction import tile_normalisation

    config, hologram = tiny_config(), hologram_of((100, 90))
    model = eager_model(focus_model_path, bias=3.0)
    meta, planes = model.meta, config.volume.planes_um()
    extended = [planes[0] - 200.0, planes[0] - 100.0, *planes, planes[-1] + 100.0, planes[-1] + 200.0]
    optics = {"wavelength_um": 0.66, "pixel_um": 2.2, "medium_index": 1.0}
    stack = backpropagate(hologram.astype(np.float32), extended, **optics)
    layout = (tile_layout(100, size=48, margin=12), tile_layout(90, size=48, margin=12))
    tile_normalisation(stack, layout, 48, invert=True, mode=meta["processing"]["mode"])
    decoder = PeakDecoder(planes, pixel_um=2.2, step_um=100.0)
    for centre, probability, offset, diameter in focus_maps(inference_network(model.network), stack, range(2, 2 + len(planes)), context=CONTEXT, diameter_scale_um=meta["diameter_scale_um"]):
        decoder.add(centre - 2, probability, offset, diameter)
    whole = suppress(decoder.candidates(), threshold=0.5, lateral_um=meta["lateral_um"], axial_um=meta["axial_um"] if meta.get("axial_um") is not None else np.inf)

    streamed = predict_particles(hologram, model, config, precision="float32")  # the reference ran in float32
    assert streamed.provenance["windows"] == [1, 1, 100, 90]
    assert_same_tables(streamed.particles, whole, atol=1e-4)  # µm: the network ran on 5 planes a call there, on 1 here
    monkeypatch.setattr(_optics, "_WORKING_BYTES", 1)  # one plane per batch
    assert_same_tables(predict_particles(hologram, model, config, precision="float32").particles, streamed.particles)


def test_windows_wider_than_the_networks_reach_give_the_whole_images_particles(focus_model_path):
    """A two-level network reaches 9 pixels: with 12-pixel margins on the pooling grid, its windows
    see all a kept pixel depends on, so tiling changes nothing but rounding."""
    from napari_lbs._core import LoadedModel, predict_particles
    from napari_lbs._core.learning._network import UNet

    base = eager_model(focus_model_path, bias=0.0)
    torch.manual_seed(3)
    network = UNet((6, 8), in_channels=len(CONTEXT), out_channels=3).eval()
    with torch.no_grad():
        network.head.bias[0] = 1.0
    model = LoadedModel(network, base.meta, base.sha256)
    hologram = hologram_of((200, 190), seed=2)
    whole = predict_particles(hologram, model, tiny_config(), window_px=1000)
    tiled = predict_particles(hologram, model, tiny_config(), window_px=64)
    assert whole.provenance["windows"] == [1, 1, 200, 190] and tiled.provenance["windows"][:2] == [6, 5]
    # where the network sees nothing its output is its bias, a plateau whose local maxima
    # rounding places: a detection there may be in one table alone
    plateau = float(torch.sigmoid(torch.tensor(1.0)))
    assert_same_detections(tiled.particles, whole.particles, atol=1e-4, undecided=lambda score: abs(score - plateau) < 1e-3)
    with pytest.raises(Exception, match="window_px: expected at least the model's tile size 48"):
        predict_particles(hologram, model, tiny_config(), window_px=40)


def test_the_planes_held_at_once_are_the_contexts_whatever_the_depth(focus_model_path, monkeypatch):
    from napari_lbs._core import predict_particles
    from napari_lbs._core.physics import _optics
    from napari_lbs._core.learning import _prediction

    live, most = [0], [0]
    normalise = _prediction._TileNormaliser.__call__

    def counted(self, plane):
        normalise(self, plane)
        live[0] += 1
        most[0] = max(most[0], live[0])
        weakref.finalize(plane, lambda: live.__setitem__(0, live[0] - 1))

    monkeypatch.setattr(_prediction._TileNormaliser, "__call__", counted)
    monkeypatch.setattr(_optics, "_WORKING_BYTES", 1)  # batches of one plane, as on a 4096² sensor
    deep = tiny_config(z_min_um=1800.0, z_max_um=4800.0)  # 31 planes, 35 with the context
    result = predict_particles(hologram_of((64, 64)), eager_model(focus_model_path, bias=0.0), deep, force=True)
    assert result.provenance["planes_um"][2] == 31
    assert 2 * 2 + 1 <= most[0] <= 2 * 2 + 2  # the context of one centre plane, and the next batch
