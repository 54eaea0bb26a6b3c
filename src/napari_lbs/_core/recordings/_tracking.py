"""Tracks: particles linked through the frames of a recording into 3-D trajectories (trackpy).

`link_tracks` links with trackpy's nearest-neighbour linking over ``x_um, y_um, z_um`` — a
search range in µm, optionally a larger one along z (holographic depths are several times
less precise than lateral positions: a focus model's depth may jump by a plane, 50 µm, from
one frame to the next), ``memory`` frames a particle may be missed and keep its track — and
adds to the table ``track`` (integer ids numbered in order of first appearance)
and ``dx_um, dy_um, dz_um``: the displacement to the same track's next detection (NaN at a
track's end; written as an empty cell, docs/formats.md).
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import PARTICLE_COLUMNS, InputError

__all__ = ["DISPLACEMENT_COLUMNS", "link_tracks"]

DISPLACEMENT_COLUMNS = ("dx_um", "dy_um", "dz_um")


def link_tracks(particles: dict[str, np.ndarray], *, search_range_um: float, axial_search_range_um: float | None = None, memory: int = 0) -> dict[str, np.ndarray]:
    """Link the particles of a recording into tracks.

    Parameters
    ----------
    particles : dict of arrays
        A particle table with a ``frame`` column (0-based integers), e.g. `predict_sequence`'s.
    search_range_um : float
        Largest distance (µm) a particle may move between two frames it is seen in: in 3-D, or
        laterally when ``axial_search_range_um`` is given.
    axial_search_range_um : float, optional
        The search range along z (µm); the search region is then an ellipsoid.
    memory : int
        Frames a particle may go undetected and still continue its track.

    Returns
    -------
    dict of arrays
        The table's rows sorted by frame (stable), with ``track`` (int64) and
        ``dx_um, dy_um, dz_um`` (float64, NaN at a track's last detection) added.

    Raises
    ------
    InputError
        No ``frame`` column, frames not non-negative integers, a search range that is not
        positive, or one so large that trackpy's subnetworks explode (it names the frame).
    """
    import pandas as pd
    import trackpy

    if "frame" not in particles:
        raise InputError("particle table: no frame column; tracks need the table of a recording (predict with several frames)")
    for name, value in (("search_range_um", search_range_um), ("axial_search_range_um", axial_search_range_um)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise InputError(f"{name}: expected a positive distance, got {value}")
    if memory < 0:
        raise InputError(f"memory: expected a non-negative number of frames, got {memory}")
    frame = np.asarray(particles["frame"], dtype=np.float64)
    if frame.size and (not np.all(np.isfinite(frame)) or np.any(frame < 0) or np.any(frame != np.round(frame))):
        raise InputError("particle table: column frame: expected non-negative integers")
    order = np.argsort(frame, kind="stable")
    table = {name: np.asarray(values)[order] for name, values in particles.items()}
    table["frame"] = frame[order].astype(np.int64)
    if not frame.size:  # nothing to link
        return {**table, "track": np.zeros(0, np.int64), **{name: np.zeros(0) for name in DISPLACEMENT_COLUMNS}}
    positions = pd.DataFrame({name: np.asarray(table[name], dtype=np.float64) for name in PARTICLE_COLUMNS[:3]})
    positions["frame"] = table["frame"]
    trackpy.quiet()
    try:
        search_range = search_range_um if axial_search_range_um is None else (search_range_um, search_range_um, axial_search_range_um)  # per pos_columns
        linked = trackpy.link_df(positions, search_range, memory=memory, pos_columns=list(PARTICLE_COLUMNS[:3]), t_column="frame")
    except trackpy.SubnetOversizeException as error:
        raise InputError(f"search_range_um: {search_range_um:g} µm links too many candidates at once ({error}); use a smaller search range") from None
    labels = linked.loc[positions.index, "particle"].to_numpy()
    _, first_seen = np.unique(labels, return_index=True)
    renumber = {labels[i]: track for track, i in enumerate(sorted(first_seen))}
    track = np.array([renumber[label] for label in labels], dtype=np.int64)
    table["track"] = track
    displacement = {name: np.full(track.size, np.nan) for name in DISPLACEMENT_COLUMNS}
    by_track = np.lexsort((table["frame"], track))  # rows of each track in frame order
    same_track = track[by_track][1:] == track[by_track][:-1]
    for name, axis in zip(DISPLACEMENT_COLUMNS, PARTICLE_COLUMNS[:3], strict=True):
        values = np.asarray(table[axis], dtype=np.float64)[by_track]
        displacement[name][by_track[:-1][same_track]] = (values[1:] - values[:-1])[same_track]
    table.update(displacement)
    return table
