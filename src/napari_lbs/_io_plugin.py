"""napari reader (particle CSV → Points) and writer (Points → particle CSV), CONTRACT.md tables.

A table read here lands on the default config's plane grid (`napari_lbs._layers`), so its
particles line up with a back-propagated stack of the default depths.
"""

from __future__ import annotations

from pathlib import Path

from napari_lbs._core import PARTICLE_COLUMNS, load_config, read_particles, write_particles
from napari_lbs._layers import PlaneGrid, particle_points, points_table


def _is_particle_table(path: str) -> bool:
    try:
        with open(path, encoding="utf-8") as handle:
            header = handle.readline().strip().split(",")
    except (OSError, UnicodeDecodeError):
        return False
    return all(column in header for column in PARTICLE_COLUMNS)


def get_reader(path):
    """Return a reader for a particle CSV, or None for anything else (napari then asks other plugins)."""
    if isinstance(path, list) or not str(path).lower().endswith(".csv") or not _is_particle_table(str(path)):
        return None
    return read_particle_csv


def read_particle_csv(path):
    """A particle CSV as a Points layer in (z, y, x) µm on the default plane grid; extra numeric columns become features."""
    config = load_config(None)
    table = read_particles(path)
    data, keywords = particle_points(table, PlaneGrid.of_planes(config.volume.planes_um(), pixel_um=config.optics.pixel_um))
    for name, values in table.items():
        if name not in PARTICLE_COLUMNS and values.dtype.kind == "f":
            keywords["features"][name] = values
    return [(data, {"name": Path(path).stem, **keywords, "metadata": {"source": str(path)}}, "points")]


def write_particle_csv(path: str, data, attributes: dict) -> list[str]:
    """Points → particle CSV in world µm (data × scale + translate); ``diameter_um`` and other features after."""
    table = points_table(data, scale=attributes.get("scale", (1.0, 1.0, 1.0)), translate=attributes.get("translate", (0.0, 0.0, 0.0)), features=attributes.get("features"), size=attributes.get("size"))
    write_particles(path, table)
    return [path]
