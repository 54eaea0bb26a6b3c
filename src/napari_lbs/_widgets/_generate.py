"""Step 3: synthetic training groups into a data set folder, with a preview of one group."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from magicgui.widgets import ComboBox, SpinBox

from napari_lbs._core import DatasetLayout, InputProcessing, generate_dataset
from napari_lbs._layers import UNITS, PlaneGrid
from napari_lbs._widgets._backprop import CONFIG_TOOLTIP
from napari_lbs._widgets._base import StepWidget, config_from, config_problem, doc_of, missing, output_problem, path_edit

__all__ = ["GenerateWidget"]


class GenerateWidget(StepWidget):
    """Synthetic training groups into a data set folder, with a preview of one group."""

    title = "synthetic data"

    def __init__(self, napari_viewer) -> None:
        self.config = path_edit(label="config", name="config", placeholder="empty: the defaults", filter="*.toml", tooltip=CONFIG_TOOLTIP)
        self.calibration = path_edit(label="calibration", name="calibration", placeholder="empty: none", filter="*.json",
                                     tooltip=f"{doc_of(generate_dataset, 'processing')} From Calibration's JSON; empty: the seed's normal simulation")
        self.groups = SpinBox(label="groups", name="groups", value=256, min=2, max=100000, tooltip=doc_of(generate_dataset, "groups"))
        self.layout_kind = ComboBox(label="planes", name="layout_kind", choices=["stack", "layers"], value="stack",
                                    tooltip="stack: the reconstruction planes plus context (focus formulation); layers: one plane per simulated layer (the seed's)")
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1, tooltip="Seeds the particle fields and the noise")
        self.output = path_edit(label="data set folder", name="output", mode="d", value="lbs-data", tooltip=f"{doc_of(generate_dataset, 'out_dir')} Resumable: run again after a Stop")
        super().__init__(napari_viewer, [self.config, self.calibration, self.groups, self.layout_kind, self.seed, self.output])

    def problem(self):
        return missing(self.calibration, "calibration") or config_problem(self.config) or output_problem(self.output, "data set folder", folder=True)

    def prepare(self):
        path = self.calibration.value
        calibration = json.loads(Path(path).read_text()) if path is not None else None
        processing = InputProcessing.from_calibration(calibration) if calibration else InputProcessing()
        layout = DatasetLayout(kind=self.layout_kind.value)
        return config_from(self.config), processing, layout, calibration, self.groups.value, self.seed.value, Path(self.output.value)

    def work(self, job, *, progress, should_stop, report):
        config, processing, layout, calibration, groups, seed, output = job
        return generate_dataset(output, config, groups=groups, processing=processing, layout=layout, calibration=calibration, seed=seed, progress=progress, should_stop=should_stop)

    def show(self, dataset):
        if dataset.groups:
            inputs, labels, _ = dataset.read_group(dataset.groups[0])
            grid = PlaneGrid.of_planes(dataset.planes_um, pixel_um=dataset.config.optics.pixel_um)
            common = {"scale": grid.scale, "translate": grid.translate, "units": UNITS, "metadata": {"dataset": str(dataset.path), "spec": dataset.spec}}
            self._viewer.add_image(inputs.astype(np.float32), name="training input (group 0)", **common)
            self._viewer.add_image(labels, name="training label (group 0)", colormap="magenta", blending="additive", **common)
        state = "complete" if dataset.complete else "stopped; run again to resume"
        self.done(f"{len(dataset.groups)} groups in {dataset.path} ({state})", dataset.path if dataset.groups else None)
