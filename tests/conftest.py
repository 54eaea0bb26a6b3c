from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def real_hologram_bmp(tmp_path_factory) -> Path:
    """The seed's real hologram as the RGB BMP it was published as, written from the shipped sample."""
    from PIL import Image

    from napari_lbs._core import load_sample_hologram

    path = tmp_path_factory.mktemp("seed") / "cropped_hologram.bmp"
    Image.fromarray(load_sample_hologram(rgb=True)).save(path)
    return path


# --- shared by the recordings' tests (test_sequence) and the Batch widget's (test_widgets) ---------


@pytest.fixture(scope="session")
def tiny_config():
    """A small setup for recordings: planes 1800-2200 um every 100 um, 48-pixel tiles, 3 particles a tile."""
    from napari_lbs._core import ExperimentConfig

    return ExperimentConfig.from_dict({
        "volume": {"z_min_um": 1800.0, "z_max_um": 2200.0, "z_step_um": 100.0},
        "particles": {"per_tile": 3, "layer_step_um": 200.0},
        "tile": {"size": 48},
    })


@pytest.fixture(scope="session")
def detector(tmp_path_factory, tiny_config):
    """A tiny focus model made eager: its centre logit raised so every frame gives a few dozen detections to compare."""
    import torch

    from napari_lbs._core import DatasetLayout, TrainingSettings, generate_dataset, load_model, train_model
    from napari_lbs._core.learning._network import save_model

    folder = tmp_path_factory.mktemp("model")
    data = generate_dataset(folder / "data", tiny_config, groups=3, layout=DatasetLayout(kind="stack", context_planes=2), seed=5)
    settings = TrainingSettings(epochs=1, batch_size=4, device="cpu", validation_groups=1, patch_size=32, context=(-2, -1, 0, 1, 2))
    model = load_model(train_model(data, folder / "base.pt", settings=settings).model_path)
    with torch.no_grad():
        model.network.head.bias[0] += 3.0
    model.meta["threshold"] = 0.1
    save_model(folder / "eager.pt", model.network, model.meta)
    return load_model(folder / "eager.pt")
