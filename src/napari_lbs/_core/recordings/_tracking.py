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

from collections.abc import Iterator

import numpy as np

from napari_lbs._core.foundation import PARTICLE_COLUMNS, InputError, ProgressCallback, Steps, StopCallback

__all__ = ["DISPLACEMENT_COLUMNS", "link_tracks"]

DISPLACEMENT_COLUMNS = ("dx_um", "dy_um", "dz_um")


MAX_FRAME = 10**7  # a frame number beyond this is no recording's (a million frames is hours of high-speed video)
MAX_MEMORY = 10**4  # frames a particle may be missed
MAX_SEARCH_UM = 1e6  # a metre, beyond any sample; trackpy squares the distances, which overflow near 1e154


def _levels(frames: np.ndarray, positions: np.ndarray, memory: int) -> Iterator[tuple[int, np.ndarray]]:
    """``(frame, coords)`` for trackpy's linker: the frames present, and of each gap only the empty frames that matter.

    The linker forgets a particle after ``memory + 1`` empty frames, so a longer gap links
    exactly as one of ``memory + 1`` empty frames: the work grows with the rows, not with
    the largest frame number.
    """
    present, starts = np.unique(frames, return_index=True)
    ends = np.append(starts[1:], frames.size)
    previous = None
    for frame, start, end in zip(present, starts, ends, strict=True):
        if previous is not None:
            for empty in range(previous + 1, min(int(frame), previous + memory + 2)):
                yield empty, np.empty((0, positions.shape[1]))
        yield int(frame), positions[start:end]
        previous = int(frame)


def link_tracks(particles: dict[str, np.ndarray], *, search_range_um: float, axial_search_range_um: float | None = None, memory: int = 0,
                progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> dict[str, np.ndarray]:
    """Link the particles of a recording into tracks.

    Parameters
    ----------
    particles : dict of arrays
        A particle table with a ``frame`` column (integers 0 … `MAX_FRAME`), e.g. `predict_sequence`'s.
    search_range_um : float
        Largest distance (µm) a particle may move between two frames it is seen in: in 3-D, or
        laterally when ``axial_search_range_um`` is given.
    axial_search_range_um : float, optional
        The search range along z (µm); the search region is then an ellipsoid.
    memory : int
        Frames (0 … `MAX_MEMORY`) a particle may go undetected and still continue its track.
    progress, should_stop : callable, optional
        Progress (frames linked) and stop requests, checked after every frame (`Stopped`).

    Returns
    -------
    dict of arrays
        The table's rows sorted by frame (stable), with ``track`` (int64) and
        ``dx_um, dy_um, dz_um`` (float64, NaN at a track's last detection) added.

    Raises
    ------
    InputError
        No ``frame`` column, frames not integers in 0 … `MAX_FRAME`, positions not finite, a
        search range that is not positive, or one so large that trackpy's subnetworks explode
        (it names the frame).
    """
    import trackpy

    if "frame" not in particles:
        raise InputError("particle table: no frame column; tracks need the table of a recording (predict with several frames)")
    for name, value in (("search_range_um", search_range_um), ("axial_search_range_um", axial_search_range_um)):
        if value is not None and not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and 0 < value <= MAX_SEARCH_UM):
            raise InputError(f"{name}: expected a positive distance up to {MAX_SEARCH_UM:g} µm, got {value!r}")
    if not isinstance(memory, (int, np.integer)) or isinstance(memory, bool) or not 0 <= memory <= MAX_MEMORY:
        raise InputError(f"memory: expected an integer number of frames in [0, {MAX_MEMORY}], got {memory!r}")
    try:
        frame = np.asarray(particles["frame"], dtype=np.float64).ravel()
        coords = np.stack([np.asarray(particles[name], dtype=np.float64).ravel() for name in PARTICLE_COLUMNS[:3]], axis=1) if frame.size else np.zeros((0, 3))
    except KeyError as error:
        raise InputError(f"particle table: missing column {error}") from None
    except (TypeError, ValueError):
        raise InputError("particle table: columns frame, x_um, y_um and z_um: expected numbers of one length per column") from None
    if frame.size and (not np.all((frame >= 0) & (frame <= MAX_FRAME)) or np.any(frame != np.round(frame))):
        raise InputError(f"particle table: column frame: expected integers in [0, {MAX_FRAME}]")
    if coords.shape[0] != frame.size or not np.all(np.isfinite(coords)):
        raise InputError("particle table: columns x_um, y_um, z_um: expected finite numbers, one per row")
    order = np.argsort(frame, kind="stable")
    table = {name: np.asarray(values)[order] for name, values in particles.items()}
    table["frame"] = frame[order].astype(np.int64)
    if not frame.size:  # nothing to link
        return {**table, "track": np.zeros(0, np.int64), **{name: np.zeros(0) for name in DISPLACEMENT_COLUMNS}}
    steps = Steps(len(np.unique(table["frame"])), progress=progress, should_stop=should_stop)
    search_range = search_range_um if axial_search_range_um is None else (search_range_um, search_range_um, axial_search_range_um)  # per axis
    trackpy.quiet()
    labels = []
    levels = _levels(table["frame"], coords[order], memory)
    try:  # frame by frame, so a stop request (and Ctrl-C) is heard between frames
        for _, ids in trackpy.link_iter(levels, search_range, memory=memory):
            steps.check()
            if len(ids):  # a frame present (the empty ones of a gap have no rows)
                labels.extend(ids)
                steps.advance()
    except trackpy.SubnetOversizeException as error:
        raise InputError(f"search_range_um: {search_range_um:g} µm links too many candidates at once ({error}); use a smaller search range") from None
    labels = np.asarray(labels)
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
