"""Step 2: GA calibration of Holo-processing on one reference tile (a Shapes rectangle)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from magicgui.widgets import ComboBox, PushButton, SpinBox, create_widget

from napari_lbs._core import CalibrationSettings, calibrate_hologram, write_json
from napari_lbs._layers import UNITS
from napari_lbs._widgets._backprop import CONFIG_TOOLTIP, HOLOGRAM_TOOLTIP
from napari_lbs._widgets._base import StepWidget, config_from, config_problem, doc_of, hologram_data, hologram_problem, output_problem, path_edit
from napari_lbs._widgets._plots import FitnessPlot

__all__ = ["CalibrationWidget"]

ROI_NAME = "reference ROI"
_GAP_PX = 8  # between I_e and I_s, side by side


class CalibrationWidget(StepWidget):
    """GA calibration of Holo-processing on a reference tile chosen with a Shapes rectangle."""

    title = "calibration"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram", options={"tooltip": HOLOGRAM_TOOLTIP})
        self.roi = create_widget(annotation=napari.layers.Shapes | None, label="reference ROI", name="roi",
                                 options={"tooltip": "The reference tile: the first rectangle's top-left pixel (tile.size square). None: the medoid tile is chosen"})
        self.config = path_edit(label="config", name="config", placeholder="empty: the defaults", filter="*.toml", tooltip=CONFIG_TOOLTIP)
        self.generations = SpinBox(label="generations", name="generations", value=100, min=1, max=10000, tooltip=doc_of(CalibrationSettings, "generations"))
        self.population = SpinBox(label="population", name="population", value=12, min=4, max=1000, tooltip=doc_of(CalibrationSettings, "population"))
        self.mode = ComboBox(label="mode", name="mode", choices=["robust", "seed"], value="robust",
                             tooltip="robust: several simulated fields, common random numbers, finalists re-scored on fresh noise; seed: the seed paper's single field and fresh noise")
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1, tooltip=doc_of(CalibrationSettings, "seed"))
        self.output = path_edit(label="save calibration", name="output", mode="w", filter="*.json", value="calibration.json",
                                tooltip="The calibration JSON (CONTRACT.md): params, ssim, roi, history; Synthetic data reads it")
        self.add_roi = PushButton(text="Add reference ROI", tooltip="Put (or select) the one tile-sized rectangle on the hologram; drag it where the hologram is typical")
        super().__init__(napari_viewer, [self.hologram, self.roi, self.config, self.generations, self.population, self.mode, self.seed, self.output])
        self.insert(2, self.add_roi)
        self._plot = FitnessPlot()
        self.native.layout().addWidget(self._plot.canvas)
        self.add_roi.changed.connect(self._add_roi)
        self.result = None
        self._live_history: list[dict] = []

    def problem(self):
        problem = hologram_problem(self.hologram.value) or config_problem(self.config)
        if problem:
            return problem
        size = config_from(self.config).tile.size
        shape = self.hologram.value.data.shape[:2]
        if size > min(shape):
            return f"tile.size: a {size}² tile is larger than the hologram {shape}"
        return output_problem(self.output, "save calibration", suffix=".json")

    def _add_roi(self, *_):
        """One ROI layer with one tile-sized rectangle, on the hologram's µm grid (a second click selects it)."""
        size = config_from(self.config).tile.size
        existing = [layer for layer in self._viewer.layers if layer.metadata.get("napari_lbs_roi")]
        if existing:
            shapes = existing[0]
        else:
            layer = self.hologram.value
            scale = tuple(layer.scale[-2:]) if layer is not None else (1.0, 1.0)
            translate = tuple(layer.translate[-2:]) if layer is not None else (0.0, 0.0)
            shapes = self._viewer.add_shapes([np.array([[0, 0], [size, size]], float)], shape_type="rectangle", name=ROI_NAME, scale=scale, translate=translate, units=UNITS,
                                             edge_color="yellow", face_color="transparent", edge_width=3, metadata={"napari_lbs_roi": True})
            shapes.events.data.connect(lambda event: self._snap(shapes, size))
        self._viewer.layers.selection.active = shapes
        self.roi.value = shapes

    @staticmethod
    def _snap(shapes, size: int) -> None:
        """Keep one rectangle, exactly one tile: the newest one's top-left corner rounded, its size fixed."""
        from napari.utils.notifications import show_info

        if not len(shapes.data):
            return
        corner = np.round(np.asarray(shapes.data[-1])[:, -2:].min(axis=0))
        target = np.array([corner, [corner[0], corner[1] + size], corner + size, [corner[0] + size, corner[1]]])
        if len(shapes.data) > 1:
            show_info("reference ROI: one tile only; the newest rectangle is kept")
        if len(shapes.data) > 1 or np.asarray(shapes.data[0]).shape != target.shape or not np.allclose(np.asarray(shapes.data[0]), target):
            with shapes.events.data.blocker():
                shapes.data = [target]

    def _roi_origin(self):
        shapes = self.roi.value
        if shapes is None or not len(shapes.data):
            return None
        row, col = np.round(np.asarray(shapes.data[0]).min(axis=0)).astype(int)[-2:]
        return int(col), int(row)

    def prepare(self):
        self._live_history = []
        self._plot.show_history([])
        settings = CalibrationSettings(mode=self.mode.value, generations=self.generations.value, population=self.population.value, seed=self.seed.value)
        layer = self.hologram.value
        return hologram_data(layer), config_from(self.config), self._roi_origin(), settings, Path(self.output.value), layer

    def work(self, job, *, progress, should_stop, report):
        hologram, config, roi, settings, output, layer = job
        result = calibrate_hologram(hologram, config, roi=roi, settings=settings, progress=progress, should_stop=should_stop, report=report)
        payload = result.to_json()
        payload["provenance"] = {"config": config.to_dict(), "seed": settings.seed}
        write_json(output, payload)
        return result, output, layer

    def report_received(self, record) -> None:
        """A generation's best fitness, as it is made: the curve grows during the run."""
        self._live_history.append(record)
        self._plot.show_history(self._live_history)

    def show(self, outcome):
        result, output, layer = outcome
        self.result = result
        x, y, size = result.roi
        scale = np.asarray(layer.scale[-2:], float)
        origin = np.asarray(layer.translate[-2:], float)
        metadata = {"calibration": result.to_json(), "file": str(output)}
        self._viewer.add_image(result.reference_experimental, name="I_e (experiment)", scale=tuple(scale), translate=tuple(origin + scale * (y, x)), units=UNITS, metadata=metadata)
        self._viewer.add_image(result.reference_synthetic, name="I_s (synthetic)", scale=tuple(scale), translate=tuple(origin + scale * (y, x + size + _GAP_PX)), units=UNITS, metadata=metadata)
        self._plot.show_history(result.history)
        p = result.params
        self.done(f"SSIM {result.ssim:.3f} at N_R={p.N_R:.3f}, N_σ={p.N_sigma:.3f}, γ={p.gamma:.3f}{' (stopped)' if result.stopped else ''} → {output.name}", output)
