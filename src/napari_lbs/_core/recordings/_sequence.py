"""Recordings: prediction frame by frame on dask, one table for the whole recording.

The frames come from `napari_lbs._core.recordings._frames` (`open_frames`) and are divided by a
background from `napari_lbs._core.recordings._background` (`sequence_background`).

`predict_sequence` runs `predict_particles` on every frame through dask: the local threaded
scheduler by default (one frame per core at a time), a ``LocalCluster`` of ``workers``
processes, or an existing ``dask.distributed`` scheduler. The process that calls it reads the
frames (so workers need not see its files) and keeps at most ``2 x workers`` frames in
flight, so memory stays bounded whatever the frame count. The model is sent once to each
worker and kept there. Every frame's particles are written atomically to a work folder as
they arrive; a run stopped or killed and started again with the same work folder skips the
frames found there.

The table is the same, to the last bit, whatever the scheduler and worker count: frames are
independent, the table is assembled in frame order, and every frame's network runs on one
torch thread — torch's CPU convolutions round differently with their thread count (by
≈ 3e-5 µm in x), so a frame's result must not depend on how many threads its worker has.
Parallelism comes from frames instead (the FFTs still use every core of a worker).
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import shutil
import time
import zipfile
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from napari_lbs import __version__
from napari_lbs._core.recordings._background import BACKGROUND_MODES, choose_background, flat_field, frame_window, frames_median, sequence_background
from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import atomic_path, read_json_object, write_json
from napari_lbs._core.recordings._frames import HologramFrames, open_frames
from napari_lbs._core.foundation import as_hologram
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback, Stopped
from napari_lbs._core.foundation import available_threads, process_threads, run_interruptibly, size_threads
from napari_lbs._core.foundation import InputError

if TYPE_CHECKING:  # for the annotations only: torch is imported when a recording is predicted
    from napari_lbs._core.learning import PredictionSettings

__all__ = ["SequenceResult", "local_cluster", "predict_sequence"]

_WORK_FORMAT = "napari-lbs-sequence-work"
_IN_FLIGHT_PER_WORKER = 2


@dataclass(frozen=True)
class SequenceResult:
    """One particle table for a whole recording and how it was made.

    Attributes
    ----------
    particles : dict of arrays
        `predict_particles` columns plus ``frame`` (int64, 0-based, ascending).
    provenance : dict
        The first frame's provenance (model, decoding, config) plus the recording's sources,
        background, scheduler and timings.
    seconds : float
        Wall time of this call (s).
    resumed : int
        Frames found finished in the work folder (not predicted again).
    """

    particles: dict[str, np.ndarray]
    provenance: dict
    seconds: float
    resumed: int


def _frame_particles(hologram: np.ndarray, model, config: ExperimentConfig, background: np.ndarray | None, settings: PredictionSettings, should_stop: StopCallback | None = None) -> tuple[dict, dict]:
    """One frame's `predict_particles` with ``settings`` (the dask task). ``model`` is the worker's copy, moved to the settings' device on first use; ``should_stop`` (threads of this process only) ends it between planes."""
    from dataclasses import replace

    from napari_lbs._core.learning import resolve_device
    from napari_lbs._core.learning import predict_particles

    size_threads(1)  # the same rounding on every worker (module docstring), and the cores split between frames
    target = resolve_device(settings.device)
    if next(model.network.parameters()).device != target:
        model.network.to(target)
    # predict_sequence checked the model against the config once, before any frame
    result = predict_particles(hologram, model, config, background=background, settings=replace(settings, force=True), should_stop=should_stop)
    return result.particles, result.provenance


class _Work:
    """The work folder of a run: one ``.npz`` per finished frame, the background, the run's identity."""

    def __init__(self, folder: Path | None, identity: dict) -> None:
        self.folder = folder
        self.results: dict[int, dict] = {}  # without a folder
        self.first_provenance: dict | None = None
        self.created = False
        if folder is None:
            return
        manifest = folder / "work.json"
        if manifest.is_file():
            previous = read_json_object(manifest, what="work folder manifest")
            if previous.get("format") != _WORK_FORMAT or previous.get("identity") != json.loads(json.dumps(identity)):
                raise InputError(f"{folder}: holds the frames of another run (other inputs, model or settings); delete it or choose another output")
        else:
            self.created = not folder.exists()
            folder.mkdir(parents=True, exist_ok=True)
            write_json(manifest, {"format": _WORK_FORMAT, "napari_lbs": __version__, "identity": identity})

    def discard_if_refused(self, exc_type, exc, traceback) -> bool:
        """An `ExitStack` exit: a fresh run refused (bad input, a bug) leaves no work folder; a stop or Ctrl-C keeps it to resume, and so does a resumed run."""
        if exc_type is not None and issubclass(exc_type, Exception) and not issubclass(exc_type, Stopped) and self.created:
            shutil.rmtree(self.folder, ignore_errors=True)
        return False

    def finished(self) -> set[int]:
        if self.folder is None:
            return set(self.results)
        return {int(p.stem.split("_")[1]) for p in self.folder.glob("frame_*.npz")}

    def provenance(self, provenance: dict | None = None) -> dict:
        """The provenance of the run's first finished frame (kept in the folder, so a resumed run still has it)."""
        path = None if self.folder is None else self.folder / "provenance.json"
        if self.first_provenance is None and path is not None and path.is_file():
            self.first_provenance = read_json_object(path, what="frame provenance")
        if self.first_provenance is None and provenance is not None:
            self.first_provenance = provenance
            if path is not None:
                write_json(path, provenance)
        return self.first_provenance or {}

    def save(self, index: int, particles: dict) -> None:
        if self.folder is None:
            self.results[index] = particles
            return
        with atomic_path(self.folder / f"frame_{index:07d}.npz") as temporary:
            with open(temporary, "wb") as handle:
                np.savez(handle, **particles)

    def load(self, index: int) -> dict[str, np.ndarray]:
        if self.folder is None:
            return self.results[index]
        path = self.folder / f"frame_{index:07d}.npz"
        try:
            with np.load(path, allow_pickle=False) as data:
                return {name: data[name] for name in data.files}
        except (zipfile.BadZipFile, OSError, ValueError, EOFError) as error:  # written atomically, so damaged after the run
            raise InputError(f"{path}: a damaged finished frame ({type(error).__name__}); delete it to predict that frame again") from None

    def background(self, compute) -> tuple[str, np.ndarray | None, dict]:
        """``(mode, global background or None, measures)``, computed once and kept in the work folder for a resumed run."""
        if self.folder is None:
            return compute()
        path, choice = self.folder / "background.npy", self.folder / "background.json"
        if choice.is_file():
            kept = read_json_object(choice, what="background choice")
            return kept["mode"], np.load(path, allow_pickle=False) if kept["mode"] == "global" else None, kept["measures"]
        mode, background, measures = compute()
        if background is not None:
            with atomic_path(path) as temporary:
                with open(temporary, "wb") as handle:
                    np.save(handle, background)
        write_json(choice, {"mode": mode, "measures": measures})  # after the array: a choice on disk always has its background
        return mode, background, measures


def local_cluster(workers: int, *, processes: bool = True):
    """A ``dask.distributed`` ``LocalCluster`` of ``workers`` single-threaded workers set up for prediction.

    Its worker processes do not get dask's ``MALLOC_TRIM_THRESHOLD_=65536``: with it, glibc
    hands every large temporary back to the system and maps it again for the next, which
    made a 512² frame cost 14.7 instead of 8.2 core-seconds (page faults x 4.5, measured).
    dask's other defaults stay (``OMP_NUM_THREADS=1``: 6.4 core-seconds). Give the workers of
    a cluster of your own (``scheduler=``) the same setting: unset
    ``distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_`` in its dask config.
    """
    import dask
    from dask.distributed import LocalCluster

    environ = {key: value for key, value in dask.config.get("distributed.nanny.pre-spawn-environ").items() if key != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes, dashboard_address=None)


class _Scheduler:
    """Frames through dask: the local threaded scheduler, a LocalCluster, or an existing scheduler."""

    def __init__(self, model, *, workers: int | None, scheduler: str | None, local_processes: bool) -> None:
        self.client = self.cluster = None
        self.model = model
        if scheduler is not None or workers is not None:
            from dask.distributed import Client

            children = {child.pid for child in multiprocessing.active_children()}
            try:
                if scheduler is not None:
                    try:
                        self.client = Client(scheduler, timeout="10s")
                    except OSError as error:
                        raise InputError(f"scheduler: cannot reach the dask scheduler at {scheduler} ({error})") from None
                else:
                    # its worker processes take seconds to start: a Ctrl-C meanwhile must not wait for them
                    self.cluster = run_interruptibly(lambda: local_cluster(workers, processes=local_processes), abandoned=lambda cluster: cluster.close(timeout=10))
                    self.client = Client(self.cluster)
                self.model = self.client.scatter(model, broadcast=True, hash=False)  # sent once, kept by every worker
            except BaseException:  # Ctrl-C or a failure while the cluster starts: no worker process outlives the run
                self.close({})
                for child in multiprocessing.active_children():
                    if child.pid not in children:
                        child.terminate()
                raise
        self.local_threads = process_threads()
        # the local scheduler runs a batch of one frame per core; a cluster keeps two frames per worker in flight
        self.slots = _IN_FLIGHT_PER_WORKER * max(1, len(self.client.scheduler_info()["workers"])) if self.client else self.local_threads
        self.description = (f"dask.distributed at {scheduler}" if scheduler else f"dask LocalCluster of {workers} workers" if workers
                            else f"dask local threaded scheduler ({self.local_threads} threads)")

    def share(self, value):
        """``value`` as every task will receive it: sent once to each worker (distributed), else as it is."""
        return value if self.client is None or value is None else self.client.scatter(value, broadcast=True, hash=False)

    def submit(self, index: int, hologram: np.ndarray, config: ExperimentConfig, background, settings: PredictionSettings, should_stop: StopCallback | None = None):
        """Frame ``index``'s task with the `PredictionSettings` ``settings``: a future (distributed) or a delayed call (local, which ``should_stop`` can end between planes)."""
        arguments = (hologram, self.model, config, background, settings)
        if self.client is not None:
            return self.client.submit(_frame_particles, *arguments, key=f"napari-lbs-frame-{index}-{id(self)}", pure=False)
        import dask

        return dask.delayed(_frame_particles, pure=False)(*arguments, should_stop)

    def completed(self, pending: dict):
        """``(index, particles, provenance)`` of the next finished frame(s) among ``pending`` (futures or delayed)."""
        if self.client is None:
            import dask

            indices = list(pending)
            results = dask.compute(*[pending[i] for i in indices], scheduler="threads", num_workers=self.local_threads)
            return [(i, *r) for i, r in zip(indices, results, strict=True)]
        from dask.distributed import wait

        done, _ = wait(list(pending.values()), return_when="FIRST_COMPLETED")
        index_of = {future.key: index for index, future in pending.items()}
        return [(index_of[future.key], *future.result()) for future in done]

    def close(self, pending: dict) -> None:
        """Cancel what is pending and end the client and the local cluster (its worker processes), each even if another step fails."""
        try:
            if self.client is not None:
                try:
                    self.client.cancel(list(pending.values()))
                finally:
                    self.client.close(timeout=10)
        finally:
            if self.cluster is not None:
                self.cluster.close(timeout=10)


def predict_sequence(
    frames: HologramFrames | Sequence[str | Path] | np.ndarray,
    model,
    config: ExperimentConfig | None = None,
    *,
    background: str | np.ndarray = "auto",
    settings: PredictionSettings | None = None,
    background_window: int = 21,
    background_samples: int = 32,
    workers: int | None = None,
    scheduler: str | None = None,
    local_processes: bool = True,
    work_dir: str | Path | None = None,
    device: str = "auto",
    precision: str = "auto",
    force: bool = False,
    threshold: float | None = None,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> SequenceResult:
    """Reconstruct the particles of every frame of a recording: one table with a ``frame`` column.

    Parameters
    ----------
    frames : HologramFrames, paths or (frames, rows, cols) array
        The recording (`open_frames` is applied to paths and arrays).
    model : LoadedModel or path
        A model file from `train_model`.
    config : ExperimentConfig, optional
        Optics and depths; default the model's own.
    background : {"auto", "global", "running", "flat", "none"} or (rows, cols) array
        What each frame is divided by before back-propagation: ``global``, the median of
        ``background_samples`` frames spread over the recording; ``running``, the median of
        the ``background_window`` frames around each frame; ``flat``, the frame's own
        illumination (`flat_field`: the frame smoothed over far more than a particle);
        ``auto`` (default), the global median when the medians of the first and second half
        of those frames agree, else flat (`choose_background`: a particle that moves too
        little over the recording stays in its median and would be divided out); ``none``,
        nothing (each frame's own mean, as a single hologram); or a background image taken
        without particles. A recording of one frame has no median background (it would be
        the frame): ``global`` and ``running`` become ``none``, ``auto`` becomes ``flat``.
    settings : PredictionSettings, optional
        Each frame's ``device``, ``precision``, ``force`` and ``threshold``, and its
        ``margin_px`` and ``window_px`` (`predict_particles`), in one object instead of the
        keywords (a call gives one or the other). The recording's own options (its
        background, the workers, the work folder) stay keywords.
    workers : int, optional
        Run on a ``dask.distributed`` ``LocalCluster`` of this many single-threaded workers
        (default: the local threaded scheduler, one frame per core at a time).
    scheduler : str, optional
        Address of an existing ``dask.distributed`` scheduler (``tcp://host:8786``) to run on.
    local_processes : bool
        ``LocalCluster`` workers as processes (default) or as threads of this process.
    work_dir : path, optional
        Folder for the per-frame results; a run started again with the same folder, inputs,
        model and settings skips the frames found there. None: results kept in memory only.
        The folder is left in place (remove it once the table is written).
    device : {"auto", "cpu", "cuda"}
        Where each worker runs the network (``auto``: a worker's GPU when it has one).
    precision : {"auto", "float32", "bfloat16"}
        The network's arithmetic on each worker (`resolve_precision`).
    force : bool
        Run a model made for other optics or depths anyway (`predict_particles`).
    threshold : float, optional
        The smallest score a detection keeps (`predict_particles`; default the model's).
    progress, should_stop
        One step per frame (resumed frames count as done at once). A stop raises `Stopped`:
        on the local threaded scheduler within a plane of the frames in flight, on dask
        workers when the next frame finishes (the others are cancelled); the finished frames
        stay in ``work_dir``.

    Returns
    -------
    SequenceResult
    """
    from napari_lbs._core.learning import LoadedModel, check_model_matches, check_threshold, load_model, prediction_settings, resolve_device, resolve_precision

    start_time = time.perf_counter()
    settings = prediction_settings(settings, device=device, precision=precision, force=force, threshold=threshold)
    device, precision, force, threshold = settings.device, settings.precision, settings.force, settings.threshold
    if workers is not None and scheduler is not None:
        raise InputError("workers: give either a number of local workers or a scheduler address, not both")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= available_threads()):
        # more single-threaded workers than cores only wait for each other, each holding a model and a frame
        raise InputError(f"workers: expected an integer in [1, {available_threads()}] (the cores this process may use), got {workers!r}")
    resolve_precision(precision, resolve_device("cpu"))  # an unknown name refused before any frame
    static = None
    if isinstance(background, np.ndarray):
        static, mode = as_hologram(background, name="background"), "file"
    elif background in BACKGROUND_MODES:
        mode = background
    else:
        raise InputError(f"background: expected one of {', '.join(BACKGROUND_MODES)} or an image, got {background!r}")
    opened = not isinstance(frames, HologramFrames)  # ours to close
    frames = open_frames(frames) if opened else frames
    with ExitStack() as cleanup:
        if opened:
            cleanup.callback(frames.close)
        frames.check()  # every frame's shape, from the headers, before any set-up
        loaded = model if isinstance(model, LoadedModel) else load_model(model, device="cpu")
        config = config if config is not None else loaded.config
        check_model_matches(loaded.meta, config, planes_um=config.volume.planes_um(), force=force)
        if threshold is not None:
            check_threshold(threshold, loaded)  # before any work folder or worker, not in every frame
        count = len(frames)
        if count == 1 and mode in ("global", "running", "auto"):
            mode = "flat" if mode == "auto" else "none"  # the median of one frame is that frame: dividing by it would leave nothing
        identity = {
            "sources": frames.describe(),
            "frames": count,
            "model_sha256": loaded.sha256,
            "precision": precision,
            "threshold": threshold,
            "margin_px": settings.margin_px,
            "window_px": settings.window_px,
            "config": config.to_dict(),
            "background": mode,
            "background_window": background_window if mode == "running" else None,
            "background_samples": background_samples if mode in ("global", "auto") else None,
            "background_sha256": hashlib.sha256(static.tobytes()).hexdigest() if static is not None else None,
        }
        first = frames.read(0)  # the first frame's pixels (and the shape every read checks)
        if static is not None and static.shape != first.shape:
            raise InputError(f"background: expected the frames' shape {first.shape}, got {static.shape}")
        cleanup.callback(size_threads, process_threads())  # the frames ran on one thread each in this process
        runner = _Scheduler(loaded, workers=workers, scheduler=scheduler, local_processes=local_processes)  # before the work folder: nothing left if unreachable
        pending: dict = {}
        cleanup.callback(runner.close, pending)
        work = _Work(Path(work_dir) if work_dir is not None else None, identity)
        cleanup.push(work.discard_if_refused)
        finished = work.finished() & set(range(count))
        steps = Steps(count, progress=progress, should_stop=should_stop)
        steps.advance(len(finished))
        todo = [index for index in range(count) if index not in finished]
        used, measures = mode, None  # auto: global or flat, as the recording allows
        if mode in ("global", "auto"):  # also with nothing left to do: the provenance says what was used
            compute = (lambda: ("global", sequence_background(frames, samples=background_samples), None)) if mode == "global" else (lambda: choose_background(frames, samples=background_samples))
            used, static, measures = work.background(compute)
        shared_background = runner.share(static)
        buffer: dict[int, np.ndarray] = {}  # frames of the running window
        queue = iter(todo)
        loop_start = time.perf_counter()
        while True:
            for index in queue:
                if mode == "running":
                    low, high = frame_window(index, count=count, window=background_window)
                    buffer = {k: buffer[k] if k in buffer else frames.read(k) for k in range(low, high)}
                    hologram, frame_background = buffer[index], frames_median(np.stack(list(buffer.values())))
                elif used == "flat":
                    hologram = frames.read(index)
                    frame_background = flat_field(hologram)
                else:
                    hologram, frame_background = frames.read(index), shared_background
                pending[index] = runner.submit(index, hologram, config, frame_background, settings, should_stop)
                if len(pending) >= runner.slots:
                    break
            if not pending:
                break
            kept = f"; the finished ones are kept in {work.folder}" if work.folder else ""
            try:
                finished_now = runner.completed(pending)
            except Stopped:  # a frame in this process's threads stopped between its planes
                raise Stopped(f"stopped after {steps.done} of {count} frames{kept}") from None
            for index, particles, frame_provenance in finished_now:
                del pending[index]
                work.save(index, particles)
                work.provenance(frame_provenance)
                steps.advance()
            if steps.stop_requested():
                raise Stopped(f"stopped after {steps.done} of {count} frames{kept}")
        loop_seconds = time.perf_counter() - loop_start
    tables = [work.load(index) for index in range(count)]
    columns = list(tables[0])
    particles = {name: np.concatenate([np.asarray(t[name]) for t in tables]) for name in columns}
    particles["frame"] = np.concatenate([np.full(len(np.asarray(t[columns[0]])), index, np.int64) for index, t in enumerate(tables)])
    seconds = time.perf_counter() - start_time
    provenance = {key: value for key, value in work.provenance().items() if key not in ("seconds", "background")}
    provenance.update({
        "napari_lbs": __version__,
        "frames": count,
        "sources": identity["sources"],
        "background": mode,
        "background_used": used,  # what auto chose (global or flat); the mode itself otherwise
        "background_measures": measures,
        "background_window": identity["background_window"],
        "background_samples": identity["background_samples"],
        "scheduler": runner.description,
        "resumed_frames": len(finished),
        "seconds": round(seconds, 3),
        # frames predicted per second once the workers run (set-up, background estimate and assembly excluded)
        "frames_per_second": round(len(todo) / loop_seconds, 4) if todo and loop_seconds > 0 else None,
    })
    return SequenceResult(particles, provenance, seconds, len(finished))
