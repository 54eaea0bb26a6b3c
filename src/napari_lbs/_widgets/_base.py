"""What every step widget shares: Run/Stop, validation, progress, results, remembered settings.

A step widget collects parameters, runs one `_core` function in napari's ``thread_worker``
(``progress`` relayed to a bar in napari's activity dock and to the widget's own bar with
elapsed time and ETA; ``should_stop`` wired to Stop) and shows the result as µm layers.
A job of several phases (a refined prediction: the network, the fit, the second look) has
one bar over the whole job, each phase named as it begins (`Phases`); a job whose phases have
no expected shares of the time (a diagnosis's frames) shows each phase's name and count, and
no time left. While its inputs are invalid Run is disabled and the reason shown. A step's
last result stays on its status line until it runs again. Settings persist between napari sessions as typed, all fields of a step
as one record, so they come back as the consistent whole they were saved as (an empty path
stays empty; a remembered input that has gone falls back to the default; a record that no
longer fits the fields is not used at all).
"""

from __future__ import annotations

import itertools
import json
import threading
import time
from pathlib import Path

import numpy as np
from magicgui.widgets import CheckBox, ComboBox, Container, FileEdit, FloatSpinBox, LineEdit, ProgressBar, PushButton, SpinBox
from psygnal import Signal
from qtpy.QtCore import QObject, QSettings, Qt
from qtpy.QtCore import Signal as QtSignal
from qtpy.QtWidgets import QFormLayout, QFrame, QLabel, QScrollArea, QVBoxLayout, QWidget

from napari_lbs._core import Stopped
from napari_lbs._layers import prefer_particle_writer
from napari_lbs._widgets._fields import wrapping_label
from napari_lbs._widgets._setup import restore_pixel_size

__all__ = ["StepWidget"]


_FIELDS = "fields"  # QSettings key of a step's remembered fields: one JSON record, written and read whole


class _Relay(QObject):
    """Carries worker-thread callbacks to the GUI thread (queued signals)."""

    progress = QtSignal(int, int, float, str)  # done, total, when (the worker's clock: queued signals may arrive in bursts), phase
    report = QtSignal(object)


def _confirmed(parent, title: str, warning: str) -> bool:
    from qtpy.QtWidgets import QMessageBox

    buttons = QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.Cancel
    answer = QMessageBox.warning(parent, f"{title}: check the setup", f"{warning}\n\nRun anyway?", buttons, QMessageBox.StandardButton.Cancel)
    return answer == QMessageBox.StandardButton.Yes


_RECENT_STEPS = 5  # the ETA's throughput: the median time per step over at least this many latest steps
_RECENT_SHARE = 0.25  # ... and over at least this share of the time elapsed, so a long job's estimate moves slowly


def time_left(marks: list[tuple[float, int]], total: int) -> float | None:
    """Seconds until ``total`` steps at the throughput measured lately, or None before two progress reports.

    ``marks`` are ``(time, done)`` at each report. The throughput is the median time per step
    over the latest steps: at least `_RECENT_STEPS` of them and at least the latest
    `_RECENT_SHARE` of the time elapsed. Recent steps follow a job whose steps change speed
    (prediction's back-propagated planes, then the network's), which an average since the start
    does not; the share of the elapsed time keeps a long job's estimate from jumping with a few
    slow or quick steps (training's validation batches).
    """
    if len(marks) < 2:
        return None
    start = len(marks) - 1 - _RECENT_STEPS
    horizon = marks[-1][0] - _RECENT_SHARE * (marks[-1][0] - marks[0][0])
    while start > 0 and marks[start][0] > horizon:
        start -= 1
    seconds_per_step = [(t1 - t0) / (d1 - d0) for (t0, d0), (t1, d1) in itertools.pairwise(marks[max(start, 0) :]) if d1 > d0]
    if not seconds_per_step:
        return None
    return float(np.median(seconds_per_step)) * max(total - marks[-1][1], 0)


class Phases:
    """The progress of a job made of phases run one after another, as one bar over the whole job.

    The work tells each phase as it begins (``progress.phase(name)``, e.g. "fit 103 particles")
    and counts its steps with ``progress(done, total)`` as usual. ``weights`` give each phase's
    expected share of the time, in the order the phases run, by the first word of a phase's
    name: the bar stands at the finished phases' weight plus the running one's share of its
    own, and the time left is the running phase's (from its throughput, `time_left`) plus the
    phases to come at the seconds per unit of weight the job has taken so far. A phase the job
    skips (the second look when nothing was refined) only ends the bar sooner.
    """

    RESOLUTION = 1000  # the bar's steps over the whole job

    def __init__(self, weights: dict[str, float], started: float) -> None:
        self.weights = dict(weights)
        self.name = ""
        self._started = started
        self._finished_weight = 0.0
        self._marks: list[tuple[float, int]] = []
        self._total = 0

    def _key(self, name: str) -> str:
        return name.split(" ", 1)[0]

    def begin(self, name: str, at: float) -> None:
        """The phase ``name`` begins at ``at`` (the worker's perf_counter)."""
        self._finished_weight += self.weights.get(self._key(self.name), 0.0)
        self.name, self._marks, self._total = name, [(at, 0)], 0

    def step(self, done: int, total: int, at: float) -> None:
        self._marks.append((at, done))
        self._total = total

    def _spent(self) -> float:
        within = min(self._marks[-1][1] / self._total, 1.0) if self._total and self._marks else 0.0
        return self._finished_weight + self.weights.get(self._key(self.name), 0.0) * within

    def fraction(self) -> float:
        """The share of the whole job done."""
        return min(self._spent() / sum(self.weights.values()), 1.0)

    def time_left(self, now: float) -> float | None:
        """Seconds to the end of the whole job, or None before it can be estimated."""
        current = time_left(self._marks, self._total)
        order = list(self.weights)
        later = order[order.index(self._key(self.name)) + 1 :] if self._key(self.name) in order else []
        if current is None or not later or self._spent() <= 0:
            return current
        return current + (now - self._started) / self._spent() * sum(self.weights[name] for name in later)


class _Reporter:
    """The worker's ``progress`` callback: ``(done, total)`` steps, and ``phase(name)`` as a phase begins; relayed with the worker's clock."""

    def __init__(self, emit) -> None:
        self._emit = emit
        self._phase = ""

    def __call__(self, done: int, total: int) -> None:
        self._emit(int(done), int(total), time.perf_counter(), self._phase)

    def phase(self, name: str) -> None:
        self._phase = name
        self._emit(0, 0, time.perf_counter(), name)


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}" if seconds >= 3600 else f"{seconds // 60}:{seconds % 60:02d}"


def _scrolling_form(fields: list) -> QScrollArea:
    """The layout rule of every step: its fields in a vertically scrolling form that never widens the dock.

    A row's field moves under its label when the dock is too narrow for both (a path or a
    text always does), and labels wrap, so the form is as narrow as its widest field (a path
    field with its button);
    plots added later (`StepWidget.add_view`) go below the fields.
    """
    form = QFormLayout()
    form.setRowWrapPolicy(QFormLayout.RowWrapPolicy.WrapLongRows)
    form.setFieldGrowthPolicy(QFormLayout.FieldGrowthPolicy.AllNonFixedFieldsGrow)
    for field in fields:
        if isinstance(field, PushButton) or not field.label:
            form.addRow(field.native)
            continue
        label = QLabel(field.label)
        label.setWordWrap(True)
        label.setToolTip(field.tooltip or "")
        if isinstance(field, (FileEdit, LineEdit)):  # a path or text needs the whole width to be read
            form.addRow(label)
            form.addRow(field.native)
        else:
            form.addRow(label, field.native)
    content = QWidget()
    column = QVBoxLayout(content)
    column.setContentsMargins(4, 4, 4, 4)
    column.addLayout(form)
    column.addStretch(1)
    area = QScrollArea()
    area.setWidgetResizable(True)
    area.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
    area.setFrameShape(QFrame.Shape.NoFrame)
    area.setWidget(content)
    return area


class StepWidget(Container):
    """Shared plumbing of one workflow step (see the module docstring).

    Subclasses define ``title``, the fields, `problem`, `prepare` (GUI thread), `work`
    (worker thread: the one `_core` call) and `show` (GUI thread); `show` calls `done` with
    the result line and, when the step wrote a file the next step reads, its path.
    """

    title = ""
    transient: tuple[str, ...] = ()  # names of fields not remembered between sessions (they describe a result, not a setting)
    produced = Signal(object)  # the path this step just wrote (calibration JSON, data set, model)

    def __init__(self, viewer, fields: list) -> None:
        super().__init__(labels=False)
        self._viewer = viewer
        self._fields = fields
        self._run = PushButton(text="Run", tooltip=f"Run {self.title}")
        self._stop = PushButton(text="Stop", enabled=False, tooltip="Stop at the next step boundary (the partial result is kept where it is meaningful)")
        self._bar = ProgressBar(value=0, min=0, max=1, label="progress")
        self._timing = wrapping_label()
        self._status = wrapping_label()
        self.extend([Container(widgets=[self._run, self._stop], layout="horizontal", labels=False), self._bar, self._timing, self._status])
        self._scroll = _scrolling_form(fields)
        self.native.layout().insertWidget(0, self._scroll, 1)  # above Run/Stop, which stay in view
        self._stop_requested = threading.Event()
        self._worker = None
        self._progress_bar = None
        self._started = 0.0
        self._marks: list[tuple[float, int]] = []  # (time, done) of each progress report: the ETA's throughput
        self._phases: Phases | None = None  # a job of several phases: one bar over them all
        self._described = ""  # the phase napari's activity dock names
        self._budget: float | None = None
        self._counts = ""  # the last "done/total" reported
        self._result_message: str | None = None
        self._outcome: str | None = None
        self._relay = _Relay()
        self._relay.progress.connect(self._on_progress)
        self._relay.report.connect(self._on_report)
        self._run.changed.connect(self._start)
        self._stop.changed.connect(self._request_stop)
        self._restore_settings()
        prefer_particle_writer()  # the particles this step shows save as particle tables
        for widget in fields:
            widget.changed.connect(self._changed)
        viewer.layers.events.inserted.connect(self._layer_inserted)
        viewer.layers.events.removed.connect(self._layers_changed)
        self._revalidate()

    # -- settings and validation --------------------------------------------------------------
    def _settings(self) -> QSettings:
        return QSettings("napari-lbs", type(self).__name__)

    def _persisted(self) -> list:
        """The fields remembered between sessions: every value typed or chosen, not a layer picker nor one listed in ``transient``."""
        return [w for w in self._fields if w.name not in self.transient
                and (isinstance(w, (SpinBox, FloatSpinBox, FileEdit, LineEdit, CheckBox)) or (isinstance(w, ComboBox) and w.choices and isinstance(w.choices[0], str)))]

    def _restore_settings(self) -> None:
        """Put back the fields as they were last saved, all of them or none (a record that does not fit the fields leaves every default)."""
        stored = self._settings().value(_FIELDS)
        try:
            record = json.loads(str(stored)) if stored is not None else {}
        except ValueError:
            return
        if not isinstance(record, dict):
            return
        values = {}
        for widget in self._persisted():
            if widget.name not in record:
                continue
            value = record[widget.name]
            if isinstance(widget, FileEdit):
                # An input (any field but "output") that has gone since is stale: keep the default.
                if not isinstance(value, str):
                    return
                if value and widget.name != "output" and not Path(value).expanduser().exists():
                    continue
            elif isinstance(widget, ComboBox) and value not in widget.choices:
                return
            elif type(value) is not type(widget.value) and not (isinstance(widget, FloatSpinBox) and type(value) is int):
                return
            elif isinstance(widget, (SpinBox, FloatSpinBox)) and not widget.min <= value <= widget.max:
                return
            values[widget] = value
        for widget, value in values.items():
            if isinstance(widget, FileEdit):
                widget.line_edit.value = value
            else:
                widget.value = value

    def _changed(self, *_) -> None:
        record = {widget.name: widget.line_edit.value if isinstance(widget, FileEdit) else widget.value for widget in self._persisted()}
        self._settings().setValue(_FIELDS, json.dumps(record))
        self._revalidate()

    def add_view(self, widget) -> None:
        """Show a Qt ``widget`` (a plot) below the fields, scrolling with them."""
        column = self._scroll.widget().layout()
        column.insertWidget(column.count() - 1, widget)  # above the closing stretch

    def reset_choices(self, *_) -> None:
        """Refresh the layer pickers (the fields live in the scrolling form, not in this container)."""
        for field in self._fields:
            if hasattr(field, "reset_choices"):
                field.reset_choices()

    def _layer_inserted(self, event) -> None:
        from qtpy.QtCore import QTimer

        layer = event.value
        QTimer.singleShot(0, lambda: restore_pixel_size(layer))  # once napari has finished adding it (its canvas visual too)
        self._layers_changed()

    def _layers_changed(self, *_) -> None:
        self.reset_choices()
        self._revalidate()

    def problem(self) -> str | None:
        """Why Run is disabled, or None when the inputs are valid."""
        return None

    def _revalidate(self) -> None:
        if self._worker is not None:
            return
        problem = self.problem()
        self._run.enabled = problem is None
        lines = [problem or ("ready" if self._result_message is None else "")]
        if self._result_message is not None:
            lines.append(self._result_message if problem is None else f"last run: {self._result_message}")
        self._status.value = "\n".join(line for line in lines if line)
        self._status.tooltip = self._status.value

    # -- running --------------------------------------------------------------------------------
    def prepare(self):
        """Read the inputs in the GUI thread (layers are not thread-safe); passed to `work`."""
        return None

    def work(self, job, *, progress, should_stop, report):
        """The `_core` call on `prepare`'s ``job``, run in the worker thread; returns what `show` receives."""
        raise NotImplementedError

    def phase_weights(self, job) -> dict[str, float] | None:
        """For a job of several phases (`Phases`): each phase's expected share of the time, in order, by the first word of its name; None: one phase."""
        return None

    def budget_seconds(self) -> float | None:
        """The run's time budget, which bounds its time left (None: none)."""
        return None

    def caution(self, job) -> str | None:
        """A warning about `prepare`'s ``job`` the user must confirm before it runs (a model for another setup), or None."""
        return None

    def show(self, result) -> None:
        """Show a finished result (GUI thread)."""

    def report_received(self, record) -> None:
        """Handle one record of the running job (GUI thread)."""

    def done(self, message: str, output: Path | None = None) -> None:
        """Record the result line shown until the next run; announce the file the next step reads."""
        self._outcome = message
        if output is not None:
            self.produced.emit(Path(output))

    def _start(self, *_) -> None:
        from napari.qt.threading import thread_worker
        from napari.utils import progress

        if self._worker is not None or self.problem() is not None:
            return
        self._stop_requested.clear()
        self._result_message = self._outcome = None
        self._run.enabled = False
        self._stop.enabled = True
        self._status.value = "running…"
        self._bar.max, self._bar.value = 1, 0
        self._timing.value = self._counts = ""
        self._started = time.perf_counter()
        self._marks = [(self._started, 0)]
        self._budget = self.budget_seconds()
        try:
            job = self.prepare()
        except (ValueError, OSError) as error:
            self._on_errored(error)
            self._on_finished()
            return
        warning = self.caution(job)
        if warning is not None and not _confirmed(self.native, self.title, warning):
            self._outcome = f"not run: {warning}"
            self._on_finished()
            return
        # Made here, before the worker runs: creating it processes events, which must not
        # happen inside a progress callback (the job could finish in between).
        self._progress_bar = progress(total=0, desc=self.title)

        weights = self.phase_weights(job)
        self._phases = Phases(weights, self._started) if weights else None
        self._described = ""

        @thread_worker(connect={"returned": self.show, "errored": self._on_errored, "finished": self._on_finished}, start_thread=False)
        def run():
            return self.work(job, progress=_Reporter(self._relay.progress.emit), should_stop=self._stop_requested.is_set, report=self._relay.report.emit)

        self._worker = run()
        self._worker.start()

    def _request_stop(self, *_) -> None:
        self._stop_requested.set()
        self._stop.enabled = False
        if self._worker is not None:
            self._status.value = "stopping…"

    def _on_progress(self, done: int, total: int, at: float, phase: str) -> None:
        bar = self._progress_bar
        if self._worker is None or bar is None:  # a late signal from a finished job
            return
        phases = self._phases
        if phases is not None:
            if phase != phases.name:
                phases.begin(phase, at)
            if total:
                phases.step(done, total, at)
            maximum, value = Phases.RESOLUTION, round(Phases.RESOLUTION * phases.fraction())
            left = phases.time_left(at)
            self._counts = f"{phase} {done}/{total}" if total else f"{phase}: starting"
        elif total:
            maximum, value = total, min(done, total)
            self._marks.append((at, done))
            # phases without weights restart their counts: their throughputs say nothing of the time left
            left = time_left(self._marks, total) if done < total and not phase else None
            self._counts = f"{phase} {done}/{total}" if phase else f"{done}/{total}"
        else:
            return  # a phase named to a step that shows none
        self._bar.max, self._bar.value = maximum, value
        elapsed = time.perf_counter() - self._started
        eta = f", about {_clock(left)} left" if left is not None else ""
        if self._budget is not None and (left is None or elapsed + left > self._budget):
            eta = f", at most {_clock(max(self._budget - elapsed, 0.0))} left (the time budget ends first)"
        self._timing.value = f"{self._counts}, {_clock(elapsed)} elapsed{eta}"
        if not self._stop_requested.is_set():
            self._status.value = f"{self.title}: running"
        # Last: napari's progress may process events, and with them this job's end.
        if phase and phase != self._described:
            self._described = phase
            bar.set_description(f"{self.title}: {phase}")
            if self._progress_bar is not bar:
                return
        if bar.total != maximum:
            bar.total = maximum
        bar.update(value - bar.n)  # update() emits the value the activity dock shows

    def _on_report(self, record) -> None:
        if self._worker is not None:
            self.report_received(record)

    def _on_errored(self, error: Exception) -> None:
        from napari.utils.notifications import show_error, show_info

        if isinstance(error, Stopped):
            show_info(f"{self.title}: stopped")
            self._outcome = "stopped; nothing was written"
        else:
            show_error(f"{self.title}: {error}")
            self._outcome = f"error: {str(error).splitlines()[0] if str(error) else type(error).__name__}"

    def _on_finished(self) -> None:
        if self._progress_bar is not None:
            self._progress_bar.close()
            self._progress_bar = None
        self._timing.value = f"{self._counts + ', ' if self._counts else ''}took {_clock(time.perf_counter() - self._started)}"
        self._worker = None
        self._stop.enabled = False
        self._result_message, self._outcome = self._outcome, None
        self._revalidate()
