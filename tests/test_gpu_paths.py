"""The device code paths (sample assembly, back-propagation with torch.fft, batched refinement) against their numpy or per-batch references.

Every test runs on the CPU and, where CUDA exists, on the GPU too: the device is a parameter
of the code, so the CPU leg checks the same code a GPU runs.
"""

import numpy as np
import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_device_crops_are_the_numpy_crops_turned_and_flipped(device):
    from napari_lbs._core.learning._device_samples import dihedral_crops

    rng = np.random.default_rng(0)
    stack = rng.random((3, 5, 20, 24)).astype(np.float16)
    count, size = 16, 7
    group, r0, c0 = rng.integers(0, 3, count), rng.integers(0, 14, count), rng.integers(0, 18, count)
    planes = rng.integers(0, 5, (count, 2))
    turns, flip = np.arange(count) % 4, (np.arange(count) // 4) % 2 == 1  # every turn with and without the flip
    crops = dihedral_crops(torch.from_numpy(stack).to(device), group * 5, planes, r0, c0, turns, flip, size=size, device=torch.device(device)).cpu().numpy()
    for k in range(count):
        expected = np.rot90(stack[group[k], planes[k], r0[k] : r0[k] + size, c0[k] : c0[k] + size].astype(np.float32), turns[k], axes=(-2, -1))
        if flip[k]:
            expected = expected[..., ::-1]
        np.testing.assert_array_equal(crops[k], expected)


@pytest.mark.parametrize("device", DEVICES)
def test_rendered_marks_are_the_dense_targets(device):
    from napari_lbs._core.learning._device_samples import render_marks
    from napari_lbs._core.learning._heatmaps import focus_marks, focus_targets

    rng = np.random.default_rng(1)
    windows, common = [], {"step_um": 50.0, "pixel_um": 3.45, "shape": (32, 32), "diameter_scale_um": 30.0}
    for _ in range(6):
        n = int(rng.integers(0, 12))
        table = {"x_um": rng.uniform(-10, 130, n), "y_um": rng.uniform(-10, 130, n), "z_um": rng.uniform(1800, 2100, n), "diameter_um": rng.uniform(20, 30, n)}
        windows.append((table, {"plane_um": float(rng.choice([1850.0, 1900.0, 1950.0])), "origin_px": (int(rng.integers(0, 6)), int(rng.integers(0, 6)))}))
    rendered = render_marks([focus_marks(t, **common, **w) for t, w in windows], size=32, device=torch.device(device)).cpu().numpy()
    assert sum(int(focus_targets(t, **common, **w).positive.sum()) for t, w in windows) > 0  # the windows hold peaks
    for k, (table, where) in enumerate(windows):
        dense = focus_targets(table, **common, **where)
        for channel, expected in enumerate((dense.heat, dense.offset, dense.diameter, dense.positive.astype(np.float32))):
            np.testing.assert_array_equal(rendered[k, channel], expected)


@pytest.mark.parametrize("device", DEVICES)
def test_device_augmentation_follows_its_seed_and_stays_in_range(device):
    from napari_lbs._core.learning._device_samples import augment_planes

    x = torch.rand(4, 3, 16, 16, device=device)
    parameters = torch.tensor([[1.0, 1.0, 0.0, 0.0], [1.3, 1.0, 0.0, 0.0], [1.0, 1.2, 0.03, 0.0], [0.8, 0.9, 0.02, 1.0]], device=device)
    first, again = augment_planes(x, parameters, seed=7), augment_planes(x, parameters, seed=7)
    assert torch.equal(first, again) and not torch.equal(first, augment_planes(x, parameters, seed=8))
    assert float(first.min()) >= 0.0 and float(first.max()) <= 1.0
    torch.testing.assert_close(first[0], x[0])  # gamma 1, contrast 1, no noise: unchanged
    torch.testing.assert_close(first[1], x[1] ** 1.3)
    assert torch.equal(torch.round(first[3] * 255.0) / 255.0, first[3])  # quantised to 8 bits


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("background", [False, True])
def test_device_back_propagation_gives_the_numpy_planes(device, background):
    from napari_lbs._core.learning._device_planes import backpropagated_planes, device_backpropagated_planes
    from napari_lbs._core.physics import backpropagate

    rng = np.random.default_rng(2)
    hologram = (1.0 + 0.2 * rng.standard_normal((96, 80))).astype(np.float32)
    light = (1.0 + 0.1 * rng.random((96, 80))).astype(np.float32) if background else None
    optics = {"wavelength_um": 0.66, "pixel_um": 3.45, "medium_index": 1.0}
    depths = [1800.0, 2000.0, 2600.0]
    expected = backpropagate(hologram, depths, background=light, **optics)
    found = np.concatenate([p.cpu().numpy() for _, _, p in device_backpropagated_planes(hologram, depths, background=light, device=torch.device(device), **optics)])
    assert found.dtype == np.float32 and found.shape == expected.shape
    np.testing.assert_allclose(found, expected, rtol=0, atol=2e-6 * float(np.abs(expected).max()))
    assert not np.array_equal(found[0], found[1])  # the depths differ
    chosen = np.concatenate([p for _, _, p in backpropagated_planes(hologram, depths, background=light, device=torch.device(device), **optics)])
    np.testing.assert_allclose(chosen, expected, rtol=0, atol=2e-6 * float(np.abs(expected).max()))


@pytest.mark.parametrize("device", DEVICES)
def test_refinement_in_one_device_batch_gives_the_table_of_small_batches(device):
    """The GPU's way (every particle in one batch, in this process) against the CPU's (small batches), within the fit's uncertainties."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from sphere_scenes import FAST, default_config, guess_table, sphere_scene

    from napari_lbs._core.refine import RefineSettings, refine_particles

    # two particles within each other's reach (neighbours in the models) and one alone
    truth = [(60.0, 60.0, 2600.0, 24.0), (120.0, 70.0, 3100.0, 28.0), (280.0, 200.0, 2800.0, 22.0)]
    hologram = sphere_scene(truth, shape=(120, 150), seed=3)
    guesses = guess_table([(x + 1.5, y - 1.0, z + 15.0, d + 1.0) for x, y, z, d in truth])
    small = refine_particles(hologram, guesses, default_config(), settings=RefineSettings(**FAST, batch=2, device="cpu"))
    whole = refine_particles(hologram, guesses, default_config(), settings=RefineSettings(**FAST, batch=len(truth) if device == "cpu" else 1, device=device))
    assert len(small) == len(whole) == len(truth) and small["refined"].all() and whole["refined"].all()
    for value, error in (("z_um", "z_err_um"), ("diameter_um", "diameter_err_um"), ("index_contrast", "index_err")):
        tolerance = 2.0 * np.hypot(small[error], whole[error])
        assert np.all(np.abs(small[value] - whole[value]) <= tolerance), (value, small[value].tolist(), whole[value].tolist())
    assert np.all(np.hypot(small["x_um"] - whole["x_um"], small["y_um"] - whole["y_um"]) < 0.5)
