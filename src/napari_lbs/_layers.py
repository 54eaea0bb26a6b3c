"""How napari-lbs results become napari layers: one world in micrometres (no Qt here).

Every layer the plugin makes has ``units = "µm"`` on every axis, so napari never meets a
unit-less layer beside a µm one. A particle table becomes Points on the plane grid of its
reconstruction: data are ``(plane index, row, col)`` with ``scale = (z_step_um, pixel_um,
pixel_um)`` and ``translate = (z_min_um, y0_um, x0_um)``, so world coordinates are the
table's ``(z_um, y_um, x_um)``, the z slider steps through the planes, and in 2-D each particle
is drawn on its nearest plane (napari shows Points within half a data unit of the slice).
A recording's layers put its frame axis in front, napari's time axis: one step per frame,
labelled ``frame`` and dimensionless (frames are counted, not measured), so they sit beside
the single-frame layers without a units conflict; the recording itself, opened by any reader
as ``(frame, row, col)``, is put on the same axes (`recording_image`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["UNITS", "PlaneGrid", "frame_points", "particle_points", "points_table", "prefer_particle_writer", "recording_image", "show_every_depth", "track_lines"]

UNITS = "µm"


@dataclass(frozen=True)
class PlaneGrid:
    """Where a stack's planes and pixels lie in the world (µm).

    Attributes
    ----------
    z_min_um, z_step_um : float
        Depth of plane 0 and the spacing of planes.
    pixel_um : float
        Lateral pixel pitch.
    origin_um : (float, float)
        World ``(y, x)`` of pixel ``(0, 0)`` (the hologram layer's translate).
    """

    z_min_um: float
    z_step_um: float
    pixel_um: float
    origin_um: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def of_planes(cls, planes_um, *, pixel_um: float, origin_um: tuple[float, float] = (0.0, 0.0)) -> PlaneGrid:
        """The grid of evenly spaced depths ``planes_um`` (one plane: a 1-µm step)."""
        planes = np.asarray(planes_um, float)
        step = float(planes[1] - planes[0]) if len(planes) > 1 else 1.0
        return cls(float(planes[0]), step, float(pixel_um), (float(origin_um[0]), float(origin_um[1])))

    @classmethod
    def of_provenance(cls, provenance: dict, *, origin_um: tuple[float, float] = (0.0, 0.0)) -> PlaneGrid:
        """The grid a prediction's particles lie on: its provenance's ``planes_um`` (first, last, count) and pixel pitch."""
        first, last, count = provenance["planes_um"]
        return cls.of_planes(np.linspace(first, last, int(count)), pixel_um=provenance["config"]["optics"]["pixel_um"], origin_um=origin_um)

    @property
    def scale(self) -> tuple[float, float, float]:
        """napari ``scale`` of a ``(plane, row, col)`` layer: ``(z_step_um, pixel_um, pixel_um)``."""
        return (self.z_step_um, self.pixel_um, self.pixel_um)

    @property
    def translate(self) -> tuple[float, float, float]:
        """napari ``translate``: the world ``(z, y, x)`` of plane 0, pixel (0, 0), in µm."""
        return (self.z_min_um, *self.origin_um)


def particle_points(table: dict, grid: PlaneGrid) -> tuple[np.ndarray, dict]:
    """Points data on ``grid`` and the layer keywords (scale, translate, units, features, size).

    Parameters
    ----------
    table : dict of arrays
        A particle table (``x_um, y_um, z_um, diameter_um``; ``score`` optional; any further
        numeric or boolean column becomes a feature too).
    grid : PlaneGrid

    Returns
    -------
    data : (n, 3) array
        ``(plane index, row, col)``, fractional.
    keywords : dict
        ``scale``, ``translate``, ``units``, ``axis_labels`` (z, y, x), ``features``
        (``diameter_um``, ``z_um``, ``score``, then the further columns), ``size`` (the
        diameter in pixels) and ``face_color``.
    """
    count = len(np.asarray(table["x_um"]))
    world = np.stack([np.asarray(table[c], float) for c in ("z_um", "y_um", "x_um")], axis=1) if count else np.zeros((0, 3))
    data = (world - np.asarray(grid.translate)) / np.asarray(grid.scale)
    diameter = np.asarray(table["diameter_um"], float)
    features = {"diameter_um": diameter, "z_um": world[:, 0], "score": np.asarray(table["score"], float) if "score" in table else np.ones(count)}
    for name, values in table.items():  # further columns (a refined table's index, uncertainties, ...) ride along
        values = np.asarray(values)
        if name not in features and name not in ("x_um", "y_um") and values.dtype.kind in "biuf" and values.shape == (count,):
            features[name] = values
    keywords = {
        "scale": grid.scale,
        "translate": grid.translate,
        "units": UNITS,
        "axis_labels": ("z", "y", "x"),  # napari's slider is then labelled z (not -3)
        "features": features,
        "size": diameter / grid.pixel_um if count else 10.0,
        "face_color": "transparent",
    }
    return data, keywords


def _recording_keywords(grid: PlaneGrid) -> dict:
    """The ``(frame, plane, row, col)`` axes of a recording's layers: scale, translate, units, labels."""
    return {"scale": (1.0, *grid.scale), "translate": (0.0, *grid.translate), "units": ("", UNITS, UNITS, UNITS), "axis_labels": ("frame", "z", "y", "x")}


def show_every_depth(viewer, layer) -> None:
    """Draw every particle of a Points ``layer`` whatever the plane the viewer shows.

    The layer projects all its points in the slice (``projection_mode="all"``) and the
    viewer's slice along the layer's depth axis is made twice as thick as the particles'
    depth range, so every particle is in it wherever the slider stands; the slider is put
    on the particles' middle depth when it stands outside them. Setting the layer's
    projection mode back to ``"none"`` shows the particles of the plane shown only.
    """
    if not len(layer.data):
        return
    axis = viewer.dims.ndim - 3  # the particles' (z, y, x) are the viewer's last three axes
    low, high = layer.extent.world[:, -3]
    layer.projection_mode = "all"
    thickness = list(viewer.dims.thickness)
    thickness[axis] = max(thickness[axis], 2 * (high - low) + layer.scale[-3])
    viewer.dims.thickness = tuple(thickness)
    if not low <= viewer.dims.point[axis] <= high:
        viewer.dims.set_point(axis, (low + high) / 2)


def recording_image(frames, grid: PlaneGrid, *, planes: int) -> tuple[object, dict]:
    """A recording's ``(frame, row, col)`` image on the axes of its results: frame as time.

    The frames get a plane axis of length one whose one plane spans all ``planes`` depths
    of ``grid``, so each frame shows under its particles at every plane.

    Returns
    -------
    data : (frames, 1, rows, cols) array
        A view of ``frames``.
    keywords : dict
        ``scale``, ``translate``, ``units`` and ``axis_labels``, as the recording's Points.
    """
    keywords = _recording_keywords(grid)
    scale, translate = list(keywords["scale"]), list(keywords["translate"])
    scale[1] = grid.z_step_um * planes
    translate[1] = grid.z_min_um + grid.z_step_um * (planes - 1) / 2
    return frames[:, None], {**keywords, "scale": tuple(scale), "translate": tuple(translate)}


def frame_points(table: dict, grid: PlaneGrid) -> tuple[np.ndarray, dict]:
    """Points of a recording's table: `particle_points` with the frame in front as napari's time axis.

    Parameters
    ----------
    table : dict of arrays
        A particle table with ``frame`` (`predict_sequence`), and ``track`` once linked.
    grid : PlaneGrid

    Returns
    -------
    data : (n, 4) array
        ``(frame, plane index, row, col)``.
    keywords : dict
        As `particle_points`, on four axes (``axis_labels`` too); ``frame`` and ``track``
        join the features, so a table saved from the layer keeps them.
    """
    data, keywords = particle_points(table, grid)
    frame = np.asarray(table["frame"], float)
    keywords["features"].update({name: np.asarray(table[name]) for name in ("frame", "track") if name in table})
    return np.column_stack([frame, data]), {**keywords, **_recording_keywords(grid)}


def track_lines(table: dict, grid: PlaneGrid) -> tuple[np.ndarray, dict]:
    """napari Tracks of a linked table (`link_tracks`) on ``grid``.

    Returns
    -------
    data : (n, 5) array
        ``(track, frame, plane index, row, col)``, sorted by track then frame (as napari needs).
    keywords : dict
        ``scale``, ``translate``, ``units`` and ``axis_labels`` of the four axes after the
        track id: world coordinates are the table's ``(frame, z_um, y_um, x_um)``.
    """
    points, _ = frame_points(table, grid)  # the same (frame, plane, row, col) as the recording's Points
    track = np.asarray(table["track"], float)
    order = np.lexsort((points[:, 0], track))
    return np.column_stack([track, points])[order], _recording_keywords(grid)


def points_table(data, *, scale, translate, features=None, size=None) -> dict[str, np.ndarray]:
    """The particle table of Points ``(z, y, x)`` data: world µm = data × scale + translate.

    ``diameter_um`` comes from the features, else from the point size (pixels × lateral
    scale); other numeric features follow, except ``z_um`` (the world z is the depth).
    """
    points = np.asarray(data, float).reshape(len(data), -1) if len(data) else np.zeros((0, 3))
    if points.shape[1] < 3:
        raise ValueError(f"expected 3-D points (z, y, x), got {points.shape[1]}-D")
    world = points[:, -3:] * np.asarray(scale, float)[-3:] + np.asarray(translate, float)[-3:]
    columns = {} if features is None else {name: np.asarray(features[name]) for name in features}
    columns.pop("z_um", None)
    diameter = columns.pop("diameter_um", None)
    if diameter is None:  # napari keeps one size per point, in data units (pixels)
        pixels = np.broadcast_to(np.asarray(10.0 if size is None else size, float).reshape(-1), (len(points),)) if len(points) else np.zeros(0)
        diameter = pixels * float(np.asarray(scale, float)[-1])
    table = {"x_um": world[:, 2], "y_um": world[:, 1], "z_um": world[:, 0], "diameter_um": np.asarray(diameter, float)}
    table.update({name: values for name, values in columns.items() if values.dtype.kind in "fiu"})
    return table


def prefer_particle_writer() -> None:
    """Put the particle-table writer first among the Points writers napari offers in *Save Selected Layers…*.

    napari lists the writers npe2 finds for the layers, sorted by (no file extension, number of
    layer types constrained) and then in the order plugins registered, napari's own first: its
    CSV writer and ours tie, so ours goes to the front of npe2's writer index (a private list;
    where npe2 keeps no such list, nothing changes). Points that are not a particle table are
    still written as napari writes them (`napari_lbs._io_plugin.write_particle_csv`).
    """
    from npe2 import PluginManager

    index = getattr(PluginManager.instance()._contrib, "_writers", None)
    if isinstance(index, list):
        index.sort(key=lambda entry: not entry[-1].command.startswith("napari-lbs."))  # stable: the rest keep their order
