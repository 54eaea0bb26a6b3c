"""Step 6: where, which and how much the experiment differs from the simulation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from magicgui.widgets import LineEdit, SpinBox, create_widget

from napari_lbs._core import DiagnosisSettings
from napari_lbs._layers import UNITS
from napari_lbs._widgets._backprop import CONFIG_TOOLTIP, HOLOGRAM_TOOLTIP
from napari_lbs._widgets._base import StepWidget, config_from, config_problem, effects_problem, hologram_data, hologram_problem, output_problem, parsed_effects, path_edit, place_hologram

__all__ = ["DiagnosisWidget"]


class DiagnosisWidget(StepWidget):
    """Sim-to-real gap diagnosis of a hologram: where it lies (map over the hologram), which effect, how much."""

    title = "gap diagnosis"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram", options={"tooltip": HOLOGRAM_TOOLTIP})
        self.config = path_edit(label="config", name="config", placeholder="empty: the defaults", filter="*.toml", tooltip=CONFIG_TOOLTIP)
        self.tile = SpinBox(label="tile px (0: tile.size)", name="tile", value=0, min=0, max=8192, tooltip="Edge of the non-overlapping tiles the hologram is cut into (pixels); at least 4 tiles")
        self.sim_tiles = SpinBox(label="simulated tiles", name="sim_tiles", value=8, min=2, max=256, tooltip="Simulated tiles per model of the experiment (more: a steadier gap, slower)")
        self.evaluations = SpinBox(label="evaluations per fit", name="evaluations", value=40, min=8, max=10000, tooltip="Evaluations of each effect's fit (more: better fitted parameters, slower)")
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1, tooltip="Seeds the simulated tiles and the fits")
        self.known_effects = LineEdit(label="known effects", name="known_effects", value="",
                                      tooltip="Effects you know the experiment has, put into every model and not diagnosed, as on the command line, separated by ';' "
                                              "(polystyrene beads in water: particle_phase:index_contrast=0.26,transmission=1). Empty: only what the file states")
        self.output = path_edit(label="report folder", name="output", mode="d", value="lbs-diagnosis", tooltip="report.json (CONTRACT.md), report.md and figures are written here")
        super().__init__(napari_viewer, [self.hologram, self.config, self.tile, self.sim_tiles, self.evaluations, self.seed, self.known_effects, self.output])
        self.diagnosis = None

    def problem(self):
        problem = hologram_problem(self.hologram.value) or config_problem(self.config) or effects_problem(self.known_effects)
        if problem:
            return problem
        size = self.tile.value or config_from(self.config).tile.size
        rows, cols = self.hologram.value.data.shape[:2]
        if (rows // size) * (cols // size) < 4:
            return f"tile: {size}-pixel tiles give fewer than 4 tiles of the {rows}x{cols} hologram; choose a smaller tile"
        return output_problem(self.output, "report folder", folder=True)

    def prepare(self):
        settings = DiagnosisSettings(sim_tiles=self.sim_tiles.value, evaluations=self.evaluations.value, seed=self.seed.value)
        layer = self.hologram.value
        place_hologram(layer, self.config)
        return hologram_data(layer), config_from(self.config), self.tile.value or None, parsed_effects(self.known_effects), settings, Path(self.output.value), layer

    def work(self, job, *, progress, should_stop, report):
        from napari_lbs._core import diagnose_hologram, write_report

        hologram, config, tile, stated, settings, output, layer = job
        diagnosis = diagnose_hologram(hologram, config, tile_px=tile, stated=stated, settings=settings, progress=progress, should_stop=should_stop)
        write_report(diagnosis, output, provenance={"source": layer.name, "config": config.to_dict(), "seed": settings.seed})  # the report holds `stated`
        return diagnosis, output, layer

    def show(self, outcome):
        diagnosis, output, layer = outcome
        self.diagnosis = diagnosis
        report = diagnosis.report
        size = int(report["tiles"]["shape"][0])  # the tiles the diagnosis cut (adapted to the hologram), not the config's
        rows, cols = layer.data.shape[0] // size, layer.data.shape[1] // size
        where = np.asarray(report["gap"]["by_region"], np.float32).reshape(rows, cols)
        pixel = np.asarray(layer.scale[-2:], float)
        scale = tuple(pixel * size)
        translate = tuple(np.asarray(layer.translate[-2:]) + (np.asarray(scale) - pixel) / 2)
        gap_map = self._viewer.add_image(where, name="gap by region", scale=scale, translate=translate, units=UNITS, colormap="magma", opacity=0.45, blending="additive", metadata={"report": report, "folder": str(output)})
        gap_map.colorbar.visible = True
        verdict = report["verdict"]
        self.done(f"gap {report['gap']['baseline']:.2f}; verdict {verdict['id'] or 'nothing missing'} (shrink {100 * verdict['shrink']:.0f} %) → {output / 'report.md'}")
