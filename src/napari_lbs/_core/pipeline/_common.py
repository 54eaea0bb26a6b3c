"""What every step shares: `StepResult`, the provenance outputs record, the log callback and the readers of a request's inputs.

Every step takes keyword-only ``progress(done, total)`` and ``should_stop()`` (see
`napari_lbs._core.foundation`'s ``ProgressCallback``) and ``log(text)`` for messages about the inputs (an RGB
image reduced to one channel, a data set with missing groups). Heavy modules are imported
inside the steps, so importing the pipeline costs nothing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from napari_lbs import __version__
from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import check_target, read_json_object

__all__ = ["Log", "StepResult", "provenance", "read_calibration", "check_outputs", "explained_by_fits"]

Log = Callable[[str], None]


@dataclass(frozen=True)
class StepResult:
    """What a step did.

    Attributes
    ----------
    summary : str
        One line for the user (the console script prints it on stderr).
    value : object
        The step's own result (`CalibrationResult`, `SyntheticDataset`, `TrainingResult`,
        `PredictionResult`, `Diagnosis`, a metrics dict, ...).
    paths : tuple of Path
        The files and folders it wrote, the main one first.
    """

    summary: str
    value: object = None
    paths: tuple[Path, ...] = ()


def provenance(config: ExperimentConfig, **extra) -> dict:
    """What every output records: the package version, the config and the step's own inputs."""
    return {"napari_lbs": __version__, "config": config.to_dict(), **extra}


def check_outputs(paths, *, replace: bool) -> None:
    """Refuse, before any work, an output that exists (unless ``replace``) or is a link, a folder, a device or a FIFO (`check_target`)."""
    for path in paths:
        check_target(path, force=replace)


def _quiet(_text: str) -> None:
    pass


def _hologram(source, *, log: Log):
    """The hologram of a request: read from its file, or the array it holds."""
    from napari_lbs._core.foundation import read_hologram

    return read_hologram(source, log=log) if isinstance(source, (str, Path)) else source


def _background(path, shape: tuple[int, int], *, log: Log):
    """The background file (None when not given), refused unless it has the hologram's ``shape``."""
    from napari_lbs._core.foundation import read_hologram

    if not path:
        return None
    background = read_hologram(path, log=log)
    if background.shape != shape:
        raise InputError(f"{path}: expected the hologram's shape {shape}, got {background.shape}")
    return background


def _source(source, name: str | None) -> str:
    return name if name is not None else str(source)


def read_calibration(path) -> dict:
    """A calibration JSON (docs/formats.md), checked before anything uses it."""
    from napari_lbs._core.foundation import check_calibration

    calibration = read_json_object(path, what="calibration")
    check_calibration(calibration, name=str(path))
    return calibration


def explained_by_fits(pending, table):
    """For each unrefined row of ``pending``, whether a refined particle of ``table`` lies within a quarter of its fitted diameter laterally.

    An unrefined row keeps its detection's guess, whose depth is the back-propagated focal
    spot's (a few micrometres off) and whose diameter is the config's mean: only its
    position says which particle it was, as `refine_particles`' twins are told apart.
    """
    import numpy as np

    refined = table[table["refined"].astype(bool)]
    if pending.empty or refined.empty:
        return np.zeros(len(pending), dtype=bool)
    lateral = np.hypot(pending["x_um"].to_numpy()[:, None] - refined["x_um"].to_numpy()[None],
                       pending["y_um"].to_numpy()[:, None] - refined["y_um"].to_numpy()[None])
    return (lateral < 0.25 * refined["diameter_um"].to_numpy()[None]).any(axis=1)
