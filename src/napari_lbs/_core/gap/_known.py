"""Known facts are inputs, not findings: what an image of integer counts states about its camera."""

from __future__ import annotations

import numpy as np

__all__ = ["known_sensor"]

# A camera that clips piles its brightest pixels up at one value; a natural image reaches its
# maximum in a handful of pixels. This share of the pixels at the maximum marks saturation.
_PILE_UP = 1e-3
# A camera's counts fill every level between the histogram's tails (the real hologram: 100 %);
# a file whose values sit on every 2nd, 4th, ... level holds an image of fewer bits than its
# format (a 6-bit image in a uint8 file, or one rescaled after a coarser quantisation).
_LEVELS_USED = 0.6
_PER_LEVEL = 5.0  # pixels a level between the quartiles, at least, for an empty level to count


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
        0.1 % of the pixels pile up there, else the full scale), ``saturated_fraction``,
        ``levels_used`` (the share of the integer levels between the quartiles that occur;
        1.0 where half the pixels fill fewer than 5 a level there, too few to tell),
        ``coarse`` (``levels_used`` below 0.6: the values are coarser than the format, so the
        bit depth is a finding to diagnose, not a fact the file states), ``effective_bits``
        (``bits + log2(levels_used)``) and ``source``. None for an image that is not integer
        counts (a float simulation).
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
    low_quartile, high_quartile = np.quantile(array, (0.25, 0.75))
    span = np.arange(int(np.ceil(low_quartile)), int(np.floor(high_quartile)) + 1)
    # where half the pixels fill fewer than _PER_LEVEL a level, an empty level says nothing
    telling = span.size > 1 and 0.5 * array.size / span.size >= _PER_LEVEL
    levels_used = float(np.isin(span, np.unique(array)).mean()) if telling else 1.0
    return {
        "bits": bits, "full_scale": full_scale, "saturation": high if saturated >= _PILE_UP else full_scale, "saturated_fraction": saturated,
        "levels_used": levels_used, "coarse": bool(levels_used < _LEVELS_USED), "effective_bits": float(bits + np.log2(max(levels_used, 2.0**-bits))), "source": source,
    }
