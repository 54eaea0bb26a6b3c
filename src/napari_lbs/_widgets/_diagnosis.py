"""Step 6: which catalog effect the simulation lacks, where the experiment differs, how much adding it helps."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from magicgui.widgets import FloatSpinBox, LineEdit, SpinBox, create_widget

from napari_lbs._core import DiagnosisSettings
from napari_lbs._layers import UNITS
from napari_lbs._widgets._backprop import CONFIG_TOOLTIP, HOLOGRAM_TOOLTIP
from napari_lbs._widgets._base import StepWidget
from napari_lbs._widgets._fields import chosen, config_from, config_problem, effects_problem, hologram_problem, output_problem, parsed_effects, path_edit, replacing
from napari_lbs._widgets._plots import ColourBarPlot, PosteriorPlot
from napari_lbs._widgets._setup import place_hologram

__all__ = ["DiagnosisWidget"]


class DiagnosisWidget(StepWidget):
    """Gap diagnosis of a hologram or a recording: the posterior over the effect catalog (a bar chart), a map of where the experiment differs."""

    title = "gap diagnosis"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram",
                                      options={"tooltip": HOLOGRAM_TOOLTIP + " A stack (frames, rows, cols) is pooled: every frame is one more look at the same setup."})
        self.config = path_edit(label="config", name="config", placeholder="empty: the defaults", filter="*.toml", tooltip=CONFIG_TOOLTIP)
        self.tile = SpinBox(label="tile px (0: 128)", name="tile", value=0, min=0, max=8192,
                            tooltip="Edge of the square tiles the hologram is read in (pixels): the sensor is cut into 4 × 4 cells and each cell is read as the whole "
                                    "tiles it holds, so the gap map has a square per tile (a 1024² hologram in 128-px tiles: 8 × 8); 0: 128, or the cell where smaller")
        self.simulations = SpinBox(label="simulations", name="simulations", value=DiagnosisSettings().simulations, min=20, max=100_000,
                                   tooltip="Simulations the setup's diagnoser learns from, once per setup (cached and reused): 2000 take about 10 minutes on 2 cores")
        self.level = FloatSpinBox(label="level", name="level", value=DiagnosisSettings().level, min=0.05, max=1.0, step=0.05,
                                  tooltip="Probability an effect needs to be named present; below it the verdict is nothing missing or undecided")
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1, tooltip="Seeds the two-sample tests' folds (the posterior does not depend on it)")
        self.known_effects = LineEdit(label="known effects", name="known_effects", value="",
                                      tooltip="Effects you know the experiment has, put into every simulation and not diagnosed, as on the command line, separated by ';' "
                                              "(polystyrene beads in water: particle_phase:index_contrast=0.26,transmission=1). Empty: only what the file states")
        self.output = path_edit(label="report folder", name="output", mode="d", value="lbs-diagnosis", tooltip="report.json (docs/formats.md), report.md and figures are written here")
        super().__init__(napari_viewer, [self.hologram, self.config, self.tile, self.simulations, self.level, self.seed, self.known_effects, self.output])
        self._plot = PosteriorPlot(level=self.level.value)
        self.add_view(self._plot.canvas)
        self.level.changed.connect(self._show_level)
        self._colour_bar = ColourBarPlot()  # the gap map's, labelled
        self.add_view(self._colour_bar.canvas)
        self.diagnosis = None

    def _show_level(self, *_) -> None:
        """The level a verdict needs, on the plot until a run shows its own report."""
        if self.diagnosis is None:
            self._plot.show({}, nothing_missing=0.0, level=float(self.level.value))

    def problem(self):
        layer = self.hologram.value
        if layer is not None and ("z_um" in layer.metadata or layer.name.endswith(" z-stack")):  # Back-propagation's planes of one hologram, not frames
            source = layer.metadata.get("source")
            return (f"hologram: {layer.name!r} is a z-stack of back-propagated planes, not a recording of frames; "
                    f"choose {'the hologram ' + repr(source) if source else 'the hologram'}")
        stack = layer is not None and not layer.rgb and layer.ndim == 3  # a recording: its frames are pooled
        problem = (None if stack else hologram_problem(layer)) or config_problem(self.config) or effects_problem(self.known_effects)
        if problem:
            return problem
        rows, cols = _frame_shape(layer)
        size = self.tile.value or min(128, min(rows, cols) // 4)
        if size < 64 or size > min(rows, cols) // 4:
            return f"tile: the {rows}x{cols} hologram holds 4 × 4 cells of {min(rows, cols) // 4} px; a tile must fit one and have at least 64 px (got {size})"
        return output_problem(self.output, "report folder", folder=True)

    def prepare(self):
        from napari_lbs._core.pipeline import DiagnoseRequest

        layer = self.hologram.value
        place_hologram(layer, chosen(self.config))
        settings = DiagnosisSettings(simulations=self.simulations.value, level=float(self.level.value), seed=self.seed.value)
        request = DiagnoseRequest(np.asarray(layer.data), Path(self.output.value), config_from(self.config), settings=settings, tile_px=self.tile.value or None,
                                  stated=parsed_effects(self.known_effects), source=layer.name)
        # the report's files are replaced only once `caution` is confirmed
        return replace(request, replace=replacing(request.outputs()) is not None), layer

    def caution(self, job):
        return replacing(job[0].outputs())

    def work(self, job, *, progress, should_stop, report):
        from napari_lbs._core.pipeline import diagnose

        request, layer = job
        return diagnose(request, progress=progress, should_stop=should_stop), request, layer

    def show(self, outcome):
        result, request, layer = outcome
        diagnosis = result.value
        self.diagnosis = diagnosis
        report = diagnosis.report
        self._plot.show(report["marginals"], nothing_missing=report["posterior"]["null"], level=report["settings"]["level"])
        size = int(report["tiles"]["tile_px"])
        pixel = np.asarray(layer.scale[-2:], float)
        scale = tuple(pixel * size)
        translate = tuple(np.asarray(layer.translate[-2:]) + (np.asarray(scale) - pixel) / 2)
        where = np.nan_to_num(diagnosis.tile_map, nan=0.0).astype(np.float32)
        gap_map = self._viewer.add_image(where, name="gap: P(tile told apart from simulation)", scale=scale, translate=translate, units=UNITS, colormap="magma",
                                         contrast_limits=(0.0, 1.0), opacity=0.45, blending="additive", metadata={"report": report, "folder": str(request.out_dir)})
        gap_map.colorbar.visible = True
        self._colour_bar.show(label=gap_map.name, limits=tuple(gap_map.contrast_limits), colormap="magma")
        self.done(result.summary)


def _frame_shape(layer) -> tuple[int, int]:
    """(rows, cols) of a hologram layer's frames (its last two axes; an RGB layer's two before the channels)."""
    shape = np.shape(layer.data)
    return tuple(shape[-3:-1]) if getattr(layer, "rgb", False) else tuple(shape[-2:])
