"""Step 1: a hologram layer → its reconstruction z-stack in µm."""

from __future__ import annotations

import numpy as np
from magicgui.widgets import create_widget

from napari_lbs._core import backpropagate, load_config
from napari_lbs._layers import UNITS, PlaneGrid
from napari_lbs._widgets._base import StepWidget
from napari_lbs._widgets._fields import chosen, config_from, config_problem, hologram_data, hologram_problem, path_edit
from napari_lbs._widgets._setup import place_hologram

__all__ = ["BackpropWidget", "CONFIG_TOOLTIP", "HOLOGRAM_TOOLTIP"]

_LAZY_BYTES = 1 << 30  # stacks larger than this are computed plane by plane on demand
HOLOGRAM_TOOLTIP = "An intensity hologram Image layer (2-D; RGB is reduced to its signal channel)"
CONFIG_TOOLTIP = f"Experiment config (TOML, docs/config.md); empty: the defaults. {load_config.__doc__.splitlines()[0]}"


class BackpropWidget(StepWidget):
    """Hologram Image layer → z-stack Image layer in µm (z values in metadata)."""

    title = "back-propagation"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram", options={"tooltip": HOLOGRAM_TOOLTIP})
        self.config = path_edit(label="config", name="config", placeholder="empty: the defaults", filter="*.toml", tooltip=CONFIG_TOOLTIP)
        super().__init__(napari_viewer, [self.hologram, self.config])

    def problem(self):
        return hologram_problem(self.hologram.value) or config_problem(self.config)

    def prepare(self):
        layer = self.hologram.value
        place_hologram(layer, chosen(self.config))
        return hologram_data(layer), config_from(self.config), layer.name, tuple(layer.translate[-2:])

    def work(self, job, *, progress, should_stop, report):
        hologram, config, name, origin = job
        z_um = config.volume.planes_um()
        optics = {"wavelength_um": config.optics.wavelength_um, "pixel_um": config.optics.pixel_um, "medium_index": config.optics.medium_index}
        if len(z_um) * hologram.size * 4 > _LAZY_BYTES:
            import dask
            import dask.array as da

            # Browse a deep stack without holding it: each plane is computed when napari shows it.
            planes = [da.from_delayed(dask.delayed(lambda z: backpropagate(hologram, [z], **optics)[0])(z), hologram.shape, np.float32) for z in z_um]
            stack = da.stack(planes)
        else:
            stack = backpropagate(hologram, z_um, progress=progress, should_stop=should_stop, **optics)
        return stack, config, name, z_um, origin

    def show(self, result):
        stack, config, name, z_um, origin = result
        grid = PlaneGrid.of_planes(z_um, pixel_um=config.optics.pixel_um, origin_um=origin)
        self._viewer.add_image(
            stack,
            name=f"{name} z-stack",
            scale=grid.scale,
            translate=grid.translate,
            units=UNITS,
            axis_labels=("z", "y", "x"),
            metadata={"z_um": list(z_um), "config": config.to_dict(), "source": name, "lazy": not isinstance(stack, np.ndarray)},
        )
        self.done(f"{len(z_um)} planes {z_um[0]:g}–{z_um[-1]:g} µm")
