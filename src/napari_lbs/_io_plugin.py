"""napari reader (particle CSV → Points) and writer (Points → particle CSV), docs/formats.md tables.

A table read here lands on the default config's plane grid (`napari_lbs._layers`), so its
particles line up with a back-propagated stack of the default depths.

napari 0.9 has its own Points CSV reader and writer (``index,axis-0,…``), and a plugin cannot
rank above them: a ``.csv`` matches both readers, so napari asks which one (until the user
ticks "remember", stored in ``settings.plugins.extension2reader``), and its own writer comes
first in *Save Selected Layers…*. Hence two menu commands (*File → IO Utilities*) that read
and write particle tables without a choice, and a reader that hands any CSV that is not a
particle table on to napari's, so remembering "LBS holography" for ``.csv`` loses nothing.

A table is written with the ``.csv`` its name lacks (napari's save dialog proposes the layer's
name, "… particles", without one), as napari's own Points writer does. The reader also takes
a file without that extension when its header is a particle table's: the manifest offers it
for the names the plugin's Points layers propose (``* particles``, ``* truth``, ``missed (*)``),
which no other reader claims, so opening one asks nothing.
"""

from __future__ import annotations

import csv
from pathlib import Path

import napari

from napari_lbs._core import load_config, read_particles, write_particles
from napari_lbs._core.foundation import PARTICLE_COLUMNS
from napari_lbs._layers import PlaneGrid, frame_points, particle_points, points_table, prefer_particle_writer


def _is_particle_table(path: str) -> bool:
    """Whether a CSV's header names the particle columns, read as `read_particles` reads it (a byte-order mark, quoted names)."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as handle:
            header = next(csv.reader(handle), [])
    except (OSError, UnicodeDecodeError, csv.Error):
        return False
    return all(column in header for column in PARTICLE_COLUMNS)


def get_reader(path):
    """Return a reader for one file: a particle table (by its header, whatever its name) becomes Points, any other CSV goes to napari's own reader; None for anything else."""
    if isinstance(path, list) or Path(path).is_dir():
        return None
    if _is_particle_table(str(path)):
        return read_particle_csv
    return _read_with_napari if str(path).lower().endswith(".csv") else None


def _read_with_napari(path):
    """A CSV that is not a particle table, read by napari's built-in reader (its Points/Shapes tables)."""
    from npe2 import read

    return read([path], stack=False, plugin_name="napari")


def read_particle_csv(path):
    """A particle CSV as a Points layer in (z, y, x) µm on the default plane grid; further numeric or boolean columns become features.

    A recording's table (a ``frame`` column) gets the frame in front, as napari's time axis (`frame_points`).
    """
    config = load_config(None)
    table = read_particles(path)
    grid = PlaneGrid.of_planes(config.volume.planes_um(), pixel_um=config.optics.pixel_um)
    data, keywords = (frame_points if "frame" in table else particle_points)(table, grid)
    return [(data, {"name": Path(path).stem, **keywords, "metadata": {"source": str(path)}}, "points")]


def write_particle_csv(path: str, data, attributes: dict) -> list[str]:
    """Points → particle CSV in world µm (data × scale + translate); ``diameter_um`` and other features after.

    A name without ``.csv`` gets it. Points without a ``diameter_um`` feature (not particles:
    a user's own annotations) are written by napari's own Points writer, as napari would have.
    """
    features = attributes.get("features")
    if features is None or "diameter_um" not in features:
        from napari_builtins.io import napari_write_points

        written = napari_write_points(path, data, attributes)
        return [written] if written else []
    path = str(path) if str(path).lower().endswith(".csv") else f"{path}.csv"
    table = points_table(data, scale=attributes.get("scale", (1.0, 1.0, 1.0)), translate=attributes.get("translate", (0.0, 0.0, 0.0)), features=attributes.get("features"), size=attributes.get("size"))
    write_particles(path, table, force=True)  # napari's save dialog asked before replacing
    return [path]


def save_particle_table(viewer: napari.viewer.Viewer) -> list[str]:
    """*File → IO Utilities → Save particle table*: the active Points layer as a particle table, no writer to choose."""
    from napari.utils.notifications import show_info
    from qtpy.QtWidgets import QFileDialog

    layer = viewer.layers.selection.active
    if not isinstance(layer, napari.layers.Points):
        show_info("Save particle table: select a Points layer first")
        return []
    path, _ = QFileDialog.getSaveFileName(None, "Save particle table", f"{layer.name}.csv", "Particle table (*.csv)")
    if not path:
        return []
    return layer.save(path if path.lower().endswith(".csv") else f"{path}.csv", plugin="napari-lbs")


def open_particle_table(viewer: napari.viewer.Viewer) -> list:
    """*File → IO Utilities → Open particle table*: particle tables as Points, no reader to choose."""
    from qtpy.QtWidgets import QFileDialog

    paths, _ = QFileDialog.getOpenFileNames(None, "Open particle table", "", "Particle table (*.csv)")
    return [layer for path in paths for layer in viewer.open(path, plugin="napari-lbs")]


prefer_particle_writer()  # the reader or writer is in use: particle layers save as particle tables
