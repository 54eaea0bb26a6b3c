"""Known facts are inputs, not findings: what an image of integer counts states about its camera."""

from __future__ import annotations

import numpy as np

__all__ = ["known_sensor"]

# A camera that clips piles its brightest pixels up at one value; a natural image reaches its
# maximum in a handful of pixels. This share of the pixels at the maximum marks saturation.
_PILE_UP = 1e-3


def known_sensor(image: np.ndarray) -> dict | None:
    """What an image of integer counts states about its camera: bit depth and saturation level.

    Parameters
    ----------
    image : 2-D array
        The hologram as recorded: an integer dtype, or floats holding integer counts (what
        `read_hologram` makes of an integer file: float32 holds integers exactly up to 2^24).

    Returns
    -------
    dict or None
        ``bits`` (uint8: 8; otherwise the fewest bits, at least 8, that hold the largest
        count), ``full_scale`` and ``saturation`` (counts: the largest value where at least
        0.1 % of the pixels pile up there, else the full scale), ``saturated_fraction`` and
        ``source``. None for an image that is not integer counts (a float simulation).
    """
    array = np.asarray(image)
    if array.ndim != 2 or array.dtype == bool or array.dtype.kind not in "uif" or array.size == 0:
        return None
    if array.dtype.kind in "ui":
        source = f"{array.dtype} image"
    elif np.all(np.isfinite(array)) and np.all(array == np.round(array)):
        source = "integer counts in a float image"
    else:
        return None
    low, high = float(array.min()), float(array.max())
    if low < 0 or high <= 0 or high > 2**16 - 1:
        return None
    bits = 8 if array.dtype == np.uint8 else int(max(8, np.ceil(np.log2(high + 1))))
    full_scale = float(2**bits - 1)
    saturated = float(np.mean(array == high))
    return {"bits": bits, "full_scale": full_scale, "saturation": high if saturated >= _PILE_UP else full_scale, "saturated_fraction": saturated, "source": source}
