import numpy as np
import pytest
from scipy import ndimage

from napari_lbs._core.physics import gaussian_blur


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", [(64, 48), (7, 5)], ids=["frame", "smaller-than-the-kernel"])
@pytest.mark.parametrize("sigma_px", [0.0, 0.3, 1.5, 5.0])
def test_is_scipys_gaussian_filter_to_rounding_at_every_pixel_and_at_the_kept_ones(dtype, shape, sigma_px):
    image = np.random.default_rng(1).random(shape).astype(dtype)
    expected = ndimage.gaussian_filter(image, sigma_px)  # truncate 4, mode reflect: its defaults
    tolerance = 1e-6 if dtype == np.float32 else 1e-14
    blurred = gaussian_blur(image, sigma_px)
    assert blurred.dtype == dtype and np.abs(blurred - expected).max() < tolerance
    keep = (slice(1, None, 2), slice(0, None, 3))
    assert np.abs(gaussian_blur(image, sigma_px, keep=keep) - expected[keep]).max() < tolerance


def test_keeps_the_light_and_refuses_a_bad_width():
    image = np.zeros((33, 33))
    image[16, 16] = 1.0
    assert gaussian_blur(image, 2.0).sum() == pytest.approx(1.0, abs=1e-12)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="sigma_px"):
            gaussian_blur(image, bad)
