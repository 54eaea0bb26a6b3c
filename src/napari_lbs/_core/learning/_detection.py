"""From network output planes to particles.

Two decoders, one per formulation (`napari_lbs._core.learning._network`).

``focus``: `PeakDecoder` and `suppress`
    The network gives, per plane, a particle-centre probability, a sub-plane depth offset and
    a diameter (`napari_lbs._core.learning._heatmaps`). Planes stream in depth order; a voxel is a
    candidate when its probability is the largest of its 3 planes x ``(2 window_px + 1)²``
    neighbourhood and at least ``floor``. Its lateral position is the probability-weighted
    centroid of its 3x3 pixels, its depth the plane's plus the regressed offset, its diameter
    the regressed one, its score the probability. `suppress` then keeps one particle per peak:
    strongest first, every weaker candidate within ``lateral_um`` and ``axial_um`` is dropped.

``seed``: `PlaneLinker`
    The network paints each in-focus particle as a 3x3 square of value ``LABEL_SCALE x diameter``
on the plane nearest its depth; a real particle is in focus over several neighbouring planes,
so its squares repeat there. Decoding, plane by plane (streaming: a deep stack never has to
be held):

1. threshold the output; each 8-connected blob is a per-plane detection with its response
   sum, its response-weighted centroid and its best 3x3 mean (the largest mean of a 3x3
   window centred in the blob: a label square's value);
2. link a blob to the blobs of the previous plane that touch it (1-pixel tolerance), so one
   particle's detections through depth form one chain (union–find);
3. each chain becomes one particle at the centroid of its strongest blob, its depth refined by
   a parabola through the chain's response sums around the strongest plane, its diameter the
   blob's best 3x3 mean / ``LABEL_SCALE``;
4. chains closer laterally than ``merge_lateral_um`` are one particle seen at several depths
   (on the real hologram the network fires on one sphere at depths up to ~1 mm apart, with
   gaps between): only the chain with the largest summed response is kept. Two true
   particles that close in projection are rare (< 1 % of particles at the seed's density).

``score`` is the 3x3 mean relative to the label of the smallest particle the model was trained
for, clipped to [0, 1]: 1 means "as strong as a true square".
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from napari_lbs._core.foundation import InputError
from napari_lbs._core.physics import LABEL_SCALE

__all__ = ["PeakDecoder", "suppress", "PlaneLinker", "detect_particles"]

_EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)


class PlaneLinker:
    """Accumulates output planes in depth order and merges detections into particles.

    Parameters
    ----------
    planes_um : sequence of float
        Depth of each plane (µm), in the order planes will be added.
    pixel_um : float
        Pixel pitch (µm).
    threshold : float
        Output value (label units, 4 x µm) above which a pixel belongs to a detection.
    full_value : float
        Label value that scores 1 (``LABEL_SCALE x`` the smallest trained diameter).
    origin_um : (x, y)
        Position of pixel (0, 0), for outputs of a crop.
    merge_lateral_um : float
        Chains closer than this in (x, y) are merged whatever their depths (0 = never).
    """

    def __init__(self, planes_um: Sequence[float], *, pixel_um: float, threshold: float, full_value: float, origin_um: tuple[float, float] = (0.0, 0.0), merge_lateral_um: float = 0.0) -> None:
        if threshold <= 0:
            raise InputError(f"threshold: expected a positive output value, got {threshold}")
        self.planes_um = np.asarray(planes_um, dtype=np.float64)
        self.pixel_um = float(pixel_um)
        self.threshold = float(threshold)
        self.full_value = float(full_value)
        self.origin_um = origin_um
        self.merge_lateral_um = float(merge_lateral_um)
        self._previous: tuple[int, np.ndarray, np.ndarray] | None = None  # (plane, labels, blob ids)
        self._blobs: list[tuple[int, float, float, float, float]] = []  # plane, row, col, response sum, 3x3 mean
        self._parent: list[int] = []

    def _root(self, blob: int) -> int:
        while self._parent[blob] != blob:
            self._parent[blob] = self._parent[self._parent[blob]]
            blob = self._parent[blob]
        return blob

    def add(self, plane: int, output: np.ndarray) -> None:
        """Add the output (label units) of plane ``plane``; planes must come in increasing order."""
        output = np.asarray(output, dtype=np.float32)
        labels, count = ndimage.label(output > self.threshold, structure=_EIGHT_CONNECTED)
        if count == 0:
            self._previous = None
            return
        index = np.arange(1, count + 1)
        sums = ndimage.sum_labels(output, labels, index)
        centroids = ndimage.center_of_mass(output, labels, index)
        # 3x3 means over the pixels inside the image, so a square clipped by the edge keeps its value
        square_means = ndimage.uniform_filter(output, size=3, mode="constant") / ndimage.uniform_filter(np.ones_like(output), size=3, mode="constant")
        best_squares = ndimage.maximum(square_means, labels, index)
        ids = np.empty(count + 1, dtype=np.int64)
        for k, (total, (row, col), square) in enumerate(zip(sums, centroids, best_squares, strict=True), start=1):
            ids[k] = len(self._blobs)
            self._blobs.append((plane, float(row), float(col), float(total), float(square)))
            self._parent.append(ids[k])
        if self._previous is not None and self._previous[0] == plane - 1:
            _, previous_labels, previous_ids = self._previous
            grown = ndimage.grey_dilation(previous_labels, size=(3, 3))
            touching = (labels > 0) & (grown > 0)
            for current, earlier in set(zip(labels[touching].tolist(), grown[touching].tolist(), strict=True)):
                a, b = self._root(int(ids[current])), self._root(int(previous_ids[earlier]))
                if a != b:
                    self._parent[a] = b
        self._previous = (plane, labels, ids)

    def particles(self) -> dict[str, np.ndarray]:
        """The particle table: x_um, y_um, z_um, diameter_um, score, planes (chain length)."""
        chains: dict[int, list[int]] = {}
        for blob in range(len(self._blobs)):
            chains.setdefault(self._root(blob), []).append(blob)
        rows, strengths = [], []
        for members in chains.values():
            by_plane: dict[int, float] = {}
            for blob in members:
                plane = self._blobs[blob][0]
                by_plane[plane] = by_plane.get(plane, 0.0) + self._blobs[blob][3]
            best = max(members, key=lambda b: self._blobs[b][3])
            plane, row, col, _, square_mean = self._blobs[best]
            strengths.append(sum(by_plane.values()))
            rows.append((
                self.origin_um[0] + col * self.pixel_um,
                self.origin_um[1] + row * self.pixel_um,
                self._refined_depth(plane, by_plane),
                square_mean / LABEL_SCALE,
                min(max(square_mean / self.full_value, 0.0), 1.0),
                len(by_plane),
            ))
        if self.merge_lateral_um > 0 and rows:
            from scipy.spatial import cKDTree

            positions = np.array([(r[0], r[1]) for r in rows])
            tree = cKDTree(positions)
            suppressed = np.zeros(len(rows), bool)
            kept: list[int] = []
            for index in np.argsort(strengths)[::-1]:  # strongest first; weaker chains under it are the same particle
                if not suppressed[index]:
                    kept.append(int(index))
                    suppressed[tree.query_ball_point(positions[index], self.merge_lateral_um)] = True
            rows = [rows[i] for i in kept]
        rows.sort(key=lambda r: (r[2], r[1], r[0]))
        columns = ("x_um", "y_um", "z_um", "diameter_um", "score", "planes")
        table = np.asarray(rows, dtype=np.float64).reshape(-1, len(columns))
        return {name: table[:, i] for i, name in enumerate(columns)}

    def _refined_depth(self, plane: int, by_plane: dict[int, float]) -> float:
        z = float(self.planes_um[plane])
        if plane - 1 not in by_plane or plane + 1 not in by_plane or not 0 < plane < len(self.planes_um) - 1:
            return z
        left, centre, right = by_plane[plane - 1], by_plane[plane], by_plane[plane + 1]
        curvature = left - 2 * centre + right
        if curvature >= 0:
            return z
        offset = 0.5 * (left - right) / curvature  # vertex of the parabola, in planes, within ±0.5
        step = 0.5 * (self.planes_um[plane + 1] - self.planes_um[plane - 1])
        return z + float(np.clip(offset, -0.5, 0.5)) * float(step)


def detect_particles(outputs: np.ndarray, planes_um: Sequence[float], *, pixel_um: float, threshold: float, full_value: float) -> dict[str, np.ndarray]:
    """Particles from a ``(planes, rows, cols)`` output volume in label units (see `PlaneLinker`)."""
    outputs = np.asarray(outputs)
    if outputs.ndim != 3 or outputs.shape[0] != len(planes_um):
        raise InputError(f"outputs: expected shape (len(planes_um)={len(planes_um)}, rows, cols), got {outputs.shape}")
    linker = PlaneLinker(planes_um, pixel_um=pixel_um, threshold=threshold, full_value=full_value)
    for plane, output in enumerate(outputs):
        linker.add(plane, output)
    return linker.particles()


class PeakDecoder:
    """3-D peak finding over streamed ``focus`` output planes (see the module docstring).

    Parameters
    ----------
    planes_um : sequence of float
        Depth of each plane (µm), increasing, in the order planes will be added.
    pixel_um : float
        Pixel pitch (µm).
    step_um : float
        The depth unit of the offsets (the training stack's plane spacing, µm).
    floor : float
        Smallest probability kept as a candidate (the final threshold is applied later).
    window_px : int
        Lateral half-width of the local-maximum neighbourhood (pixels).
    origin_um : (x, y)
        Position of pixel (0, 0), for outputs of a crop.
    """

    def __init__(self, planes_um: Sequence[float], *, pixel_um: float, step_um: float, floor: float = 0.05, window_px: int = 2, origin_um: tuple[float, float] = (0.0, 0.0)) -> None:
        if not 0 < floor < 1:
            raise InputError(f"floor: expected a probability in (0, 1), got {floor}")
        self.planes_um = np.asarray(planes_um, dtype=np.float64)
        self.pixel_um, self.step_um, self.floor = float(pixel_um), float(step_um), float(floor)
        self.size = 2 * int(window_px) + 1
        self.origin_um = origin_um
        self._window: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []  # (plane, p, offset, diameter, lateral max)
        self._rows: list[tuple[float, float, float, float, float]] = []

    def add(self, plane: int, probability: np.ndarray, offset: np.ndarray, diameter_um: np.ndarray) -> None:
        """Add plane ``plane`` (increasing): probability, offset (planes), diameter (µm), each ``(rows, cols)``.

        A plane is decoded once its next neighbour has arrived (or at `candidates`), so at most
        three planes are held whatever the depth of the stack.
        """
        probability = np.asarray(probability, np.float32)
        if self._window and plane != self._window[-1][0] + 1:
            self._flush()  # a gap in depth: the planes on either side are not neighbours
        lateral_max = ndimage.maximum_filter(probability, size=self.size, mode="constant", cval=0.0)
        self._window.append((plane, probability, np.asarray(offset, np.float32), np.asarray(diameter_um, np.float32), lateral_max))
        if len(self._window) >= 2:
            self._emit(len(self._window) - 2)
        if len(self._window) == 3:
            self._window.pop(0)

    def _emit(self, middle: int) -> None:
        """Candidates of ``self._window[middle]`` given its neighbours in the window."""
        plane, probability, offset, diameter, _ = self._window[middle]
        neighbourhood = np.max(np.stack([w[4] for w in self._window[max(middle - 1, 0) : middle + 2]]), axis=0)
        peaks = np.argwhere((probability >= neighbourhood) & (probability >= self.floor))
        rows, cols = probability.shape
        for row, col in peaks:
            r0, r1, c0, c1 = max(row - 1, 0), min(row + 2, rows), max(col - 1, 0), min(col + 2, cols)
            weights = probability[r0:r1, c0:c1]
            r_grid, c_grid = np.mgrid[r0:r1, c0:c1]
            total = float(weights.sum())
            row_c, col_c = float((weights * r_grid).sum() / total), float((weights * c_grid).sum() / total)
            self._rows.append((
                self.origin_um[0] + col_c * self.pixel_um,
                self.origin_um[1] + row_c * self.pixel_um,
                float(self.planes_um[plane]) + self.step_um * float(np.clip(offset[row, col], -1.0, 1.0)),
                max(float(diameter[row, col]), 0.0),
                float(probability[row, col]),
            ))

    def _flush(self) -> None:
        """Decode the last plane held (it has no next neighbour) and start afresh."""
        if self._window:
            self._emit(len(self._window) - 1)
        self._window = []

    def candidates(self) -> dict[str, np.ndarray]:
        """All candidates so far (call once all planes are added): x_um, y_um, z_um, diameter_um, score."""
        self._flush()
        table = np.asarray(self._rows, dtype=np.float64).reshape(-1, 5)
        return {name: table[:, i] for i, name in enumerate(("x_um", "y_um", "z_um", "diameter_um", "score"))}


def suppress(candidates: dict[str, np.ndarray], *, threshold: float, lateral_um: float, axial_um: float) -> dict[str, np.ndarray]:
    """One particle per peak: candidates scoring at least ``threshold``, strongest first, each
    removing the weaker ones within ``lateral_um`` in (x, y) *and* ``axial_um`` in z.

    Returns the kept rows of ``candidates`` (same columns), sorted by depth.
    """
    keep = np.flatnonzero(candidates["score"] >= threshold)
    keep = keep[np.argsort(-candidates["score"][keep], kind="stable")]
    xy = np.column_stack([candidates["x_um"][keep], candidates["y_um"][keep]])
    z = candidates["z_um"][keep]
    kept: list[int] = []
    if keep.size:
        from scipy.spatial import cKDTree

        tree = cKDTree(xy)
        suppressed = np.zeros(keep.size, bool)
        for i in range(keep.size):
            if suppressed[i]:
                continue
            kept.append(int(keep[i]))
            near = np.asarray(tree.query_ball_point(xy[i], lateral_um), dtype=np.int64)
            suppressed[near[np.abs(z[near] - z[i]) <= axial_um]] = True
    kept_index = np.asarray(kept, np.int64)
    kept_index = kept_index[np.lexsort((candidates["x_um"][kept_index], candidates["y_um"][kept_index], candidates["z_um"][kept_index]))]
    return {name: values[kept_index] for name, values in candidates.items()}
