"""A step's setup before it runs: the hologram layer in µm, and the model checked against it.

napari's own readers open an image in pixels while every result of the plugin is in µm; a
step puts the hologram it uses in µm first (the pixel size from its config, told before for
the file, or asked), so results sit on it. A model is compared with the hologram's setup
(`model_mismatches`) and a mismatch becomes a warning the user confirms (`StepWidget.caution`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from qtpy.QtCore import QSettings

from napari_lbs._core import load_config
from napari_lbs._layers import UNITS

__all__ = ["file_of", "in_micrometres", "model_setup", "place_hologram", "place_in_micrometres", "restore_pixel_size"]

_PIXEL_SIZES = "pixel_um of files"  # QSettings group: the pixel size told for each file opened in pixels


def file_of(layer) -> str | None:
    """The absolute path of the file a layer was opened from, or None."""
    path = getattr(layer.source, "path", None)
    return str(Path(path).resolve()) if path else None


def _put_in_micrometres(layer, pixel_um: float) -> None:
    """Give a layer in pixels the µm scale of ``pixel_um`` pixels on its last two axes (its translate, in pixels, scaled alike)."""
    lateral = np.ones(layer.ndim)
    lateral[-2:] = pixel_um
    layer.scale = np.asarray(layer.scale) * lateral
    layer.translate = np.asarray(layer.translate) * lateral
    layer.units = [*layer.units[:-2], UNITS, UNITS]


def in_micrometres(layer) -> bool:
    """Whether a layer's lateral axes are in µm (the plugin's layers are; napari's own readers give pixels)."""
    return str(layer.units[-1]) == "micrometer"


def restore_pixel_size(layer) -> None:
    """Put an Image layer opened in pixels in µm when its file's pixel size was told before."""
    from napari.layers import Image

    file = file_of(layer)
    if isinstance(layer, Image) and file is not None and not in_micrometres(layer) and np.allclose(layer.scale[-2:], 1.0):
        told = QSettings("napari-lbs", _PIXEL_SIZES).value(file)
        if told is not None:
            _put_in_micrometres(layer, float(told))


def place_in_micrometres(layer, *, pixel_um: float | None, proposed_um: float) -> float:
    """Put a hologram layer in µm before a step uses it; return its pixel size (µm).

    A layer in µm keeps its scale, and so does one whose scale was set (its units become µm).
    One in pixels (opened by napari's own reader, scale 1) takes the
    pixel size told for its file before, else ``pixel_um`` (the step's config names one),
    else the one the user gives when asked (``proposed_um`` offered); it is remembered for
    the file, so the file opens in µm from then on.

    Raises
    ------
    ValueError
        When the user declines to give a pixel size.
    """
    from napari.utils.notifications import show_info
    from qtpy.QtWidgets import QInputDialog

    if in_micrometres(layer):
        return float(layer.scale[-1])
    if not np.allclose(layer.scale[-2:], 1.0):  # a scale set by hand is a pixel size in µm: only its units were missing
        layer.units = [*layer.units[:-2], UNITS, UNITS]
        return float(layer.scale[-1])
    file = file_of(layer)
    settings = QSettings("napari-lbs", _PIXEL_SIZES)
    told = settings.value(file) if file is not None else None
    if told is not None:
        pixel_um = float(told)
    elif pixel_um is None:
        pixel_um, ok = QInputDialog.getDouble(None, "Pixel size", f"{layer.name} is in pixels: its pixel size (µm)?", proposed_um, 0.001, 10000.0, 3)
        if not ok:
            raise ValueError(f"{layer.name}: in pixels and no pixel size given; give one, or a config")
    if file is not None:
        settings.setValue(file, float(pixel_um))
    _put_in_micrometres(layer, float(pixel_um))
    show_info(f"{layer.name}: put in µm ({pixel_um:g} µm pixels), as the plugin's results are")
    return float(pixel_um)


def place_hologram(layer, config_path: Path | None) -> float:
    """`place_in_micrometres` for a step whose config field names ``config_path`` (None: the defaults, whose pixel size is then offered, not assumed)."""
    config = load_config(config_path)
    return place_in_micrometres(layer, pixel_um=config.optics.pixel_um if config_path is not None else None, proposed_um=config.optics.pixel_um)


def model_setup(model_path: Path, config, layer=None):
    """The setup a model is to run on and how it differs from the one the model was trained for.

    Parameters
    ----------
    model_path : Path
        A model file.
    config : ExperimentConfig or None
        The config field's; None: the model's own, with the hologram layer's pixel size.
    layer : napari Image layer, optional
        The hologram, put in µm first (`place_in_micrometres`).

    Returns
    -------
    config : ExperimentConfig
    warning : str or None
        The mismatches (`model_mismatches`), one a line; None when the model fits.
    """
    from napari_lbs._core import ExperimentConfig, load_model
    from napari_lbs._core.learning import model_mismatches

    model = load_model(model_path)
    named = "the config"
    if layer is not None:
        pixel_um = place_in_micrometres(layer, pixel_um=config.optics.pixel_um if config is not None else None, proposed_um=model.config.optics.pixel_um)
        if config is None:
            setup = model.config.to_dict()
            setup["optics"]["pixel_um"] = pixel_um
            config, named = ExperimentConfig.from_dict(setup), f"the hologram {layer.name!r}"
    config = config if config is not None else model.config
    found = model_mismatches(model.meta, config, planes_um=config.volume.planes_um(), setup=named)
    return config, "The model was made for another setup:\n" + "\n".join(found) if found else None
