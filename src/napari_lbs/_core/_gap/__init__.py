"""Diagnosing the sim-to-real gap: where it lies, which unmodelled effect causes it, how far it shrinks.

One concern per module:

`_summaries`
    `tile_summaries`: the measurements, one code path for real and simulated tiles;
    `measured_fringe`: the experiment's static-fringe frequency.
`_tiling`
    `TileLayout` (where the tiles lie, the checkerboard split), `field_surroundings`,
    `adapted_tile_px`.
`_statistic`
    `gap_statistic` (excess standardised χ²), `real_spread` (its unit), `where_gap`.
`_fitting`
    simulated tiles with common random numbers and the refits; `DiagnosisSettings`.
`_verdict`
    `resampled_gaps` (bootstrap over held-out tiles and simulation seeds) and the verdict rule.
`_known`
    `known_sensor`: what a file of integer counts states (bit depth, saturation).
`_diagnose`
    `diagnose_tiles`, `diagnose_hologram`: fit, screen, confirm, ablate, rank, decide; cross-fit
    (each half fitted, the other scored) where the held-out half is small.
`_report`
    `write_report`: ``report.json`` (CONTRACT.md), ``report.md``, figures.
"""

from napari_lbs._core._gap._diagnose import Diagnosis, diagnose_hologram, diagnose_tiles
from napari_lbs._core._gap._fitting import DiagnosisSettings
from napari_lbs._core._gap._known import known_sensor
from napari_lbs._core._gap._report import write_report
from napari_lbs._core._gap._statistic import gap_statistic, real_spread, where_gap
from napari_lbs._core._gap._summaries import MIN_TILE_PX, SUMMARY_GROUPS, measured_fringe, tile_summaries
from napari_lbs._core._gap._tiling import TileLayout, adapted_tile_px, field_surroundings
from napari_lbs._core._gap._verdict import resampled_gaps

__all__ = [
    "tile_summaries", "measured_fringe", "gap_statistic", "real_spread", "write_report", "where_gap", "diagnose_tiles", "diagnose_hologram",
    "DiagnosisSettings", "Diagnosis", "TileLayout", "field_surroundings", "known_sensor", "adapted_tile_px", "resampled_gaps", "SUMMARY_GROUPS",
    "MIN_TILE_PX",
]
