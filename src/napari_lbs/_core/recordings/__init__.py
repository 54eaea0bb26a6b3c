"""Recordings: frames, backgrounds, prediction over every frame, tracks and simulated flows.

Stands on learning, calibration, physics and the foundation. Other wings import these names from ``napari_lbs._core.recordings``, never from its
private modules; each name is imported on first use.

`_background`
    The background of a recording, estimated from its own frames.
`_flow`
    A ground-truth recording: particles moving with a known flow, one hologram per frame.
`_frames`
    Reading recordings: frames one at a time from files, folders, glob patterns, TIFF pages or videos.
`_sequence`
    Recordings: prediction frame by frame on dask, one table for the whole recording.
`_tracking`
    Tracks: particles linked through the frames of a recording into 3-D trajectories (trackpy).
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_background": ("BACKGROUND_MODES", "sequence_background"),
        "_flow": ("SimulatedSequence", "simulate_sequence"),
        "_frames": ("HologramFrames", "open_frames"),
        "_sequence": ("SequenceResult", "predict_sequence"),
        "_tracking": ("DISPLACEMENT_COLUMNS", "link_tracks"),
    },
)
