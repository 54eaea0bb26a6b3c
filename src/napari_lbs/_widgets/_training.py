"""Step 4: train the U-Net on a data set folder, with a live loss and validation plot."""

from __future__ import annotations

from pathlib import Path

from magicgui.widgets import ComboBox, FloatSpinBox, SpinBox

from napari_lbs._core import InputError, TrainingSettings, open_dataset
from napari_lbs._core.pipeline import TrainRequest, train
from napari_lbs._widgets._base import StepWidget
from napari_lbs._widgets._fields import doc_of, output_problem, path_edit, replacing
from napari_lbs._widgets._plots import LossPlot

__all__ = ["TrainingWidget"]


class TrainingWidget(StepWidget):
    """Train the U-Net on a data set folder; live loss and validation plot; Stop keeps the best."""

    title = "training"

    def __init__(self, napari_viewer) -> None:
        def tip(name: str) -> str:
            return doc_of(TrainingSettings, name)

        self.data = path_edit(label="data set folder", name="data", mode="d", value="lbs-data", tooltip="A data set folder from Synthetic data (dataset.json inside)")
        self.output = path_edit(label="model file", name="output", mode="w", filter="*.pt", value="lbs-model.pt", tooltip="The model file (.pt); the training log goes beside it as .json. Prediction reads it")
        self.formulation = ComboBox(label="formulation", name="formulation", choices=["focus", "seed"], value="focus",
                                    tooltip="focus: context planes in, centre probability + depth offset + diameter out; seed: the seed paper's single-plane U-Net")
        self.preset = ComboBox(label="preset", name="preset", choices=["small", "medium", "paper"], value="small", tooltip="Network size: small and medium train on a CPU; paper is the seed paper's U-Net")
        self.epochs = SpinBox(label="epochs", name="epochs", value=10, min=1, max=10000, tooltip="Passes over the training groups")
        self.minutes = FloatSpinBox(label="minutes (0: no limit)", name="minutes", value=0.0, min=0.0, max=10000.0, tooltip=tip("minutes"))
        self.learning_rate = FloatSpinBox(label="learning rate (0: preset)", name="learning_rate", value=0.0, min=0.0, max=0.1, step=1e-4, tooltip=tip("learning_rate"))
        self.device = ComboBox(label="device", name="device", choices=["auto", "cpu", "cuda"], value="auto", tooltip="auto: CUDA when available, else the CPU")
        self.foreground_weight = FloatSpinBox(label="foreground weight (seed)", name="foreground_weight", value=30.0, min=1.0, max=1000.0, tooltip=tip("foreground_weight"))
        self.patch = SpinBox(label="patch px (0: tile)", name="patch", value=0, min=0, max=8192, tooltip=tip("patch_size"))
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1, tooltip=tip("seed"))
        self.average_last = SpinBox(label="average last epochs (0: best)", name="average_last", value=0, min=0, max=10000, tooltip=tip("average_last"))
        super().__init__(napari_viewer, [self.data, self.output, self.formulation, self.preset, self.epochs, self.minutes, self.learning_rate, self.device, self.foreground_weight,
                                         self.patch, self.seed, self.average_last])
        self._plot = LossPlot()
        self.add_view(self._plot.canvas)
        self.result = None

    def problem(self):
        if self.data.value is None:
            return "data set folder: choose one (Synthetic data writes it)"
        try:
            dataset = open_dataset(self.data.value)
        except InputError as error:
            return str(error)
        if self.formulation.value == "focus" and dataset.layout.kind != "stack":
            return "data set: made with the layers layout; the focus formulation needs the stack layout (or choose the seed formulation)"
        return output_problem(self.output, "model file", suffix=".pt")

    def budget_seconds(self):
        return 60.0 * self.minutes.value or None

    def prepare(self):
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
            average_last=self.average_last.value,
        )
        request = TrainRequest(Path(self.data.value), Path(self.output.value), settings=settings)
        # the model, its log and resume state are replaced only once `caution` is confirmed
        return TrainRequest(request.data, request.out_path, settings=settings, replace=replacing(request.outputs()) is not None)

    def caution(self, job):
        return replacing(job.outputs())

    def work(self, job, *, progress, should_stop, report):
        return train(job, progress=progress, should_stop=should_stop, report=report).value

    def report_received(self, record) -> None:
        self._plot.add(record)

    def show(self, result):
        self.result = result
        best = result.log["best"]
        ended = f" ({result.log['stop_reason']})" if result.stopped else ""
        kept = f"mean of epochs {best['averaged_epochs'][0]}–{best['averaged_epochs'][-1]}" if best.get("averaged_epochs") else f"best epoch {best['epoch']}"
        self.done(f"{kept}: validation JI {best['score'][0]:.3f}, ER {100 * best['score'][1]:.1f} %{ended} → {result.model_path.name}", result.model_path)
