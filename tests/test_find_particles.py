"""Particles found in the back-propagated volume, without a trained model (`find_particles`)."""

import numpy as np
import pytest

from napari_lbs._core import ExperimentConfig, InputError, ParticleField, find_particles, simulate_hologram

CONFIG = ExperimentConfig.from_dict({"volume": {"z_min_um": 1800.0, "z_max_um": 3800.0, "z_step_um": 50.0}})


def _scene(seed: int):
    """Four opaque discs of 20-30 um at known places of a 256 x 256 frame, with 2 % read noise."""
    rng = np.random.default_rng(seed)
    x = np.array([60.0, 190.0, 70.0, 180.0]) * 2.2 + rng.uniform(-5, 5, 4)
    y = np.array([60.0, 70.0, 190.0, 185.0]) * 2.2 + rng.uniform(-5, 5, 4)
    z = np.array([1900.0, 2500.0, 3000.0, 3600.0])
    d = rng.uniform(20.0, 30.0, 4)
    field = ParticleField(x, y, z, d, (256, 256), 2.2)
    hologram = simulate_hologram(field, wavelength_um=0.66) + 0.02 * rng.standard_normal((256, 256)).astype(np.float32)
    return hologram, field


@pytest.mark.parametrize("seed", [0, 1])
def test_every_particle_is_found_near_its_place_and_depth(seed):
    hologram, truth = _scene(seed)
    found = find_particles(hologram, CONFIG, z_step_um=50.0)
    assert len(found["x_um"]) == 4
    for x, y, z in zip(truth.x_um, truth.y_um, truth.z_um, strict=True):
        distance = np.hypot(found["x_um"] - x, found["y_um"] - y)
        nearest = int(np.argmin(distance))
        assert distance[nearest] < 2 * 2.2 and abs(found["z_um"][nearest] - z) <= 150.0
    assert np.all(np.diff(found["focus"]) <= 0)  # strongest first


def test_a_frame_without_particles_gives_none_and_bad_input_is_refused():
    noise = 1.0 + 0.02 * np.random.default_rng(3).standard_normal((128, 128))
    assert len(find_particles(noise, CONFIG)["x_um"]) == 0
    with pytest.raises(InputError, match="2-D"):
        find_particles(np.ones(16), CONFIG)
    with pytest.raises(InputError, match="max_particles"):
        find_particles(noise, CONFIG, max_particles=0)
