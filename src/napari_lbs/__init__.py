"""napari-lbs: learning from better simulation for in-line particle holography.

The computation lives in `napari_lbs._core` (no Qt, no napari); the dock widgets and the
``napari-lbs`` console script are thin fronts over it.
"""

__version__ = "0.1.0"
