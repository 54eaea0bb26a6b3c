"""Step 5: hologram + model → a Points layer of particles on the reconstruction planes (µm)."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from magicgui.widgets import CheckBox, ComboBox, LineEdit, create_widget

from napari_lbs._core import InputError, load_model, match_particles, predict_particles, read_particles, score_particles
from napari_lbs._core.refine import MATERIAL_SIGMAS, MATERIAL_TOLERANCE
from napari_lbs._core.pipeline import refined_prediction
from napari_lbs._layers import PlaneGrid, particle_points, show_every_depth
from napari_lbs._widgets._backprop import HOLOGRAM_TOOLTIP
from napari_lbs._widgets._base import StepWidget
from napari_lbs._widgets._fields import chosen, config_problem, doc_of, hologram_data, hologram_problem, missing, model_config, model_problem, path_edit
from napari_lbs._widgets._plots import SizeIndexPlot
from napari_lbs._widgets._setup import model_setup

__all__ = ["PredictionWidget"]

_MATCH = "match"
_FOUND = (0.0, 0.9, 1.0, 1.0)  # cyan, without a reference
_TRUE_POSITIVE = (0.2, 1.0, 0.2, 1.0)
_FALSE_POSITIVE = (1.0, 0.2, 0.2, 1.0)


class PredictionWidget(StepWidget):
    """Hologram + model → Points layer (z, y, x in µm) with diameter, depth and score; optional scoring."""

    title = "prediction"
    transient = ("colour_by",)  # the last result's features

    def __init__(self, napari_viewer) -> None:
        import napari

        self.hologram = create_widget(annotation=napari.layers.Image, label="hologram", name="hologram", options={"tooltip": HOLOGRAM_TOOLTIP})
        self.model = path_edit(label="model file", name="model", filter="*.pt", value="lbs-model.pt", tooltip=doc_of(predict_particles, "model"))
        self.config = path_edit(label="config", name="config", placeholder="empty: the model's", filter="*.toml", tooltip=doc_of(predict_particles, "config"))
        self.device = ComboBox(label="device", name="device", choices=["auto", "cpu", "cuda"], value="auto", tooltip="auto: CUDA when available, else the CPU")
        self.refine = CheckBox(label="refine", text="Lorenz-Mie fit of every detection", name="refine", value=False,
                               tooltip="Fit every detection with the exact scattering of a sphere (in water): depth, diameter, index contrast, "
                                       "absorption and their uncertainties as features (colour by them); the network proposes down to 0.8 of "
                                       "its threshold and the fit keeps the particles, then it looks again in what the fit leaves unexplained "
                                       "(docs/refinement.md). The fits run in worker processes (one per core) that start by importing the script "
                                       "napari was started from, if any: such a script must keep its code under if __name__ == \"__main__\":, "
                                       "else each worker runs it again (a new viewer per worker)")
        self.material = LineEdit(label="material n_p − n_m", name="material", value="",
                                 tooltip="Optional, with refine: the sample's index contrast (polystyrene in water: 0.26). Every fit starts there, and the "
                                         f"particles whose fitted index contrast differs by more than {MATERIAL_TOLERANCE:g} and {MATERIAL_SIGMAS:g} standard "
                                         "deviations (debris) are set apart")
        self.material.native.setPlaceholderText("optional, with refine: e.g. 0.26")
        self.reference = path_edit(label="truth CSV", name="reference", placeholder="optional", filter="*.csv",
                                   tooltip="A true particle table: predictions are then coloured true (green) / false (red) positives, misses shown, ER and JI reported")
        self._points = None  # the last result's layer and its match colours
        self._match_colours = None
        self.colour_by = ComboBox(label="colour by", name="colour_by", choices=self._colour_choices, value=_MATCH,
                                  tooltip="The particles' rims: match (found cyan; with a truth CSV true green, false red) or a feature of the table, low to high (viridis)")
        super().__init__(napari_viewer, [self.hologram, self.model, self.config, self.device, self.refine, self.material, self.reference, self.colour_by])
        self.colour_by.changed.connect(self._recolour)
        self._plot = SizeIndexPlot()
        self.add_view(self._plot.canvas)

    def problem(self):
        return (model_problem(self.model) or hologram_problem(self.hologram.value) or self._size_problem() or missing(self.reference, "reference")
                or config_problem(self.config) or self._material_problem())

    def _size_problem(self) -> str | None:
        """A hologram smaller than the model's tile cannot be predicted: said before Run."""
        layer, path = self.hologram.value, chosen(self.model)
        rows, cols = layer.data.shape[:2] if layer.rgb else layer.data.shape[-2:]
        tile = _model_tile(str(path), path.stat().st_mtime_ns)
        if tile is not None and tile > min(rows, cols):
            return f"hologram: {layer.name!r} is {rows}x{cols} pixels, smaller than the model's {tile}-pixel tile"
        return None

    def _material_problem(self) -> str | None:
        text = self.material.value.strip()
        if not text:
            return None
        try:
            value = float(text)
        except ValueError:
            return f"material: expected the index contrast n_p − n_m as a number (polystyrene in water: 0.26), got {text!r}"
        if not -0.9 <= value <= 2.5:
            return f"material: expected an index contrast between -0.9 and 2.5 (the fit's range), got {value:g}"
        return None if self.refine.value else "material: tick refine (the fit measures each particle's index contrast)"

    def prepare(self):
        layer = self.hologram.value
        config, warning = model_setup(chosen(self.model), model_config(self.config), layer)
        reference = read_particles(chosen(self.reference)) if chosen(self.reference) is not None else None
        material = float(self.material.value) if self.material.value.strip() else None
        return hologram_data(layer), chosen(self.model), config, warning, self.device.value, self.refine.value, material, reference, layer.name, tuple(layer.translate[-2:])

    def caution(self, job):
        return job[3]

    def phase_weights(self, job):
        # a refined prediction's phases and their usual shares of the time (the seed's hologram on 2 cores);
        # the refit runs where the second look found particles, as it does on such holograms
        return {"network": 1.0, "fit": 3.0, "second": 1.5, "refit": 3.0} if job[5] else None

    def work(self, job, *, progress, should_stop, report):
        hologram, model, config, warning, device, refine, material, reference, name, origin = job
        options = {"device": device, "force": warning is not None, "progress": progress, "should_stop": should_stop}
        if refine:
            result = refined_prediction(hologram, model, config, material_index_contrast=material, **options)
        else:
            result = predict_particles(hologram, model, config, **options)
        return result, reference, name, origin

    def show(self, outcome):
        result, reference, name, origin = outcome
        grid = PlaneGrid.of_provenance(result.provenance, origin_um=origin)
        data, keywords = particle_points(result.particles, grid)
        metadata = {"provenance": result.provenance, "source": name}
        colours = np.tile(np.array([_FOUND]), (len(data), 1))
        refined = result.provenance.get("refine")
        gate = refined.get("material") if refined else None
        message = f"{len(data)} particles in {result.seconds:.1f} s"
        if refined:
            apart = f", {gate['other_material']} of another material set apart" if gate else ""
            message += f" (refined, {refined['residual']['found']} found in the fit's residual{apart}: colour by index_contrast, z_err_um, ...)"
        self._plot.show(result.particles if refined else None, others=gate["other_particles"] if gate else None, material=gate)
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
        # every particle drawn over the hologram whatever the plane shown, its rim coloured by its depth (with a truth CSV: by its match)
        self._points = self._viewer.add_points(data, **keywords, border_color=colours if len(data) else "cyan", border_width=0.15, name=f"{name} particles", metadata=metadata)
        show_every_depth(self._viewer, self._points)
        self._match_colours = colours
        self.colour_by.reset_choices()
        self.colour_by.value = _MATCH if reference is not None or not len(data) else "z_um"
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
            values = np.asarray(layer.features[self.colour_by.value], float)
            finite = values[np.isfinite(values)]
            layer.border_colormap = "viridis"
            layer.border_color = self.colour_by.value
            if finite.size:  # this feature's range, not the one coloured by before
                layer.border_contrast_limits = (float(finite.min()), float(finite.max()) if finite.max() > finite.min() else float(finite.min()) + 1.0)
        else:
            layer.border_color = self._match_colours


@functools.lru_cache(maxsize=8)
def _model_tile(path: str, modified_ns: int) -> int | None:
    """The tile size (pixels) of the model file ``path`` as modified at ``modified_ns``; None when it is no model."""
    try:
        return int(load_model(Path(path)).meta["tile_size"])
    except (InputError, KeyError, TypeError, ValueError):
        return None
