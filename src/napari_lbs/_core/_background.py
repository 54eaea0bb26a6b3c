"""The background of a recording, estimated from its own frames.

The background of a recording (the illumination, dust, fringes of the windows: everything
that does not move) is estimated from the frames themselves (`sequence_background`): the
per-pixel median of frames spread over the whole recording (``global``) or of the frames
around each frame (``running``, for drifting illumination). Particles move, so the median
of each pixel is the light without them. Each frame is divided by it before
back-propagation.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core._errors import InputError
from napari_lbs._core._frames import HologramFrames

__all__ = ["BACKGROUND_MODES", "sequence_background", "frame_window", "frames_median"]

BACKGROUND_MODES = ("global", "running", "none")


def frame_window(index: int, *, count: int, window: int) -> tuple[int, int]:
    """The ``window`` frames around ``index`` (clamped inside ``[0, count)``): ``(first, stop)``."""
    size = min(window, count)
    first = min(max(index - size // 2, 0), count - size)
    return first, first + size


def sequence_background(frames: HologramFrames, *, samples: int = 32, index: int | None = None, window: int = 21) -> np.ndarray:
    """The background of a recording: the per-pixel median of its frames.

    Parameters
    ----------
    frames : HologramFrames
        The recording (`open_frames`).
    samples : int
        Global background (``index`` None): the median of this many frames spread evenly over
        the whole recording (all of them when it has fewer). Memory: ``samples`` frames.
    index : int, optional
        Running background: the median of the ``window`` frames centred on frame ``index``
        (shifted inside the recording at its ends).
    window : int
        Frames of a running background.

    Returns
    -------
    (rows, cols) float32 array, positive (a pixel dark in every frame gets the smallest
    positive value of the estimate, so dividing by it is always defined).
    """
    count = len(frames)
    if index is None:
        if samples < 1:
            raise InputError(f"samples: expected at least 1 frame, got {samples}")
        chosen = np.unique(np.linspace(0, count - 1, min(samples, count)).round().astype(int))
    else:
        if window < 1:
            raise InputError(f"window: expected at least 1 frame, got {window}")
        chosen = range(*frame_window(index, count=count, window=window))
    return frames_median(np.stack([frames.read(int(k)) for k in chosen]))


def frames_median(stack: np.ndarray) -> np.ndarray:
    """The per-pixel median of ``(frames, rows, cols)``, float32, floored at its smallest positive value so dividing by it is always defined."""
    median = np.median(stack, axis=0).astype(np.float32)
    positive = median[median > 0]
    floor = positive.min() if positive.size else np.float32(1.0)
    return np.maximum(median, floor)
