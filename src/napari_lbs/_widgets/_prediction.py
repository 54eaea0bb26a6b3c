"""Step 5: hologram + model → a Points layer of particles on the reconstruction planes (µm)."""

from __future__ import annotations

import numpy as np
from magicgui.widgets import CheckBox, ComboBox, create_widget

from napari_lbs._core import match_particles, predict_particles, read_particles, score_particles
from napari_lbs._core._pipeline import refined_prediction
from napari_lbs._layers import PlaneGrid, particle_points
from napari_lbs._widgets._backprop import HOLOGRAM_TOOLTIP
from napari_lbs._widgets._base import StepWidget, chosen, config_problem, doc_of, hologram_data, hologram_problem, missing, model_config, model_problem, path_edit
from napari_lbs._widgets._setup import model_setup

__all__ = ["PredictionWidget"]

_MATCH = "match"
_FOUND = (0.0, 0.9, 1.0, 1.0)  # cyan, without a reference
_TRUE_POSITIVE = (0.2, 1.0, 0.2, 1.0)
_FALSE_POSITIVE = (1.0, 0.2, 0.2, 1.0)


class PredictionWidget(StepWidget):
    """Hologram + model → Points layer (z, y, x in µm) with diameter, depth and score; optional scoring."""

    title = "prediction"

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram", options={"tooltip": HOLOGRAM_TOOLTIP})
        self.model = path_edit(label="model file", name="model", filter="*.pt", value="lbs-model.pt", tooltip=doc_of(predict_particles, "model"))
        self.config = path_edit(label="config", name="config", placeholder="empty: the model's", filter="*.toml", tooltip=doc_of(predict_particles, "config"))
        self.device = ComboBox(label="device", name="device", choices=["auto", "cpu", "cuda"], value="auto", tooltip="auto: CUDA when available, else the CPU")
        self.refine = CheckBox(label="refine", text="Lorenz-Mie fit of every detection", name="refine", value=False,
                               tooltip="Fit every detection with the exact scattering of a sphere (in water): depth, diameter, index contrast, "
                                       "absorption and their uncertainties as features (colour by them); the network proposes down to 0.8 of "
                                       "its threshold and the fit keeps the particles (docs/refinement.md)")
        self.reference = path_edit(label="truth CSV", name="reference", placeholder="optional", filter="*.csv",
                                   tooltip="A true particle table: predictions are then coloured true (green) / false (red) positives, misses shown, ER and JI reported")
        self._points = None  # the last result's layer and its match colours
        self._match_colours = None
        self.colour_by = ComboBox(label="colour by", name="colour_by", choices=self._colour_choices, value=_MATCH,
                                  tooltip="The particles' rims: match (found cyan; with a truth CSV true green, false red) or a feature of the table, low to high (viridis)")
        super().__init__(napari_viewer, [self.hologram, self.model, self.config, self.device, self.refine, self.reference, self.colour_by])
        self.colour_by.changed.connect(self._recolour)

    def problem(self):
        return model_problem(self.model) or hologram_problem(self.hologram.value) or missing(self.reference, "reference") or config_problem(self.config)

    def prepare(self):
        layer = self.hologram.value
        config, warning = model_setup(chosen(self.model), model_config(self.config), layer)
        reference = read_particles(chosen(self.reference)) if chosen(self.reference) is not None else None
        return hologram_data(layer), chosen(self.model), config, warning, self.device.value, self.refine.value, reference, layer.name, tuple(layer.translate[-2:])

    def caution(self, job):
        return job[3]

    def work(self, job, *, progress, should_stop, report):
        hologram, model, config, warning, device, refine, reference, name, origin = job
        result = (refined_prediction if refine else predict_particles)(hologram, model, config, device=device, force=warning is not None, progress=progress,
                                                                        should_stop=should_stop)
        return result, reference, name, origin

    def show(self, outcome):
        result, reference, name, origin = outcome
        grid = PlaneGrid.of_provenance(result.provenance, origin_um=origin)
        data, keywords = particle_points(result.particles, grid)
        metadata = {"provenance": result.provenance, "source": name}
        colours = np.tile(np.array([_FOUND]), (len(data), 1))
        message = f"{len(data)} particles in {result.seconds:.1f} s" + (" (refined: colour by index_contrast, z_err_um, ...)" if "refine" in result.provenance else "")
        if reference is not None:
            metrics = score_particles(result.particles, reference)
            matched = match_particles(result.particles, reference)
            colours[:] = _FALSE_POSITIVE
            for p, _ in matched:
                colours[p] = _TRUE_POSITIVE
            missed = sorted(set(range(len(reference["x_um"]))) - {t for _, t in matched})
            if missed:
                missed_data, missed_keywords = particle_points({k: np.asarray(reference[k])[missed] for k in ("x_um", "y_um", "z_um", "diameter_um")}, grid)
                self._viewer.add_points(missed_data, **missed_keywords, name="missed (FN)", border_color="yellow", border_width=0.15, metadata={"source": "reference"})
            metadata["metrics"] = metrics
            message += f"; ER {100 * metrics['er']:.1f} %, JI {metrics['ji']:.3f} (one-to-one)"
        self._points = self._viewer.add_points(data, **keywords, border_color=colours if len(data) else "cyan", border_width=0.15, name=f"{name} particles", metadata=metadata)
        self._match_colours = colours
        self.colour_by.reset_choices()
        self._recolour()
        self.done(message)

    def _colour_choices(self, *_) -> list[str]:
        """match, then the last result's numeric features."""
        layer = self._points
        features = layer.features if layer is not None else {}
        return [_MATCH, *[column for column in features if features[column].dtype.kind in "iuf"]]

    def _recolour(self, *_) -> None:
        """Colour the last result's rims as `colour_by` says."""
        layer = self._points
        if layer is None or layer not in self._viewer.layers or not len(layer.data):
            return
        if self.colour_by.value in layer.features.columns:
            layer.border_colormap = "viridis"
            layer.border_color = self.colour_by.value
        else:
            layer.border_color = self._match_colours
