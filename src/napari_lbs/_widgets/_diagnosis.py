"""Step 6: which catalog effects the experiment holds around its own particles, where its structure is left unexplained, how much each effect explains."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from magicgui.widgets import SpinBox, create_widget

from napari_lbs._core.gap import parameter_text
from napari_lbs._core.pipeline import DIAGNOSED_FRAMES
from napari_lbs._layers import UNITS
from napari_lbs._widgets._backprop import CONFIG_TOOLTIP, HOLOGRAM_TOOLTIP
from napari_lbs._widgets._base import StepWidget
from napari_lbs._widgets._fields import chosen, config_from, config_problem, hologram_problem, output_problem, path_edit, replacing, wrapping_label
from napari_lbs._widgets._plots import ColourBarPlot, EffectsPlot
from napari_lbs._widgets._setup import place_hologram

__all__ = ["DiagnosisWidget"]


class DiagnosisWidget(StepWidget):
    """Gap diagnosis of a hologram or a recording: each effect's held-out z (a bar chart), the verdict and why, a map of the unexplained share per tile."""

    title = "gap diagnosis"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram",
                                      options={"tooltip": HOLOGRAM_TOOLTIP + f" A stack (frames, rows, cols) is a recording of one setup: up to {DIAGNOSED_FRAMES} "
                                                                             "evenly spaced frames are diagnosed, each on its own, and pooled."})
        self.config = path_edit(label="config", name="config", placeholder="empty: the defaults", filter="*.toml", tooltip=CONFIG_TOOLTIP)
        self.tile = SpinBox(label="tile px (0: 4 × 4 tiles)", name="tile", value=0, min=0, max=8192,
                            tooltip="Edge of the square tiles the frame's effects are fitted on and judged on, a checkerboard (pixels): the frame's shorter side "
                                    "over it gives the tiles per side, at most 16, and the gap map has a square per tile; 0: 4 × 4 tiles (a 1024² hologram: 256 px)")
        self.output = path_edit(label="report folder", name="output", mode="d", value="lbs-diagnosis", tooltip="report.json (docs/formats.md), report.md and figures are written here")
        super().__init__(napari_viewer, [self.hologram, self.config, self.tile, self.output])
        self._plot = EffectsPlot()
        self.add_view(self._plot.canvas)
        self._verdict = wrapping_label()  # the verdict and its reason
        self.add_view(self._verdict.native)
        self._colour_bar = ColourBarPlot()  # the gap map's, labelled
        self.add_view(self._colour_bar.canvas)

    def problem(self):
        from napari_lbs._core import InputError
        from napari_lbs._core.pipeline import tiles_per_side

        layer = self.hologram.value
        if layer is not None and ("z_um" in layer.metadata or layer.name.endswith(" z-stack")):  # Back-propagation's planes of one hologram, not frames
            source = layer.metadata.get("source")
            return (f"hologram: {layer.name!r} is a z-stack of back-propagated planes, not a recording of frames; "
                    f"choose {'the hologram ' + repr(source) if source else 'the hologram'}")
        stack = layer is not None and not layer.rgb and layer.ndim == 3  # a recording: its frames are diagnosed
        problem = (None if stack else hologram_problem(layer)) or config_problem(self.config)
        if problem:
            return problem
        if self.tile.value:
            try:
                tiles_per_side(_frame_shape(layer), self.tile.value, flag="tile")
            except InputError as error:
                return str(error)
        return output_problem(self.output, "report folder", folder=True)

    def prepare(self):
        from napari_lbs._core.pipeline import DiagnoseRequest

        layer = self.hologram.value
        place_hologram(layer, chosen(self.config))
        request = DiagnoseRequest(np.asarray(layer.data), Path(self.output.value), config_from(self.config),
                                  tile_px=self.tile.value or None, source=layer.name)
        # the report's files are replaced only once `caution` is confirmed
        return replace(request, replace=replacing(request.outputs()) is not None), layer

    def caution(self, job):
        return replacing(job[0].outputs())

    def work(self, job, *, progress, should_stop, report):
        from napari_lbs._core.pipeline import diagnose

        request, layer = job
        return diagnose(request, progress=progress, should_stop=should_stop), request, layer

    def show(self, outcome):
        from napari_lbs._core import SceneDiagnosisSettings

        result, request, layer = outcome
        diagnosis = result.value
        report = diagnosis.report
        levels = request.settings or SceneDiagnosisSettings()  # the decisions' levels (the step's default only sizes the fits' processes)
        self._plot.show(report["effects"], level=levels.level_z)
        verdict = report["verdict"]
        fitted = "; ".join(f"{e['id']} ({parameter_text(e)})" for e in report["effects"] if e["selected"] and e["params"])
        probability = f" (probability {verdict['probability']:.2f})" if verdict.get("probability") is not None else ""
        self._verdict.value = f"verdict: {verdict['id'] or 'nothing named'}{probability}; {verdict['reason']}" + (f"\nfitted: {fitted}" if fitted else "")
        self._verdict.tooltip = self._verdict.value
        # the tiles: a centred checkerboard of grid × grid squares of tile_px pixels
        size, grid = int(report["gap"]["tile_px"]), diagnosis.tile_map.shape[0]
        offset = (np.asarray(_frame_shape(layer)) - grid * size) // 2
        pixel = np.asarray(layer.scale[-2:], float)
        translate = tuple(np.asarray(layer.translate[-2:]) + pixel * (offset + (size - 1) / 2))
        where = np.nan_to_num(diagnosis.tile_map, nan=0.0).astype(np.float32)
        limits = (0.0, max(float(where.max()), 1.5 * levels.structure_level))
        gap_map = self._viewer.add_image(where, name="gap: unexplained share of the structure", scale=tuple(pixel * size), translate=translate, units=UNITS,
                                         colormap="magma", contrast_limits=limits, opacity=0.45, blending="additive",
                                         metadata={"report": report, "folder": str(request.out_dir)})
        gap_map.colorbar.visible = True
        self._colour_bar.show(label=gap_map.name, limits=limits, colormap="magma")
        self.done(result.summary)


def _frame_shape(layer) -> tuple[int, int]:
    """(rows, cols) of a hologram layer's frames (its last two axes; an RGB layer's two before the channels)."""
    shape = np.shape(layer.data)
    return tuple(shape[-3:-1]) if getattr(layer, "rgb", False) else tuple(shape[-2:])
