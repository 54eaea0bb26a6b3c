"""The background of a recording, estimated from its own frames.

The background of a recording (the illumination, dust, fringes of the windows: everything
that does not move) is estimated from the frames themselves (`sequence_background`): the
per-pixel median of frames spread over the whole recording (``global``) or of the frames
around each frame (``running``, for drifting illumination). Particles that move far enough
are gone from the median of each pixel, so it is the light without them. Each frame is
divided by it before back-propagation.

A particle that moves less than its hologram's extent over the frames of the median leaves
part of its fringes in it, and dividing by it takes part of the particle away. A per-frame
flat field (`flat_field`: the frame smoothed over far more than a particle's hologram) has
no particle in it whatever the motion, but keeps no static fine structure either.
``auto`` (`choose_background`) uses the median only where the recording shows that it has
static structure to remove and that it is particle-free: the medians of the first and of
the second half of the sampled frames must agree better than the median's fine structure
(static structure is in both halves, a slow particle's residue sits in each at another
place) and better than a frame differs from the median (the particles' own signal); else
the flat field.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import InputError
from napari_lbs._core.recordings._frames import HologramFrames

__all__ = ["BACKGROUND_MODES", "FLAT_SIGMA_PX", "MEDIAN_AGREEMENT", "MEDIAN_RESIDUE", "choose_background", "flat_field", "frame_window", "frames_median", "sequence_background"]

BACKGROUND_MODES = ("auto", "global", "running", "flat", "none")
FLAT_SIGMA_PX = 32.0  # smoothing of the flat field: a particle's shadow is ~100 px² of the ~6400 px² it averages over
# auto takes the median when its halves disagree by less than its fine structure (most of that structure is static) and
# by at most 1.3 times a frame's own deviation from it (the particles have left it). Both set on development recordings
# (benchmarks/bench_flow.py, seeds 1-3; docs/sequences.md): structure ratio 1.2-4.5 in uniform light, 0.3-0.7 behind
# static fringes; residue 1.42-1.69 where flat found more tracks (4-8 um a frame), 0.97-1.14 where the median did (16-32).
MEDIAN_AGREEMENT = 1.0
MEDIAN_RESIDUE = 1.3


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
        chosen = _sample_indices(count, samples)
    else:
        if window < 1:
            raise InputError(f"window: expected at least 1 frame, got {window}")
        chosen = range(*frame_window(index, count=count, window=window))
    return frames_median(np.stack([frames.read(int(k)) for k in chosen]))


def _sample_indices(count: int, samples: int) -> np.ndarray:
    if samples < 1:
        raise InputError(f"samples: expected at least 1 frame, got {samples}")
    return np.unique(np.linspace(0, count - 1, min(samples, count)).round().astype(int))


def choose_background(frames: HologramFrames, *, samples: int = 32, agreement: float = MEDIAN_AGREEMENT,
                      residue: float = MEDIAN_RESIDUE) -> tuple[str, np.ndarray | None, dict]:
    """The ``auto`` background: the global median when the recording shows it has static structure and no particles, else a per-frame flat field.

    The ``samples`` frames of the global median are split into the first and the second
    half (in time). Static structure (illumination, dust, window fringes) is the same in
    both halves' medians; the fringes of a particle that moved too little to leave the median
    sit in each at another place. The disagreement is the mean of ``|median_1 / median_2 - 1|``
    (the particles' residue), the structure the mean of ``|median / flat_field(median) - 1|``
    (the median's fine structure: static structure and residue), the signal the mean over the
    sampled frames of ``|frame / median - 1|`` (what the particles add to a frame). The
    median is taken when the disagreement is at most ``agreement`` times the structure
    (most of the structure is static: there is something for the median to remove that a
    flat field cannot) and at most ``residue`` times the signal (the particles have moved
    out of it); else the particles would lose more to it than the static structure costs:
    flat. In uniform light there is no static structure and a flat field loses nothing.

    Parameters
    ----------
    frames : HologramFrames
    samples : int
        Frames of the global median (spread evenly over the recording).
    agreement : float
        Largest ratio of disagreement to structure that still takes the median (dimensionless).
    residue : float
        Largest ratio of disagreement to signal that still takes the median (dimensionless).

    Returns
    -------
    (mode, background, measures)
        ``("global", median, ...)`` or ``("flat", None, ...)``; ``measures`` holds the
        ``disagreement``, ``structure``, ``signal``, ``ratio`` (disagreement / structure) and
        ``residue`` (disagreement / signal), all None with fewer than 4 sampled frames (too
        few to split: flat), and the number of ``frames`` sampled.
    """
    chosen = _sample_indices(len(frames), samples)
    if chosen.size < 4:
        return "flat", None, {"disagreement": None, "structure": None, "signal": None, "ratio": None, "residue": None, "frames": int(chosen.size)}
    stack = np.stack([frames.read(int(k)) for k in chosen])
    half = chosen.size // 2
    first, second = frames_median(stack[:half]), frames_median(stack[half:])
    disagreement = float(np.mean(np.abs(first / second - 1.0)))
    median = frames_median(stack)
    structure = float(np.mean(np.abs(median / flat_field(median) - 1.0)))
    signal = float(np.mean([np.mean(np.abs(frame / median - 1.0)) for frame in stack]))
    ratio = disagreement / structure if structure > 0 else np.inf
    moved = disagreement / signal if signal > 0 else np.inf
    measures = {"disagreement": round(disagreement, 6), "structure": round(structure, 6), "signal": round(signal, 6),
                "ratio": round(float(ratio), 4), "residue": round(float(moved), 4), "frames": int(chosen.size)}
    if ratio <= agreement and moved <= residue:
        return "global", median, measures
    return "flat", None, measures


def flat_field(hologram: np.ndarray, *, sigma_px: float = FLAT_SIGMA_PX) -> np.ndarray:
    """A frame's own illumination: the frame smoothed by a Gaussian of ``sigma_px`` pixels (float32, positive).

    Smoothed over ~2π σ² pixels (6400 px² at 32 px), a particle's hologram (a shadow of
    ~100 px² and fringes that average out) is gone, while the illumination's envelope
    (vignetting, a tilted or flickering lamp) stays: dividing by it leaves every particle
    whatever it did in the other frames. Static fine structure (dust, window fringes) stays
    in the quotient. Computed on blocks of ``sigma_px / 4`` pixels and interpolated
    bilinearly back: 16 ms of CPU time for a 1024² frame (measured), against seconds for its prediction.
    """
    image = np.asarray(hologram, dtype=np.float32)
    if not sigma_px > 0:
        raise InputError(f"sigma_px: expected a positive width, got {sigma_px}")
    import scipy.ndimage

    block = max(1, int(sigma_px // 4))
    rows, cols = image.shape
    padded = np.pad(image, ((0, -rows % block), (0, -cols % block)), mode="edge")
    coarse = padded.reshape(padded.shape[0] // block, block, padded.shape[1] // block, block).mean(axis=(1, 3), dtype=np.float64)
    coarse = scipy.ndimage.gaussian_filter(coarse, sigma_px / block, mode="nearest")
    smooth = _interpolation(rows, coarse.shape[0], block) @ coarse @ _interpolation(cols, coarse.shape[1], block).T
    smooth = smooth.astype(np.float32)
    positive = smooth[smooth > 0]
    return np.maximum(smooth, positive.min() if positive.size else np.float32(1.0))


def _interpolation(size: int, blocks: int, block: int) -> np.ndarray:
    """``(size, blocks)`` weights of linear interpolation from block centres to pixel centres (clamped at the ends)."""
    position = np.clip((np.arange(size) + 0.5) / block - 0.5, 0, blocks - 1)
    low = np.floor(position).astype(int)
    high = np.minimum(low + 1, blocks - 1)
    weights = np.zeros((size, blocks))
    np.add.at(weights, (np.arange(size), low), 1 - (position - low))
    np.add.at(weights, (np.arange(size), high), position - low)
    return weights


def frames_median(stack: np.ndarray) -> np.ndarray:
    """The per-pixel median of ``(frames, rows, cols)``, float32, floored at its smallest positive value so dividing by it is always defined."""
    median = np.median(stack, axis=0).astype(np.float32)
    positive = median[median > 0]
    floor = positive.min() if positive.size else np.float32(1.0)
    return np.maximum(median, floor)
