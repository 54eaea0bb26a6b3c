"""Step 3: synthetic training groups into a data set folder, with a preview of one group."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from magicgui.widgets import CheckBox, ComboBox, LineEdit, SpinBox

from napari_lbs._core import DatasetLayout, Distractors, InputError, generate_dataset
from napari_lbs._core.pipeline import GenerateRequest, generate, report_distractors, report_sizes, requested_effects
from napari_lbs._layers import UNITS, PlaneGrid
from napari_lbs._widgets._backprop import CONFIG_TOOLTIP
from napari_lbs._widgets._base import StepWidget
from napari_lbs._widgets._fields import chosen, config_from, config_problem, doc_of, effects_problem, missing, output_problem, path_edit

__all__ = ["GenerateWidget"]

_GAP_UM = 50.0  # between what the viewer shows and the data set's preview, to its right


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
        self.report = path_edit(label="diagnosis report", name="report", placeholder="empty: none", filter="*.json",
                                tooltip="A Gap diagnosis report.json: its verdict's effects with their fitted parameters are added, "
                                        "the small scatterers its scene measured fill the impurities, and its particles' sizes are drawn (as generate --effects-from)")
        self.effects = LineEdit(label="effects", name="effects", value="",
                                tooltip="Effects of the catalog added to every hologram, as on the command line, separated by ';' "
                                        "(the demo's: particle_phase:index_contrast=0.26,transmission=1). Empty: the seed's opaque discs")
        self.impurities = SpinBox(label="impurities per tile", name="impurities", value=0, min=0, max=1000, tooltip=doc_of(Distractors, "impurities_per_tile") + " (the demo: 6)")
        self.neighbours_margin = SpinBox(label="neighbours margin (px)", name="neighbours_margin", value=0, min=0, max=4096, tooltip=doc_of(Distractors, "neighbours_margin_px") + " (the demo: 96)")
        self.measured_sizes = CheckBox(label="particle sizes", text="as the report measured", name="measured_sizes", value=True,
                                       tooltip="With a diagnosis report: particle diameters as its scene measured them, within the config's range "
                                               "(where it fitted ten or more). Off, or without a report: uniform over the config's range")
        self.keep_calibration = CheckBox(label="with a report", text="keep the calibration", name="keep_calibration", value=False,
                                         tooltip=doc_of(GenerateRequest, "keep_calibration") + " (generate --keep-calibration)")
        self.seed = SpinBox(label="seed", name="seed", value=0, min=0, max=2**31 - 1, tooltip="Seeds the particle fields and the noise")
        self.output = path_edit(label="data set folder", name="output", mode="d", value="lbs-data", tooltip=f"{doc_of(generate_dataset, 'out_dir')} Resumable: run again after a Stop")
        super().__init__(napari_viewer, [self.config, self.calibration, self.groups, self.layout_kind, self.report, self.effects, self.impurities, self.neighbours_margin,
                                         self.measured_sizes, self.keep_calibration, self.seed, self.output])
        self.report.changed.connect(self._take_report_distractors)

    def _report_measured(self) -> Distractors:
        """The small scatterers the chosen report's scene measured, for the config's tiles (none without a readable report)."""
        path = chosen(self.report)
        if path is None or not path.is_file():
            return Distractors()
        try:
            return report_distractors(path, config_from(self.config))
        except (InputError, ValueError):  # the status line says what is wrong (problem)
            return Distractors()

    def _take_report_distractors(self, *_) -> None:
        """Fill the impurities and neighbours fields with what the chosen report's scene measured (the user may change them)."""
        if chosen(self.report) is not None and self._report_problem() is None:
            measured = self._report_measured()
            self.impurities.value = measured.impurities_per_tile
            self.neighbours_margin.value = measured.neighbours_margin_px

    def problem(self):
        return (missing(self.calibration, "calibration") or missing(self.report, "diagnosis report") or config_problem(self.config) or self._report_problem()
                or effects_problem(self.effects) or self._impurities_problem() or output_problem(self.output, "data set folder", folder=True))

    def _report_problem(self) -> str | None:
        path = chosen(self.report)
        if path is None:
            return None
        try:
            requested_effects(report_path=path)
            report_distractors(path, config_from(self.config))
            report_sizes(path, config_from(self.config))
        except (InputError, ValueError) as error:  # a malformed report, or a config that config_problem names
            return str(error)
        return None

    def _distractors(self) -> Distractors:
        """The impurities field's count, with the report's measured sizes where it holds the report's count, else the defaults."""
        measured = self._report_measured()
        sizes = ({"impurity_diameter_min_um": measured.impurity_diameter_min_um, "impurity_diameter_max_um": measured.impurity_diameter_max_um}
                 if measured.active and self.impurities.value == measured.impurities_per_tile else {})
        return Distractors(impurities_per_tile=self.impurities.value, neighbours_margin_px=self.neighbours_margin.value, **sizes)

    def _impurities_problem(self) -> str | None:
        distractors = self._distractors()
        smallest, largest_impurity = config_from(self.config).particles.diameter_min_um, distractors.impurity_diameter_max_um
        if self.impurities.value and largest_impurity >= smallest:
            return f"impurities: they are {distractors.impurity_diameter_min_um:g}-{largest_impurity:g} µm, not smaller than the config's particles ({smallest:g} µm); use 0"
        return None

    def prepare(self):
        report = chosen(self.report)
        effects, source = requested_effects(report_path=str(report) if report else None, explicit=[part.strip() for part in self.effects.value.split(";")],
                                            flag=f"{self.effects.label}:")
        distractors = self._distractors()
        config = config_from(self.config)
        sizes = report_sizes(report, config) if report and self.measured_sizes.value else None
        return GenerateRequest(Path(self.output.value), config, groups=self.groups.value, calibration_path=self.calibration.value, effects=effects,
                               effects_source=source, layout=DatasetLayout(kind=self.layout_kind.value), distractors=distractors, sizes=sizes,
                               keep_calibration=self.keep_calibration.value, seed=self.seed.value)

    def work(self, request, *, progress, should_stop, report):
        return generate(request, progress=progress, should_stop=should_stop).value

    def show(self, dataset):
        if dataset.groups:
            inputs, labels, _ = dataset.read_group(dataset.groups[0])
            for layer in [layer for layer in self._viewer.layers if "napari_lbs_preview" in layer.metadata]:  # the last run's
                self._viewer.layers.remove(layer)
            # beside everything shown (the hologram, its particles), never over it
            right = self._viewer.layers.extent.world[1][-1] + _GAP_UM if len(self._viewer.layers) else 0.0
            grid = PlaneGrid.of_planes(dataset.planes_um, pixel_um=dataset.config.optics.pixel_um, origin_um=(0.0, right))
            common = {"scale": grid.scale, "translate": grid.translate, "units": UNITS, "metadata": {"dataset": str(dataset.path), "spec": dataset.spec, "napari_lbs_preview": True}}
            self._viewer.add_image(inputs.astype(np.float32), name="training input (group 0)", **common)
            self._viewer.add_image(labels, name="training label (group 0)", colormap="magenta", blending="additive", **common)
        state = "complete" if dataset.complete else "stopped; run again to resume"
        self.done(f"{len(dataset.groups)} groups in {dataset.path} ({state})", dataset.path if dataset.groups else None)
