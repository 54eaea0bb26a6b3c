"""The sample's material: a gate on the fitted index contrast (`same_material`)."""

import numpy as np
import pytest

from napari_lbs._core import InputError, same_material


def test_a_particle_is_of_another_material_beyond_the_tolerance_and_two_sigma():
    table = {"index_contrast": np.array([0.26, 0.33, 0.35, 0.35, 0.12, np.nan, 0.45]), "index_err": np.array([0.01, 0.01, 0.01, 0.06, 0.01, np.nan, np.nan])}
    # within 0.01 / within 0.08 / beyond both / within 2 sigma / far / not measured / measured without an uncertainty
    assert same_material(table, index_contrast=0.26).tolist() == [True, True, False, True, False, True, True]
    assert same_material(table, index_contrast=0.26, tolerance=0.0, sigmas=0.0).tolist() == [True, False, False, False, False, True, False]


@pytest.mark.parametrize(("table", "options", "culprit"), [
    ({"index_contrast": np.array([0.26])}, {"index_contrast": 0.26}, "index_err"),
    ({"index_contrast": np.array([0.26]), "index_err": np.array([0.01])}, {"index_contrast": float("nan")}, "index_contrast"),
    ({"index_contrast": np.array([0.26]), "index_err": np.array([0.01])}, {"index_contrast": 0.26, "tolerance": -1.0}, "tolerance"),
])
def test_bad_gates_are_refused_in_one_line(table, options, culprit):
    with pytest.raises(InputError, match=culprit):
        same_material(table, **options)


def test_refined_spheres_of_two_materials_are_told_apart():
    """A polystyrene sphere (0.26) and a smaller one of a denser material (0.35) in water: the gate keeps the polystyrene one."""
    from sphere_scenes import FAST, PIXEL_UM, default_config, guess_table, sphere_scene

    from napari_lbs._core import RefineSettings, refine_particles

    polystyrene, dense = (36.0 * PIXEL_UM, 36.0 * PIXEL_UM, 900.0, 18.0, 0.26), (160.0 * PIXEL_UM, 36.0 * PIXEL_UM, 900.0, 10.0, 0.35)
    hologram = sphere_scene([polystyrene, dense], shape=(72, 196), noise=0.005)
    guesses = guess_table([(x + 1.0, y - 1.0, z + 20.0, 19.0) for x, y, z, _, _ in (polystyrene, dense)])  # the network's usual size for both
    refined = refine_particles(hologram, guesses, default_config(), settings=RefineSettings(**FAST))
    assert len(refined) == 2 and abs(refined["index_contrast"][0] - 0.26) < 0.01 and refined["index_contrast"][1] > 0.34
    assert same_material(refined, index_contrast=0.26).tolist() == [True, False]
