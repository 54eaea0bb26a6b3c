"""Small matplotlib plots that sit in a dock on napari's dark theme."""

from __future__ import annotations

import numpy as np

__all__ = ["ColourBarPlot", "EffectsPlot", "FitnessPlot", "LossPlot", "SizeIndexPlot"]

_BACKGROUND = "#262930"  # napari's dark theme
_FOREGROUND = "#d6d0ce"
_LOSS_COLOUR = "#4fc3f7"
_SCORE_COLOUR = "#ffb74d"


def _dark_canvas(*, height_px: int):
    """A figure canvas and one axes styled for napari's dark theme, at least ``height_px`` tall."""
    from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(3.5, 2.4), facecolor=_BACKGROUND, layout="constrained")
    canvas = FigureCanvasQTAgg(figure)
    canvas.setMinimumHeight(height_px)
    axes = figure.add_subplot(111)
    return canvas, axes


def _style(axes) -> None:
    axes.set_facecolor(_BACKGROUND)
    axes.tick_params(colors=_FOREGROUND, labelsize=8)
    axes.xaxis.label.set_color(_FOREGROUND)
    axes.yaxis.label.set_color(_FOREGROUND)
    for spine in axes.spines.values():
        spine.set_color(_FOREGROUND)


def _legend(axes, handles) -> None:
    legend = axes.legend(handles=handles, loc="upper right", fontsize=7, facecolor=_BACKGROUND, edgecolor=_FOREGROUND, labelcolor=_FOREGROUND)
    legend.get_frame().set_alpha(0.8)


class LossPlot:
    """Training loss per batch and synthetic-validation JI per epoch, redrawn as records arrive."""

    def __init__(self) -> None:
        self.canvas, self.loss_axes = _dark_canvas(height_px=200)
        self.ji_axes = self.loss_axes.twinx()
        self.clear()

    def clear(self) -> None:
        self.batches, self.epochs = [], []
        self._draw()

    def add(self, record: dict) -> None:
        """One record of `train_model`'s ``report`` (a batch's ``loss`` or an epoch's ``validation``)."""
        if "loss" in record:
            self.batches.append(record["loss"])
        if "validation" in record:
            self.epochs.append((len(self.batches), record["validation"]["ji"]))
        self._draw()

    def _draw(self) -> None:
        from matplotlib.ticker import MaxNLocator

        self.loss_axes.clear()
        self.ji_axes.clear()
        for axes in (self.loss_axes, self.ji_axes):
            _style(axes)
        self.loss_axes.set_xlabel("batch", fontsize=8)
        self.loss_axes.set_ylabel("loss", fontsize=8, color=_LOSS_COLOUR)
        self.ji_axes.set_ylabel("JI", fontsize=8, color=_SCORE_COLOUR)
        self.loss_axes.xaxis.set_major_locator(MaxNLocator(integer=True))
        self.ji_axes.set_ylim(0, 1)
        handles = []
        if self.batches:
            handles += self.loss_axes.semilogy(np.arange(1, len(self.batches) + 1), self.batches, lw=0.8, color=_LOSS_COLOUR, label="training loss (per batch)")
        if self.epochs:
            x, y = zip(*self.epochs, strict=True)
            handles += self.ji_axes.plot(x, y, "o-", color=_SCORE_COLOUR, label="validation JI (per epoch)")
        if handles:
            _legend(self.ji_axes, handles)
        self.canvas.draw_idle()


class FitnessPlot:
    """Calibration progress: generations done, then the best ``1 - SSIM`` per generation of the run."""

    def __init__(self) -> None:
        self.canvas, self.axes = _dark_canvas(height_px=170)
        self.show_history([])

    def show_history(self, history: list[dict]) -> None:
        """Plot a calibration's ``history`` (``generation``, ``best_fitness`` and ``run`` per record)."""
        from matplotlib.ticker import MaxNLocator

        self.axes.clear()
        _style(self.axes)
        self.axes.set_xlabel("generation", fontsize=8)
        self.axes.set_ylabel("best 1 − SSIM", fontsize=8)
        self.axes.xaxis.set_major_locator(MaxNLocator(integer=True))
        handles = []
        for run in sorted({record.get("run", 0) for record in history}):
            records = [r for r in history if r.get("run", 0) == run]
            handles += self.axes.plot([r["generation"] for r in records], [r["best_fitness"] for r in records], "o-", ms=3, lw=1, color=_LOSS_COLOUR if run == 0 else None, label=f"run {run + 1}")
        if handles:
            _legend(self.axes, handles)
        self.canvas.draw_idle()


class EffectsPlot:
    """A diagnosis's answer: each effect's held-out z, the selected effects marked, and the level a selection needs."""

    def __init__(self) -> None:
        self.canvas, self.axes = _dark_canvas(height_px=190)
        self.show([], level=0.0)

    def show(self, effects: list, *, level: float) -> None:
        """Bars of each effect's ``z`` (a report's ``effects``, best first; selected ones in the score colour) and the ``level``; a note before a run."""
        self.axes.clear()
        _style(self.axes)
        if not effects:
            self.axes.text(0.5, 0.5, "each effect's held-out z shows here after a run", ha="center", va="center", fontsize=8, color=_FOREGROUND,
                           transform=self.axes.transAxes)
            self.axes.set_xticks([])
            self.axes.set_yticks([])
            self.canvas.draw_idle()
            return
        rows = effects[::-1]  # best at the top
        z = [float(e["z"]) if e.get("z") is not None and np.isfinite(e["z"]) else 0.0 for e in rows]
        self.axes.barh([e["id"] for e in rows], z, color=[_SCORE_COLOUR if e["selected"] else _LOSS_COLOUR for e in rows])
        for row, effect in enumerate(rows):
            if effect.get("z") is None:  # no likelihood: the levels of integer counts (quantization), or not fitted
                self.axes.text(0, row, " named from the levels" if effect["selected"] else " no z", va="center", fontsize=7, color=_FOREGROUND)
        self.axes.axvline(level, color=_FOREGROUND, lw=1, ls="--")
        self.axes.set_xlabel(f"held-out z (selected from {level:g}: orange)", fontsize=8)
        self.canvas.draw_idle()


class ColourBarPlot:
    """The labelled colour bar of a map drawn over the hologram (napari's own colour bar has no label)."""

    def __init__(self) -> None:
        self.canvas, self.axes = _dark_canvas(height_px=70)
        self.canvas.figure.set_size_inches(3.5, 0.7)
        self.axes.set_visible(False)

    def show(self, *, label: str, limits: tuple[float, float], colormap: str) -> None:
        """Draw the bar of ``colormap`` over ``limits`` with ``label`` under it."""
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        self.axes.clear()
        self.axes.set_visible(True)
        bar = self.canvas.figure.colorbar(ScalarMappable(Normalize(*limits), colormap), cax=self.axes, orientation="horizontal")
        bar.set_label(label, fontsize=8, color=_FOREGROUND)
        bar.outline.set_edgecolor(_FOREGROUND)
        self.axes.tick_params(colors=_FOREGROUND, labelsize=8)
        self.canvas.draw_idle()


class SizeIndexPlot:
    """Refined particles' diameter against index contrast: one material is one cluster (debris lie apart), the declared material's band shaded."""

    def __init__(self) -> None:
        self.canvas, self.axes = _dark_canvas(height_px=190)
        self.show(None)

    def show(self, particles: dict | None, *, others: dict | None = None, material: dict | None = None) -> None:
        """Plot a refined table's ``diameter_um`` and ``index_contrast`` (± ``index_err``); ``others``: the particles of another material than ``material``."""
        self.axes.clear()
        _style(self.axes)
        self.axes.set_xlabel("diameter (µm)", fontsize=8)
        self.axes.set_ylabel("index contrast n_p − n_m", fontsize=8)
        if particles is None or "index_contrast" not in particles:
            self.axes.text(0.5, 0.5, "refine to measure each particle's size and index", ha="center", va="center", fontsize=8, color=_FOREGROUND,
                           transform=self.axes.transAxes)
            self.canvas.draw_idle()
            return
        if material is not None:
            centre, width = material["index_contrast"], material["tolerance"]
            self.axes.axhspan(centre - width, centre + width, color=_FOREGROUND, alpha=0.12, lw=0)
        handles, shown = [], [] if material is None else [material["index_contrast"] - material["tolerance"], material["index_contrast"] + material["tolerance"]]
        for table, colour, marker, label in ((particles, _LOSS_COLOUR, "o", "particles"), (others, _SCORE_COLOUR, "x", "of another material")):
            if table is None or not len(table["diameter_um"]):
                continue
            diameter, contrast = np.asarray(table["diameter_um"], dtype=float), np.asarray(table["index_contrast"], dtype=float)
            error = np.nan_to_num(np.asarray(table["index_err"], dtype=float), nan=0.0, posinf=0.0)
            handles.append(self.axes.errorbar(diameter, contrast, yerr=error, fmt=marker, ms=3, lw=0.6, color=colour, label=f"{len(diameter)} {label}"))
            shown += contrast[np.isfinite(contrast)].tolist()
        if shown:  # the values, not the widest error bar, set the scale
            low, high = min(shown), max(shown)
            margin = 0.05 + 0.1 * (high - low)
            self.axes.set_ylim(low - margin, high + margin)
        if handles:
            _legend(self.axes, handles)
        else:
            self.axes.text(0.5, 0.5, "no particle kept by the fit", ha="center", va="center", fontsize=8, color=_FOREGROUND, transform=self.axes.transAxes)
        self.canvas.draw_idle()
