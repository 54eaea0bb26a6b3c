"""napari reader (particle CSV → Points) and writer (Points → particle CSV), CONTRACT.md tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from napari_lbs._core import PARTICLE_COLUMNS, read_particles, write_particles


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
    """A particle CSV as a Points layer in (z, y, x) µm; extra numeric columns become features."""
    from napari_lbs._widgets import particles_layer_data

    table = read_particles(path)
    data, features = particles_layer_data(table)
    for name, values in table.items():
        if name not in PARTICLE_COLUMNS and values.dtype.kind == "f":
            features[name] = values
    return [(data, {"name": Path(path).stem, "features": features, "size": features["diameter_um"] if len(data) else 10.0, "face_color": "transparent", "out_of_slice_display": True, "metadata": {"source": str(path)}}, "points")]


def write_particle_csv(path: str, data, attributes: dict) -> list[str]:
    """Points (z, y, x in µm) → particle CSV; ``diameter_um`` from the features (else the point size) and other features after."""
    points = np.asarray(data, dtype=float).reshape(-1, np.shape(data)[-1] if np.ndim(data) == 2 else 3)
    if points.shape[1] < 3:
        raise ValueError(f"{path}: expected 3-D points (z, y, x), got {points.shape[1]}-D")
    features = attributes.get("features")
    columns = {} if features is None else {name: np.asarray(features[name]) for name in features}
    size = np.asarray(attributes.get("size", 10.0), dtype=float)
    diameter = columns.pop("diameter_um", None)
    if diameter is None:
        diameter = size if size.ndim == 1 else np.broadcast_to(size.reshape(-1)[:1] if size.size else 10.0, (len(points),))
    columns.pop("z_um", None)
    table = {"x_um": points[:, -1], "y_um": points[:, -2], "z_um": points[:, -3], "diameter_um": np.asarray(diameter, float)}
    table.update({name: values for name, values in columns.items() if values.dtype.kind in "fiu"})
    write_particles(path, table)
    return [path]
