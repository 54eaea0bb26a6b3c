"""Holo-processing (noise and a gamma map) calibrated to the experiment by a genetic algorithm.

Stands on physics and the foundation. Other wings import these names from ``napari_lbs._core.calibration``, never from its
private modules; each name is imported on first use.

`_calibrate`
    Holo-processing and its calibration to one experimental tile (OCE, seed paper Sec. 2.2).
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_calibrate": ("CalibrationResult", "CalibrationSettings", "HoloParams", "calibrate_hologram", "experimental_planes", "experimental_reference", "holo_processing", "reference_planes"),
    },
)
