"""Quantization and saturation read from the levels a frame of integer counts uses.

A camera's analogue-to-digital converter puts every pixel on a grid of levels. A frame stored
in a container of more levels than the converter has (a 6-bit converter in an 8-bit file, a
12-bit one in a 16-bit file) uses one level in ``step``: the largest step whose grid holds
(nearly) every pixel's value is the converter's. Its noise, ``(step / mean)² / 12`` of the
normalised frame, is compared with the residual's white floor: quantization is part of the
gap when it is a noticeable share of the noise (``SHARE_LEVEL``), whatever the step.

Pixels at the container's top level are saturated. Their error is the light the fitted model
puts above the top there; saturation is part of the gap by the same rule, when that error's
variance over the frame is a noticeable share of the noise. A camera whose brightest fringes
touch the top in a few pixels loses a few counts there; one exposed so that the fringes' crests
are cut loses them in every ring.

No likelihood is needed for the step: the levels are a property of the file, not a fit. A frame
that is not integer counts (a float image, a background-divided frame) holds no levels to read.
"""

from __future__ import annotations

import numpy as np

__all__ = ["levels_test", "SHARE_LEVEL"]

SHARE_LEVEL = 0.1  # quantization noise as a share of the white floor's variance above which it is named
_ON_GRID = 0.999  # share of the pixels a step's grid must hold
_LARGEST_STEP = 256


def levels_test(counts: np.ndarray, model_excess: np.ndarray, *, floor_variance: float) -> dict:
    """The converter's step and the saturated pixels, each with its share of the noise, from a frame of integer counts.

    Parameters
    ----------
    counts : (rows, cols) array
        The frame as recorded (before any normalisation).
    model_excess : (rows, cols) array
        The fitted model less the normalised frame (mean 1): at a saturated pixel, the light
        the camera cut.
    floor_variance : float
        The variance of the residual's white floor in the normalised frame.

    Returns
    -------
    dict
        ``integer`` (whether the frame holds counts), ``step_counts``, ``noise_share`` (the
        step's noise over the floor), ``saturated_share`` (pixels at the container's top
        level), ``saturation_noise_share`` (the cut light's variance over the frame, over the
        floor), ``selected`` and the catalog's ``params`` (``bits``: the converter's levels
        over the container's range, ``saturation``: the top level in units of the mean).
    """
    values = np.asarray(counts)
    finite = values[np.isfinite(values)] if values.dtype.kind == "f" else values.ravel()
    if finite.size == 0 or not np.all(np.mod(finite, 1) == 0) or finite.min() < 0 or finite.max() >= 2**32:
        return {"integer": False, "step_counts": None, "noise_share": None, "saturated_share": None, "saturation_noise_share": None,
                "selected": False, "params": {}}
    histogram = np.bincount(finite.astype(np.int64))
    levels = np.arange(histogram.size)
    step = 1
    for candidate in range(min(_LARGEST_STEP, max(histogram.size // 4, 1)), 1, -1):
        on_offset = np.bincount(levels % candidate, weights=histogram, minlength=candidate)
        if on_offset.max() >= _ON_GRID * finite.size:
            step = candidate
            break
    mean = float(finite.mean())
    top = 2 ** int(np.ceil(np.log2(histogram.size))) - 1  # the container's largest value (255 for 8 bits)
    saturated = float(histogram[top] / finite.size) if top < histogram.size else 0.0
    noise_share = float((step / mean) ** 2 / 12.0 / floor_variance) if mean > 0 and floor_variance > 0 else None
    cut = np.clip(np.asarray(model_excess, dtype=np.float64)[values == top], 0.0, None) if saturated > 0 else np.zeros(0)
    saturation_share = float(np.sum(cut**2) / values.size / floor_variance) if floor_variance > 0 else None
    selected = bool((step > 1 and noise_share is not None and noise_share >= SHARE_LEVEL)
                    or (saturation_share is not None and saturation_share >= SHARE_LEVEL))
    params = {"bits": float(np.log2(top / step + 1.0)), "saturation": float(top / mean)} if selected and mean > 0 else {}
    return {"integer": True, "step_counts": int(step), "noise_share": noise_share, "saturated_share": saturated,
            "saturation_noise_share": saturation_share, "selected": selected, "params": params}
