"""The Lorenz–Mie hologram of a particle table over a whole frame, and the residual it leaves."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sphere_scenes import PIXEL_UM, WATER, WAVELENGTH_UM, default_config, guess_table, sphere_scene

from napari_lbs._core import InputError
from napari_lbs._core.physics._lorenz_mie import sphere_fields, sphere_holograms
from napari_lbs._core.refine._scene import particle_hologram, residual_hologram


def test_one_sphere_is_its_lorenz_mie_hologram_inside_its_fringe_disc_and_light_outside():
    shape = (300, 300)
    x, y, z, d = 120.0 * PIXEL_UM, 150.0 * PIXEL_UM, 1500.0, 22.0
    rendered = particle_hologram(shape, guess_table([(x, y, z, d)]), default_config())
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]] * PIXEL_UM
    exact = sphere_holograms(torch.tensor(cols.ravel() - x)[None], torch.tensor(rows.ravel() - y)[None], torch.tensor([z * WATER]), torch.tensor([d]),
                             torch.tensor([0.26]), torch.tensor([0.0]), wavelength_um=WAVELENGTH_UM, medium_index=WATER, pixel_um=PIXEL_UM)[0].numpy().reshape(shape)
    inside = rendered != 1.0
    assert inside[150, 120] and not inside[0, 299]  # the centre is rendered, a far corner is not
    # the partial waves stop at the scattered field's count, not at the internal field's: 1e-7
    np.testing.assert_allclose(rendered[inside], exact[inside], rtol=0, atol=1e-6)
    assert np.max(np.abs(exact[~inside] - 1.0)) < 0.1  # what is left out: faint, aliased fringes


def test_the_whole_reach_renders_the_aliased_rings_a_pixel_records():
    """To 1 cycle per pixel the sphere is its pixel-integrated hologram over the whole frame; inside the Nyquist disc both reaches agree."""
    shape = (300, 300)
    x, y, z, d = 120.0 * PIXEL_UM, 150.0 * PIXEL_UM, 1500.0, 22.0
    near, whole = (particle_hologram(shape, guess_table([(x, y, z, d)]), default_config(), reach_cycles_per_px=reach) for reach in (0.5, 1.0))
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]] * PIXEL_UM
    exact = sphere_holograms(torch.tensor(cols.ravel() - x)[None], torch.tensor(rows.ravel() - y)[None], torch.tensor([z * WATER]), torch.tensor([d]),
                             torch.tensor([0.26]), torch.tensor([0.0]), wavelength_um=WAVELENGTH_UM, medium_index=WATER, pixel_um=PIXEL_UM)[0].numpy().reshape(shape)
    inside = near != 1.0
    np.testing.assert_allclose(whole[inside], near[inside], rtol=0, atol=1e-9)
    assert np.all(whole != 1.0)  # the far corner too
    np.testing.assert_allclose(whole, exact, rtol=0, atol=1e-6)
    for reach in (0.0, 1.5, float("nan")):
        with pytest.raises(InputError, match="reach_cycles_per_px"):
            particle_hologram(shape, guess_table([(x, y, z, d)]), default_config(), reach_cycles_per_px=reach)


def test_overlapping_spheres_add_as_fields():
    table = guess_table([(60.0 * PIXEL_UM, 60.0 * PIXEL_UM, 900.0, 25.0), (70.0 * PIXEL_UM, 64.0 * PIXEL_UM, 1100.0, 20.0)])
    rendered = particle_hologram((120, 120), table, default_config(), settings=None)
    # near both centres: each sphere's own hologram, plus the cross term of their fields 2 Re(E1 · E2*)
    rows, cols = np.mgrid[50:80, 50:80] * PIXEL_UM
    fields = [sphere_fields(torch.tensor(cols.ravel() - x)[None], torch.tensor(rows.ravel() - y)[None], torch.tensor([z * WATER]), torch.tensor([d]),
                            torch.tensor([0.26]), torch.tensor([0.0]), wavelength_um=WAVELENGTH_UM, medium_index=WATER)
              for x, y, z, d in table.itertuples(index=False)]
    singles = [particle_hologram((120, 120), table.iloc[[i]], default_config())[50:80, 50:80] for i in range(2)]
    coherent = sum(2.0 * (f1 * f2.conj()).real for f1, f2 in zip(fields[0], fields[1], strict=True))[0].numpy().reshape(30, 30)
    np.testing.assert_allclose(rendered[50:80, 50:80], singles[0] + singles[1] - 1.0 + coherent, rtol=0, atol=1e-6)
    assert np.max(np.abs(coherent)) > 1e-3  # the field cross term is not negligible here


def test_a_table_rendered_in_several_materials_at_once_is_each_material_rendered_alone():
    from napari_lbs._core.refine import particle_holograms

    table = guess_table([(60.0 * PIXEL_UM, 60.0 * PIXEL_UM, 900.0, 25.0), (70.0 * PIXEL_UM, 64.0 * PIXEL_UM, 1100.0, 20.0)])
    materials = [{"index_contrast": 0.0, "absorption": 1.0}, {"index_contrast": 0.12, "absorption": 0.0}, {"index_contrast": 0.26, "absorption": 0.01}]
    together = particle_holograms((120, 120), table, default_config(), materials=materials, reach_cycles_per_px=1.0)
    assert together.shape == (3, 120, 120)
    for rendered, material in zip(together, materials, strict=True):
        alone = particle_hologram((120, 120), table.assign(**material), default_config(), reach_cycles_per_px=1.0)
        np.testing.assert_allclose(rendered, alone, rtol=0, atol=1e-12)
    assert np.max(np.abs(together[0] - together[2])) > 0.01  # the materials differ
    for bad in ([], [{"index_contrast": 0.1}], [{"index_contrast": float("nan"), "absorption": 0.0}]):
        with pytest.raises(InputError, match="^particle holograms: "):
            particle_holograms((120, 120), table, default_config(), materials=bad)


def test_a_sphere_rendered_in_blocks_of_rows_is_the_sphere_rendered_at_once(monkeypatch):
    from napari_lbs._core.refine import _scene

    table = guess_table([(60.0 * PIXEL_UM, 60.0 * PIXEL_UM, 900.0, 25.0), (70.0 * PIXEL_UM, 64.0 * PIXEL_UM, 1100.0, 20.0)])
    at_once = particle_hologram((120, 120), table, default_config(), reach_cycles_per_px=1.0)
    monkeypatch.setattr(_scene, "_BLOCK_POINTS", 1000)  # 8 rows of a 120-pixel patch a block
    np.testing.assert_allclose(particle_hologram((120, 120), table, default_config(), reach_cycles_per_px=1.0), at_once, rtol=0, atol=1e-12)


def test_the_residual_of_a_scene_by_its_own_table_is_its_noise():
    particles = [(70.0 * PIXEL_UM, 80.0 * PIXEL_UM, 900.0, 24.0)]
    hologram = sphere_scene(particles, shape=(150, 150), noise=0.01, seed=4)
    table = guess_table([p[:4] for p in particles])
    residual = residual_hologram(hologram * 80.0, table, default_config(), background=np.full(hologram.shape, 80.0))
    rendered = particle_hologram(hologram.shape, table, default_config()) != 1.0  # inside the spheres' fringe discs
    assert np.std(hologram[rendered] - 1.0) > 0.05
    assert np.std(residual[rendered] / 80.0 - 1.0) < 0.0105  # the noise's 0.01


@pytest.mark.parametrize(("shape", "culprit"), [((0, 10), "shape"), ((10, 10, 3), "2-D")])
def test_bad_frames_are_refused_in_one_line(shape, culprit):
    table = guess_table([(1.0, 1.0, 800.0, 20.0)])
    with pytest.raises(InputError, match=culprit):
        if len(shape) == 2:
            particle_hologram(shape, table, default_config())
        else:
            residual_hologram(np.ones(shape), table, default_config())


def test_a_sphere_the_table_misses_is_found_in_its_residual_and_the_tables_own_is_not_found_twice():
    from sphere_scenes import FAST

    from napari_lbs._core import RefineSettings, refine_particles
    from napari_lbs._core.refine._scene import residual_particles

    known, missed = (40.0 * PIXEL_UM, 42.0 * PIXEL_UM, 900.0, 20.0), (78.0 * PIXEL_UM, 74.0 * PIXEL_UM, 1100.0, 24.0)
    hologram = sphere_scene([known, missed], shape=(120, 120), noise=0.01, seed=5)
    settings = RefineSettings(**FAST)
    table = refine_particles(hologram, guess_table([(known[0] + 1.0, known[1] - 1.0, 920.0, 20.5)]), default_config(), settings=settings)
    looked = []

    def propose(image):  # a network that proposes both spheres in the residual
        looked.append(image)
        return {"x_um": np.array([known[0], missed[0] - 1.5]), "y_um": np.array([known[1], missed[1] + 1.0]), "z_um": np.array([900.0, 1080.0]),
                "diameter_um": np.array([20.0, 23.0]), "score": np.array([0.5, 0.4])}

    found = residual_particles(hologram, table, default_config(), propose=propose, settings=settings)
    assert len(looked) == 1 and np.std(looked[0][20:60, 20:60]) < 0.5 * np.std(hologram[20:60, 20:60])  # the known sphere is taken out
    assert len(found) == 1
    assert abs(found.x_um[0] - missed[0]) < 0.5 and abs(found.y_um[0] - missed[1]) < 0.5 and abs(found.z_um[0] - missed[2]) < 5.0
    assert abs(found.diameter_um[0] - missed[3]) < 0.5 and abs(found.index_contrast[0] - 0.26) < 0.02 and bool(found.refined[0])


def test_rendering_stops_when_asked():
    from napari_lbs._core import Stopped

    table = guess_table([(50.0, 50.0, 900.0, 20.0), (120.0, 90.0, 1000.0, 24.0)])
    with pytest.raises(Stopped):
        particle_hologram((80, 80), table, default_config(), should_stop=lambda: True)
