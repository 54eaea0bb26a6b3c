"""napari dock widgets: thin fronts over `napari_lbs._core`, one per step of the workflow.

Every widget collects parameters, runs one `_core` function in napari's ``thread_worker``
(with the `_core` callbacks: ``progress`` relayed to a progress bar in napari's activity dock,
``should_stop`` wired to the Stop button) and shows the result as layers. While its inputs are
invalid, Run is disabled and the reason is shown. Errors become napari notifications and the
widget returns to ready on error, stop or finish. Settings persist between napari sessions.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
from magicgui.widgets import CheckBox, ComboBox, Container, FileEdit, FloatSpinBox, Label, PushButton, SpinBox, create_widget
from qtpy.QtCore import QObject, QSettings, Signal

from napari_lbs._core import (
    CalibrationSettings,
    DatasetLayout,
    InputError,
    InputProcessing,
    Stopped,
    backpropagate,
    calibrate_hologram,
    generate_dataset,
    load_config,
    match_particles,
    open_dataset,
    read_particles,
    score_particles,
    write_json,
)

__all__ = ["BackpropWidget", "CalibrationWidget", "GenerateWidget", "TrainingWidget", "PredictionWidget", "DiagnosisWidget", "particles_layer_data"]

_LAZY_BYTES = 1 << 30  # stacks larger than this are computed plane by plane on demand


class _Relay(QObject):
    """Carries worker-thread callbacks to the GUI thread (queued signals)."""

    progress = Signal(int, int)
    report = Signal(object)


class _StepWidget(Container):
    """Shared plumbing: Run/Stop, validation, progress, notifications, persisted settings."""

    title = ""

    def __init__(self, viewer, fields: list) -> None:
        super().__init__(labels=True)
        self._viewer = viewer
        self._fields = fields
        self._run = PushButton(text="Run")
        self._stop = PushButton(text="Stop", enabled=False)
        self._status = Label(value="")
        self.extend([*fields, Container(widgets=[self._run, self._stop], layout="horizontal", labels=False), self._status])
        self._stop_requested = threading.Event()
        self._worker = None
        self._progress_bar = None
        self._relay = _Relay()
        self._relay.progress.connect(self._on_progress)
        self._relay.report.connect(self._on_report)
        self._run.changed.connect(self._start)
        self._stop.changed.connect(self._stop_requested.set)
        self._restore_settings()
        for widget in fields:
            widget.changed.connect(self._changed)
        viewer.layers.events.inserted.connect(self._layers_changed)
        viewer.layers.events.removed.connect(self._layers_changed)
        self._revalidate()

    # -- settings and validation --------------------------------------------------------------
    def _settings(self) -> QSettings:
        return QSettings("napari-lbs", type(self).__name__)

    def _persisted(self):
        return [w for w in self._fields if isinstance(w, (SpinBox, FloatSpinBox, FileEdit, CheckBox)) or (isinstance(w, ComboBox) and isinstance(w.choices[0] if w.choices else None, str))]

    def _restore_settings(self) -> None:
        settings = self._settings()
        for widget in self._persisted():
            stored = settings.value(widget.name)
            if stored in (None, ""):
                continue
            try:
                widget.value = type(widget.value)(stored) if not isinstance(widget, CheckBox) else stored in (True, "true", "1")
            except (TypeError, ValueError):
                pass  # a stale setting is ignored, the default stays

    def _changed(self, *_):
        settings = self._settings()
        for widget in self._persisted():
            settings.setValue(widget.name, str(widget.value) if widget.value is not None else "")
        self._revalidate()

    def _layers_changed(self, *_):
        self.reset_choices()
        self._revalidate()

    def problem(self) -> str | None:
        """Why Run is disabled, or None when the inputs are valid."""
        return None

    def _revalidate(self) -> None:
        busy = self._worker is not None
        problem = None if busy else self.problem()
        self._run.enabled = not busy and problem is None
        if not busy:
            self._status.value = problem or "ready"

    # -- running --------------------------------------------------------------------------------
    def work(self, job, *, progress, should_stop, report):
        """The `_core` call on `prepare`'s ``job``, run in the worker thread; returns what `show` receives."""
        raise NotImplementedError

    def show(self, result) -> None:
        """Show a finished result (GUI thread)."""

    def _start(self, *_):
        from napari.qt.threading import thread_worker

        if self._worker is not None or self.problem() is not None:
            return
        self._stop_requested.clear()
        self._run.enabled = False
        self._stop.enabled = True
        self._status.value = "running…"
        try:
            job = self.prepare()
        except (ValueError, OSError) as error:
            self._on_errored(error)
            self._on_finished()
            return
        from napari.utils import progress

        # Made here, before the worker runs: creating it processes events, which must not
        # happen inside a progress callback (the job could finish in between).
        self._progress_bar = progress(total=0, desc=self.title)

        @thread_worker(connect={"returned": self._on_returned, "errored": self._on_errored, "finished": self._on_finished}, start_thread=False)
        def run():
            return self.work(job, progress=self._relay.progress.emit, should_stop=self._stop_requested.is_set, report=self._relay.report.emit)

        self._worker = run()
        self._worker.start()

    def prepare(self):
        """Read the inputs in the GUI thread (layers are not thread-safe); passed to `work`."""
        return None

    def _on_progress(self, done: int, total: int) -> None:
        if self._worker is None or self._progress_bar is None:  # a late signal from a finished job
            return
        self._progress_bar.total = total
        self._progress_bar.n = done
        self._progress_bar.refresh()
        self._status.value = f"{self.title}: {done}/{total}"

    def _on_report(self, record) -> None:
        """Per-step records (training); widgets that plot them override `report_received`."""
        if self._worker is not None:
            self.report_received(record)

    def report_received(self, record) -> None:
        """Handle one record of the running job (GUI thread)."""

    def _on_returned(self, result) -> None:
        self.show(result)

    def _on_errored(self, error: Exception) -> None:
        from napari.utils.notifications import show_error, show_info

        if isinstance(error, Stopped):
            show_info(f"{self.title}: stopped")
            self._last_message = "stopped; nothing was written"
        else:
            show_error(f"{self.title}: {error}")
            self._last_message = f"error: {str(error).splitlines()[0] if str(error) else type(error).__name__}"

    def _on_finished(self) -> None:
        if self._progress_bar is not None:
            self._progress_bar.close()
            self._progress_bar = None
        self._worker = None
        self._stop.enabled = False
        message = getattr(self, "_last_message", None)
        self._last_message = None
        self._revalidate()
        if message:
            self._status.value = message

    def _done(self, message: str) -> None:
        self._last_message = message


def _chosen(edit: FileEdit) -> Path | None:
    """The file an optional FileEdit names, or None when it is left empty (magicgui shows empty as ".")."""
    path = edit.value
    return Path(path) if path and str(path) not in ("", ".") else None


def _missing(edit: FileEdit, label: str) -> str | None:
    """Why an optional file input is invalid (named but absent), or None."""
    path = _chosen(edit)
    return f"{label}: {path} not found" if path is not None and not path.is_file() else None


def _config_from(edit: FileEdit):
    path = _chosen(edit)
    return load_config(path if path is not None and path.is_file() else None)


def _config_problem(edit: FileEdit) -> str | None:
    missing = _missing(edit, "config")
    if missing:
        return missing
    try:
        _config_from(edit)
    except ValueError as error:
        return str(error)
    return None


def _hologram_problem(layer) -> str | None:
    if layer is None:
        return "choose a hologram Image layer"
    if layer.rgb:
        return None  # reduced to one channel by as_hologram, with a message
    if layer.ndim != 2:
        return f"hologram: expected a 2-D image, got {layer.ndim}-D layer {layer.name!r}"
    return None


def _hologram_data(layer) -> np.ndarray:
    from napari_lbs._core import as_hologram

    return as_hologram(np.asarray(layer.data), name=layer.name)


class BackpropWidget(_StepWidget):
    """Hologram Image layer → z-stack Image layer in µm (z values in metadata)."""

    title = "back-propagation"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram")
        self.config = FileEdit(label="config (TOML, empty = default)", name="config", filter="*.toml", value="")
        super().__init__(napari_viewer, [self.hologram, self.config])

    def problem(self):
        return _hologram_problem(self.hologram.value) or _config_problem(self.config)

    def prepare(self):
        layer = self.hologram.value
        return _hologram_data(layer), _config_from(self.config), layer.name

    def work(self, job, *, progress, should_stop, report):
        hologram, config, name = job
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
        return stack, config, name, z_um

    def show(self, result):
        stack, config, name, z_um = result
        pixel = config.optics.pixel_um
        step = z_um[1] - z_um[0] if len(z_um) > 1 else 1.0
        self._viewer.add_image(
            stack,
            name=f"{name} z-stack",
            scale=(step, pixel, pixel),
            translate=(z_um[0], 0.0, 0.0),
            units="µm",
            metadata={"z_um": list(z_um), "config": config.to_dict(), "source": name, "lazy": not isinstance(stack, np.ndarray)},
        )
        self._done(f"{len(z_um)} planes {z_um[0]:g}–{z_um[-1]:g} µm")


class CalibrationWidget(_StepWidget):
    """GA calibration of Holo-processing on a reference tile chosen with a Shapes rectangle."""

    title = "calibration"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram")
        self.roi = create_widget(annotation=napari.layers.Shapes | None, label="reference ROI (Shapes)", name="roi")
        self.config = FileEdit(label="config (TOML, empty = default)", name="config", filter="*.toml", value="")
        self.generations = SpinBox(label="generations", name="generations", value=100, min=1, max=10000)
        self.population = SpinBox(label="population", name="population", value=12, min=4, max=1000)
        self.mode = ComboBox(label="mode", name="mode", choices=["robust", "seed"], value="robust")
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1)
        self.output = FileEdit(label="save calibration", name="output", mode="w", filter="*.json", value="calibration.json")
        self.add_roi = PushButton(text="Add reference ROI")
        super().__init__(napari_viewer, [self.hologram, self.roi, self.config, self.generations, self.population, self.mode, self.seed, self.output])
        self.insert(2, self.add_roi)
        self.add_roi.changed.connect(self._add_roi)
        self.result = None

    def problem(self):
        problem = _hologram_problem(self.hologram.value) or _config_problem(self.config)
        if problem:
            return problem
        size = _config_from(self.config).tile.size
        shape = self.hologram.value.data.shape[:2]
        if size > min(shape):
            return f"tile.size: a {size}² tile is larger than the hologram {shape}"
        if self.population.value < 4:
            return "population: at least 4"
        return None

    def _add_roi(self, *_):
        size = _config_from(self.config).tile.size
        layer = self.hologram.value
        scale = tuple(layer.scale[-2:]) if layer is not None else (1.0, 1.0)
        shapes = self._viewer.add_shapes([np.array([[0, 0], [size, size]], float)], shape_type="rectangle", name="reference ROI", scale=scale, edge_color="yellow", face_color="transparent", edge_width=3)
        shapes.events.data.connect(lambda event: self._snap(shapes, size))
        self.roi.value = shapes

    @staticmethod
    def _snap(shapes, size: int) -> None:
        """Keep the first rectangle exactly one tile: its top-left corner rounded, its size fixed."""
        if not len(shapes.data):
            return
        corner = np.round(np.asarray(shapes.data[0]).min(axis=0))
        target = np.array([corner, [corner[0], corner[1] + size], corner + size, [corner[0] + size, corner[1]]])
        if np.asarray(shapes.data[0]).shape != target.shape or not np.allclose(np.asarray(shapes.data[0]), target):
            with shapes.events.data.blocker():
                data = list(shapes.data)
                data[0] = target
                shapes.data = data

    def _roi_origin(self):
        shapes = self.roi.value
        if shapes is None or not len(shapes.data):
            return None
        row, col = np.round(np.asarray(shapes.data[0]).min(axis=0)).astype(int)[-2:]
        return int(col), int(row)

    def prepare(self):
        settings = CalibrationSettings(mode=self.mode.value, generations=self.generations.value, population=self.population.value, seed=self.seed.value)
        return _hologram_data(self.hologram.value), _config_from(self.config), self._roi_origin(), settings, Path(self.output.value)

    def work(self, job, *, progress, should_stop, report):
        hologram, config, roi, settings, output = job
        result = calibrate_hologram(hologram, config, roi=roi, settings=settings, progress=progress, should_stop=should_stop)
        payload = result.to_json()
        payload["provenance"] = {"config": config.to_dict(), "seed": settings.seed}
        write_json(output, payload)
        return result, output

    def show(self, result_and_path):
        result, output = result_and_path
        self.result = result
        x, y, size = result.roi
        metadata = {"calibration": result.to_json(), "file": str(output)}
        self._viewer.add_image(result.reference_experimental, name="I_e (experiment)", translate=(y, x), metadata=metadata)
        self._viewer.add_image(result.reference_synthetic, name="I_s (synthetic)", translate=(y, x + size + 8), metadata=metadata)
        p = result.params
        self._done(f"SSIM {result.ssim:.3f} at N_R={p.N_R:.3f}, N_σ={p.N_sigma:.3f}, γ={p.gamma:.3f}{' (stopped)' if result.stopped else ''} → {output.name}")


class GenerateWidget(_StepWidget):
    """Synthetic training groups into a data set folder, with a preview of one group."""

    title = "synthetic data"

    def __init__(self, napari_viewer) -> None:
        self.config = FileEdit(label="config (TOML, empty = default)", name="config", filter="*.toml", value="")
        self.calibration = FileEdit(label="calibration JSON (empty = none)", name="calibration", filter="*.json", value="")
        self.groups = SpinBox(label="groups", name="groups", value=256, min=2, max=100000)
        self.layout_kind = ComboBox(label="planes", name="layout_kind", choices=["stack", "layers"], value="stack",
                                    tooltip="stack: the reconstruction planes plus context (focus formulation); layers: one plane per simulated layer (the seed's)")
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1)
        self.output = FileEdit(label="data set folder", name="output", mode="d", value="lbs-data")
        super().__init__(napari_viewer, [self.config, self.calibration, self.groups, self.layout_kind, self.seed, self.output])

    def problem(self):
        return _missing(self.calibration, "calibration") or _config_problem(self.config)

    def prepare(self):
        path = _chosen(self.calibration)
        calibration = json.loads(path.read_text()) if path is not None else None
        processing = InputProcessing.from_calibration(calibration) if calibration else InputProcessing()
        layout = DatasetLayout(kind=self.layout_kind.value)
        return _config_from(self.config), processing, layout, calibration, self.groups.value, self.seed.value, Path(self.output.value)

    def work(self, job, *, progress, should_stop, report):
        config, processing, layout, calibration, groups, seed, output = job
        return generate_dataset(output, config, groups=groups, processing=processing, layout=layout, calibration=calibration, seed=seed, progress=progress, should_stop=should_stop)

    def show(self, dataset):
        if dataset.groups:
            inputs, labels, _ = dataset.read_group(dataset.groups[0])
            pixel = dataset.config.optics.pixel_um
            planes = dataset.planes_um
            step = planes[1] - planes[0] if len(planes) > 1 else 1.0
            common = {"scale": (step, pixel, pixel), "translate": (planes[0], 0.0, 0.0), "metadata": {"dataset": str(dataset.path), "spec": dataset.spec}}
            self._viewer.add_image(inputs.astype(np.float32), name="training input (group 0)", **common)
            self._viewer.add_image(labels, name="training label (group 0)", colormap="magenta", blending="additive", **common)
        state = "complete" if dataset.complete else "stopped; run again to resume"
        self._done(f"{len(dataset.groups)} groups in {dataset.path} ({state})")


class TrainingWidget(_StepWidget):
    """Train the U-Net on a data set folder; live loss and validation plot; Stop keeps the best."""

    title = "training"

    def __init__(self, napari_viewer) -> None:
        self.data = FileEdit(label="data set folder", name="data", mode="d", value="lbs-data")
        self.output = FileEdit(label="model file", name="output", mode="w", filter="*.pt", value="lbs-model.pt")
        self.formulation = ComboBox(label="formulation", name="formulation", choices=["focus", "seed"], value="focus",
                                    tooltip="focus: context planes in, centre probability + depth offset + diameter out; seed: the seed paper's single-plane U-Net")
        self.preset = ComboBox(label="preset", name="preset", choices=["small", "medium", "paper"], value="small")
        self.epochs = SpinBox(label="epochs", name="epochs", value=10, min=1, max=10000)
        self.minutes = FloatSpinBox(label="time budget (min, 0 = none)", name="minutes", value=0.0, min=0.0, max=10000.0)
        self.learning_rate = FloatSpinBox(label="learning rate (0 = preset's)", name="learning_rate", value=0.0, min=0.0, max=0.1, step=1e-4)
        self.device = ComboBox(label="device", name="device", choices=["auto", "cpu", "cuda"], value="auto")
        self.foreground_weight = FloatSpinBox(label="foreground weight (seed)", name="foreground_weight", value=30.0, min=1.0, max=1000.0)
        self.patch = SpinBox(label="patch size (0 = tiles)", name="patch", value=0, min=0, max=8192)
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1)
        super().__init__(napari_viewer, [self.data, self.output, self.formulation, self.preset, self.epochs, self.minutes, self.learning_rate, self.device, self.foreground_weight, self.patch, self.seed])
        self._plot = _LossPlot()
        self.native.layout().addWidget(self._plot.canvas)
        self.result = None

    def problem(self):
        try:
            dataset = open_dataset(self.data.value)
        except InputError as error:
            return str(error)
        if self.formulation.value == "focus" and dataset.layout.kind != "stack":
            return "data set: made with the layers layout; the focus formulation needs the stack layout (or choose the seed formulation)"
        if not str(self.output.value).endswith(".pt"):
            return "model file: expected a name ending in .pt"
        return None

    def prepare(self):
        from napari_lbs._core import TrainingSettings

        self._plot.clear()
        settings = TrainingSettings(
            formulation=self.formulation.value,
            preset=self.preset.value,
            epochs=self.epochs.value,
            minutes=self.minutes.value,
            learning_rate=self.learning_rate.value or None,
            device=self.device.value,
            foreground_weight=self.foreground_weight.value,
            patch_size=self.patch.value,
            seed=self.seed.value,
        )
        return Path(self.data.value), Path(self.output.value), settings

    def work(self, job, *, progress, should_stop, report):
        from napari_lbs._core import train_model

        data, output, settings = job
        return train_model(data, output, settings=settings, progress=progress, should_stop=should_stop, report=report)

    def report_received(self, record) -> None:
        self._plot.add(record)

    def show(self, result):
        self.result = result
        best = result.log["best"]
        self._done(f"best epoch {best['epoch']}: validation JI {best['score'][0]:.3f}, ER {100 * best['score'][1]:.1f} %{' (stopped)' if result.stopped else ''} → {result.model_path.name}")


class _LossPlot:
    """Training loss per batch and validation JI per epoch, redrawn as records arrive."""

    def __init__(self) -> None:
        from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
        from matplotlib.figure import Figure

        figure = Figure(figsize=(3.5, 2.2), tight_layout=True)
        self.canvas = FigureCanvasQTAgg(figure)
        self.loss_axes = figure.add_subplot(111)
        self.ji_axes = self.loss_axes.twinx()
        self.clear()

    def clear(self) -> None:
        self.batches, self.epochs = [], []
        self._draw()

    def add(self, record: dict) -> None:
        if "loss" in record:
            self.batches.append(record["loss"])
        if "validation" in record:
            self.epochs.append((len(self.batches), record["validation"]["ji"]))
        self._draw()

    def _draw(self) -> None:
        self.loss_axes.clear()
        self.ji_axes.clear()
        self.loss_axes.set_xlabel("batch")
        self.loss_axes.set_ylabel("loss")
        self.ji_axes.set_ylabel("validation JI")
        if self.batches:
            self.loss_axes.semilogy(np.arange(1, len(self.batches) + 1), self.batches, lw=0.8)
        if self.epochs:
            x, y = zip(*self.epochs, strict=True)
            self.ji_axes.plot(x, y, "o-", color="tab:orange")
            self.ji_axes.set_ylim(0, 1)
        self.canvas.draw_idle()


def particles_layer_data(table: dict) -> tuple[np.ndarray, dict]:
    """Points data ``(z, y, x)`` in µm and the ``features`` table of a particle table."""
    data = np.stack([table["z_um"], table["y_um"], table["x_um"]], axis=1) if len(table["x_um"]) else np.zeros((0, 3))
    features = {"diameter_um": np.asarray(table["diameter_um"], float), "z_um": np.asarray(table["z_um"], float)}
    features["score"] = np.asarray(table["score"], float) if "score" in table else np.ones(len(data))
    return data, features


class PredictionWidget(_StepWidget):
    """Hologram + model → Points layer (z, y, x in µm) with diameter, depth and score; optional scoring."""

    title = "prediction"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram")
        self.model = FileEdit(label="model file", name="model", filter="*.pt", value="lbs-model.pt")
        self.config = FileEdit(label="config (empty = the model's)", name="config", filter="*.toml", value="")
        self.device = ComboBox(label="device", name="device", choices=["auto", "cpu", "cuda"], value="auto")
        self.reference = FileEdit(label="reference CSV (optional)", name="reference", filter="*.csv", value="")
        super().__init__(napari_viewer, [self.hologram, self.model, self.config, self.device, self.reference])

    def problem(self):
        problem = _hologram_problem(self.hologram.value)
        if problem:
            return problem
        if not Path(self.model.value).is_file():
            return f"model: {self.model.value} not found"
        return _missing(self.reference, "reference") or _config_problem(self.config)

    def prepare(self):
        config = load_config(_chosen(self.config)) if _chosen(self.config) is not None else None
        reference = read_particles(_chosen(self.reference)) if _chosen(self.reference) is not None else None
        return _hologram_data(self.hologram.value), Path(self.model.value), config, self.device.value, reference, self.hologram.value.name

    def work(self, job, *, progress, should_stop, report):
        from napari_lbs._core import predict_particles

        hologram, model, config, device, reference, name = job
        result = predict_particles(hologram, model, config, device=device, progress=progress, should_stop=should_stop)
        return result, reference, name

    def show(self, outcome):
        result, reference, name = outcome
        data, features = particles_layer_data(result.particles)
        metadata = {"provenance": result.provenance, "source": name}
        colours = np.tile(np.array([[0.0, 0.9, 1.0, 1.0]]), (len(data), 1))
        message = f"{len(data)} particles in {result.seconds:.1f} s"
        if reference is not None:
            metrics = score_particles(result.particles, reference)
            matched = match_particles(result.particles, reference)
            colours[:] = (1.0, 0.2, 0.2, 1.0)  # false positives red, true positives green
            for p, _ in matched:
                colours[p] = (0.2, 1.0, 0.2, 1.0)
            missed = sorted(set(range(len(reference["x_um"]))) - {t for _, t in matched})
            if missed:
                missed_data, missed_features = particles_layer_data({k: np.asarray(v)[missed] for k, v in reference.items() if k in ("x_um", "y_um", "z_um", "diameter_um")})
                self._viewer.add_points(missed_data, features=missed_features, size=missed_features["diameter_um"], name="missed (FN)", face_color="transparent", border_color="yellow", out_of_slice_display=True)
            metadata["metrics"] = metrics
            message += f"; ER {100 * metrics['er']:.1f} %, JI {metrics['ji']:.3f} (one-to-one)"
        self._viewer.add_points(
            data,
            features=features,
            size=features["diameter_um"] if len(data) else 10.0,
            face_color="transparent",
            border_color=colours if len(data) else "cyan",
            border_width=0.15,
            out_of_slice_display=True,
            name=f"{name} particles",
            metadata=metadata,
        )
        self._done(message)


class DiagnosisWidget(_StepWidget):
    """Sim-to-real gap diagnosis of a hologram: where it lies (map over the hologram), which effect, how much."""

    title = "gap diagnosis"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram")
        self.config = FileEdit(label="config (TOML, empty = default)", name="config", filter="*.toml", value="")
        self.tile = SpinBox(label="tile (px, 0 = tile.size)", name="tile", value=0, min=0, max=8192)
        self.sim_tiles = SpinBox(label="simulated tiles", name="sim_tiles", value=8, min=2, max=256)
        self.evaluations = SpinBox(label="evaluations per fit", name="evaluations", value=40, min=5, max=10000)
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1)
        self.output = FileEdit(label="report folder", name="output", mode="d", value="lbs-diagnosis")
        super().__init__(napari_viewer, [self.hologram, self.config, self.tile, self.sim_tiles, self.evaluations, self.seed, self.output])
        self.diagnosis = None

    def problem(self):
        problem = _hologram_problem(self.hologram.value) or _config_problem(self.config)
        if problem:
            return problem
        size = self.tile.value or _config_from(self.config).tile.size
        rows, cols = self.hologram.value.data.shape[:2]
        if (rows // size) * (cols // size) < 4:
            return f"tile: {size}-pixel tiles give fewer than 4 tiles of the {rows}x{cols} hologram; choose a smaller tile"
        return None

    def prepare(self):
        from napari_lbs._core import DiagnosisSettings

        settings = DiagnosisSettings(sim_tiles=self.sim_tiles.value, evaluations=self.evaluations.value, seed=self.seed.value)
        layer = self.hologram.value
        return _hologram_data(layer), _config_from(self.config), self.tile.value or None, settings, Path(self.output.value), layer

    def work(self, job, *, progress, should_stop, report):
        from napari_lbs._core import diagnose_hologram, write_report

        hologram, config, tile, settings, output, layer = job
        diagnosis = diagnose_hologram(hologram, config, tile_px=tile, settings=settings, progress=progress, should_stop=should_stop)
        write_report(diagnosis, output, provenance={"source": layer.name, "config": config.to_dict(), "seed": settings.seed})
        return diagnosis, output, layer, tile or config.tile.size

    def show(self, outcome):
        diagnosis, output, layer, size = outcome
        self.diagnosis = diagnosis
        report = diagnosis.report
        rows, cols = layer.data.shape[0] // size, layer.data.shape[1] // size
        where = np.asarray(report["gap"]["by_region"], np.float32).reshape(rows, cols)
        scale = tuple(np.asarray(layer.scale[-2:]) * size)
        self._viewer.add_image(where, name="gap by region", scale=scale, translate=tuple(np.asarray(layer.translate[-2:]) + (np.asarray(scale) - np.asarray(layer.scale[-2:])) / 2), colormap="magma", opacity=0.45, blending="additive", metadata={"report": report, "folder": str(output)})
        verdict = report["verdict"]
        self._done(f"gap {report['gap']['baseline']:.2f}; verdict {verdict['id'] or 'nothing missing'} (shrink {100 * verdict['shrink']:.0f} %) → {output / 'report.md'}")
