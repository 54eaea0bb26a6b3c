"""Step 2: GA calibration of Holo-processing on one reference tile (a Shapes rectangle).

Before any run the ROI shows its tile's reference image ``I_e`` (the image calibration
compares against): each move of the rectangle is debounced, the whole hologram's reference
planes are back-propagated once in a ``thread_worker`` (kept while hologram and config stay
the same) and the tile's ``I_e`` is cut from them; a result overtaken by a newer move is dropped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from magicgui.widgets import ComboBox, PushButton, SpinBox, create_widget
from qtpy.QtCore import QTimer

from napari_lbs._core import CalibrationSettings
from napari_lbs._core.calibration import experimental_reference, reference_planes
from napari_lbs._core.pipeline import CalibrateRequest, calibrate
from napari_lbs._layers import UNITS
from napari_lbs._widgets._backprop import CONFIG_TOOLTIP, HOLOGRAM_TOOLTIP
from napari_lbs._widgets._base import StepWidget
from napari_lbs._widgets._fields import chosen, config_from, config_problem, doc_of, hologram_data, hologram_problem, output_problem, path_edit, replacing
from napari_lbs._widgets._plots import FitnessPlot
from napari_lbs._widgets._setup import place_hologram

__all__ = ["CalibrationWidget"]

ROI_NAME = "reference ROI"
I_E_NAME = "I_e (experiment)"
I_S_NAME = "I_s (synthetic)"
_GAP_PX = 8  # between I_e and I_s, side by side
PREVIEW_DELAY_MS = 300  # the ROI must rest this long before its I_e is computed


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
                                tooltip="The calibration JSON (docs/formats.md): params, ssim, roi, history; Synthetic data reads it")
        self.add_roi = PushButton(text="Add reference ROI", tooltip="Put (or select) the one tile-sized rectangle on the hologram; drag it where the hologram is typical")
        super().__init__(napari_viewer, [self.hologram, self.roi, self.add_roi, self.config, self.generations, self.population, self.mode, self.seed, self.output])
        self._plot = FitnessPlot()
        self.add_view(self._plot.canvas)
        self.add_roi.changed.connect(self._add_roi)
        self.result = None
        self._live_history: list[dict] = []
        self._preview_timer = QTimer(self.native)
        self._preview_timer.setSingleShot(True)
        self._preview_timer.setInterval(PREVIEW_DELAY_MS)
        self._preview_timer.timeout.connect(self._start_preview)
        self._preview_wanted = 0  # counts requests: a result for an older one is stale
        self._preview_running: int | None = None  # the request being computed
        self._planes_cache: tuple | None = None  # (key, reference planes of the whole hologram)
        self._watched_roi = None
        for widget in (self.hologram, self.config, self.mode):
            widget.changed.connect(self._schedule_preview)
        self.roi.changed.connect(self._watch_roi)
        self._watch_roi()

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
            if layer is not None:
                try:
                    place_hologram(layer, chosen(self.config))
                except ValueError as error:
                    from napari.utils.notifications import show_info

                    show_info(str(error))
                    return
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

    # -- the ROI's I_e, before any run ------------------------------------------------------------
    def _watch_roi(self, *_) -> None:
        """Follow the chosen ROI layer's rectangle (and only that layer's)."""
        if self._watched_roi is not None:
            self._watched_roi.events.data.disconnect(self._schedule_preview)
        self._watched_roi = self.roi.value
        if self._watched_roi is not None:
            self._watched_roi.events.data.connect(self._schedule_preview)
        self._schedule_preview()

    def _schedule_preview(self, *_) -> None:
        self._preview_wanted += 1
        self._preview_timer.start()  # restarts: a moving ROI is computed once it rests

    def _preview_request(self):
        """What the preview needs, read in the GUI thread, or None while it cannot be made."""
        layer, origin = self.hologram.value, self._roi_origin()
        if origin is None or hologram_problem(layer) or config_problem(self.config):
            return None
        config = config_from(self.config)
        size = config.tile.size
        rows, cols = layer.data.shape[:2]
        x, y = origin
        if x < 0 or y < 0 or x + size > cols or y + size > rows:
            return None
        key = (id(layer.data), repr(config))
        cached = self._planes_cache if self._planes_cache is not None and self._planes_cache[0] == key else None
        return key, None if cached else hologram_data(layer), cached[1] if cached else None, config, origin, self.mode.value, layer

    def _start_preview(self) -> None:
        from napari.qt.threading import thread_worker
        from napari.utils.notifications import show_warning

        if self._preview_running is not None:
            return  # `_preview_finished` starts the newest request
        request = self._preview_request()
        if request is None:
            return
        key, hologram, planes, config, (x, y), mode, layer = request
        size = config.tile.size

        @thread_worker(start_thread=False)
        def compute():
            stack = reference_planes(hologram, config) if planes is None else planes
            return key, stack, experimental_reference(stack[:, y : y + size, x : x + size], mode=mode)

        self._preview_running = self._preview_wanted
        worker = compute()
        worker.returned.connect(lambda outcome, request=self._preview_running: self._show_preview(request, outcome, (x, y), layer))
        worker.errored.connect(lambda error: show_warning(f"reference ROI preview: {error}"))
        worker.finished.connect(self._preview_finished)
        worker.start()

    def _show_preview(self, request: int, outcome, origin, layer) -> None:
        key, stack, image = outcome
        self._planes_cache = (key, stack)
        if request != self._preview_wanted:
            return  # the ROI, hologram or config changed since: a newer preview follows
        x, y = origin
        self._put_image(I_E_NAME, image, layer, (y, x), {"napari_lbs_reference": "preview", "roi": [x, y]})

    def _preview_finished(self) -> None:
        started, self._preview_running = self._preview_running, None
        if started != self._preview_wanted and not self._preview_timer.isActive():
            self._start_preview()

    def _put_image(self, name: str, data: np.ndarray, layer, corner_px: tuple[float, float], metadata: dict) -> None:
        """Show ``data`` at pixel ``corner_px`` (row, col) of ``layer`` in µm: the plugin's layer of that name is updated, else added below the ROI."""
        scale = np.asarray(layer.scale[-2:], float)
        translate = tuple(np.asarray(layer.translate[-2:], float) + scale * np.asarray(corner_px, float))
        existing = next((other for other in self._viewer.layers if other.name == name and "napari_lbs_reference" in other.metadata), None)
        if existing is not None:
            existing.data, existing.translate, existing.metadata = data, translate, metadata
            existing.contrast_limits = (float(data.min()), float(data.max()) if data.max() > data.min() else float(data.min()) + 1.0)
            return
        active = self._viewer.layers.selection.active
        added = self._viewer.add_image(data, name=name, scale=tuple(scale), translate=translate, units=UNITS, metadata=metadata)
        roi = self.roi.value
        if roi is not None and roi in self._viewer.layers:
            self._viewer.layers.move(self._viewer.layers.index(added), self._viewer.layers.index(roi))
        if active is not None:
            self._viewer.layers.selection.active = active  # the ROI stays in hand

    def prepare(self):
        self._live_history = []
        self._plot.show_history([])
        settings = CalibrationSettings(mode=self.mode.value, generations=self.generations.value, population=self.population.value, seed=self.seed.value)
        layer = self.hologram.value
        place_hologram(layer, chosen(self.config))
        output = Path(self.output.value)
        request = CalibrateRequest(hologram_data(layer), output, config_from(self.config), settings=settings, roi=self._roi_origin(), source=layer.name,
                                   replace=replacing([output]) is not None)  # run only once `caution` is confirmed
        return request, layer

    def caution(self, job):
        return replacing(job[0].outputs())

    def work(self, job, *, progress, should_stop, report):
        # the pipeline's step: the same JSON and provenance as the console script writes
        request, layer = job
        result = calibrate(request, progress=progress, should_stop=should_stop, report=report).value
        return result, request.out_path, layer

    def report_received(self, record) -> None:
        """A generation's best fitness, as it is made: the curve grows during the run."""
        self._live_history.append(record)
        self._plot.show_history(self._live_history)

    def show(self, outcome):
        result, output, layer = outcome
        self.result = result
        x, y, size = result.roi
        metadata = {"napari_lbs_reference": "calibration", "calibration": result.to_json(), "file": str(output)}
        self._put_image(I_E_NAME, result.reference_experimental, layer, (y, x), metadata)
        self._put_image(I_S_NAME, result.reference_synthetic, layer, (y, x + size + _GAP_PX), metadata)
        self._plot.show_history(result.history)
        p = result.params
        self.done(f"SSIM {result.ssim:.3f} at N_R={p.N_R:.3f}, N_σ={p.N_sigma:.3f}, γ={p.gamma:.3f}{' (stopped)' if result.stopped else ''} → {output.name}", output)
