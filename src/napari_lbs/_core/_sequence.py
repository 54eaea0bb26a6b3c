"""Recordings: frames read one at a time, a background from the frames, prediction frame by frame on dask.

A recording is any list of inputs — image files, folders of images (sorted naturally,
``frame2`` before ``frame10``), glob patterns, multi-page TIFFs (read page by page) and
videos (read frame by frame through OpenCV) — numbered 0, 1, ... in input order
(`open_frames`). Nothing reads a whole file: a frame is decoded when it is needed.

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

The background of a recording (the illumination, dust, fringes of the windows: everything
that does not move) is estimated from the frames themselves (`sequence_background`): the
per-pixel median of frames spread over the whole recording (``global``) or of the frames
around each frame (``running``, for drifting illumination). Particles move, so the median
of each pixel is the light without them. Each frame is divided by it before
back-propagation.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from napari_lbs import __version__
from napari_lbs._core._config import ExperimentConfig
from napari_lbs._core._files import atomic_path, read_json_object, write_json
from napari_lbs._core._io import as_hologram
from napari_lbs._core._progress import ProgressCallback, Steps, StopCallback, Stopped
from napari_lbs._core._validation import InputError

__all__ = [
    "BACKGROUND_MODES",
    "HologramFrames",
    "SequenceResult",
    "local_cluster",
    "open_frames",
    "predict_sequence",
    "sequence_background",
]

BACKGROUND_MODES = ("global", "running", "none")
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".bmp", ".jpg", ".jpeg", ".webp")
VIDEO_SUFFIXES = (".avi", ".mp4", ".mov", ".mkv", ".m4v")
_WORK_FORMAT = "napari-lbs-sequence-work"
_IN_FLIGHT_PER_WORKER = 2


class _TiffPages:
    """The pages of one (multi-page) TIFF, decoded one at a time from an open file."""

    def __init__(self, path: Path) -> None:
        import tifffile

        self.path = path
        self._handle = tifffile.TiffFile(path)
        self._handle.pages.cache = False  # keep only page offsets, never the pages read
        self.count = len(self._handle.pages)

    def read(self, index: int) -> np.ndarray:
        return self._handle.pages[index].asarray()

    def shape(self, index: int) -> tuple[int, int]:
        page = self._handle.pages[index]  # its tags only
        return int(page.imagelength), int(page.imagewidth)

    def close(self) -> None:
        self._handle.close()


class _ImageFile:
    """One single-frame image (TIFF, PNG, BMP, JPEG)."""

    count = 1

    def __init__(self, path: Path) -> None:
        self.path = path

    def read(self, index: int) -> np.ndarray:
        from PIL import Image

        with Image.open(self.path) as handle:
            return np.asarray(handle.convert("RGB") if handle.mode in ("P", "PA") else handle)

    def shape(self, index: int) -> tuple[int, int]:
        from PIL import Image

        with Image.open(self.path) as handle:  # the header only
            return handle.height, handle.width

    def close(self) -> None:
        pass


class _VideoFile:
    """A video decoded frame by frame (OpenCV); reading forward never seeks back."""

    def __init__(self, path: Path) -> None:
        try:
            import cv2
        except ImportError:
            raise InputError(f"{path}: reading videos needs OpenCV (pip install 'napari-lbs[sequences]')") from None
        self.path = path
        self._cv2 = cv2
        self._capture = None
        self._next = 0
        probe = cv2.VideoCapture(str(path))
        self.count = int(probe.get(cv2.CAP_PROP_FRAME_COUNT)) if probe.isOpened() else 0
        self._shape = (int(probe.get(cv2.CAP_PROP_FRAME_HEIGHT)), int(probe.get(cv2.CAP_PROP_FRAME_WIDTH)))
        probe.release()
        if self.count <= 0:
            raise InputError(f"{path}: cannot be read as a video (no frames decoded)")

    def read(self, index: int) -> np.ndarray:
        if self._capture is None or index < self._next:
            self.close()
            self._capture, self._next = self._cv2.VideoCapture(str(self.path)), 0
        while self._next < index:  # skip without decoding
            self._capture.grab()
            self._next += 1
        ok, image = self._capture.read()
        self._next += 1
        if not ok:
            raise InputError(f"{self.path}: frame {index} cannot be decoded")
        return image[..., ::-1] if image.ndim == 3 else image  # OpenCV's BGR → RGB

    def shape(self, index: int) -> tuple[int, int]:
        return self._shape  # a video's frames share the stream's size

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None


class _ArrayFrames:
    """Frames already in memory: a ``(frames, rows, cols)`` array."""

    def __init__(self, array: np.ndarray) -> None:
        self.path = Path("array")
        self._array = array
        self.count = int(array.shape[0])

    def read(self, index: int) -> np.ndarray:
        return self._array[index]

    def shape(self, index: int) -> tuple[int, int]:
        return tuple(self._array.shape[1:3])

    def close(self) -> None:
        pass


class HologramFrames:
    """The frames of a recording, numbered in input order and read one at a time.

    Use `open_frames` to make one. ``frames.read(k)`` returns frame ``k`` as a validated 2-D
    float array (`as_hologram`); every frame must have frame 0's shape.
    """

    def __init__(self, sources: Sequence) -> None:
        self._sources = list(sources)
        self._starts = np.cumsum([0] + [source.count for source in self._sources])
        self.shape: tuple[int, int] | None = None

    def __len__(self) -> int:
        return int(self._starts[-1])

    def __enter__(self) -> HologramFrames:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> list[str]:
        """The sources with their frame counts, for provenance (``file`` or ``file[frames 0-99]``)."""
        return [str(s.path) if s.count == 1 else f"{s.path}[frames 0-{s.count - 1}]" for s in self._sources]

    def name(self, index: int) -> str:
        """Frame ``index`` as the user knows it: ``file`` or ``file[frame k]``."""
        source, local = self._locate(index)
        return str(source.path) if source.count == 1 else f"{source.path}[frame {local}]"

    def read(self, index: int, *, log=None) -> np.ndarray:
        """Frame ``index`` (0-based) as a 2-D float array; ``log`` as `as_hologram`'s (which channel of RGB was kept)."""
        source, local = self._locate(index)
        try:
            image = source.read(local)
        except InputError:
            raise
        except Exception as error:  # any decoder failure is the file's fault: say which frame
            raise InputError(f"{self.name(index)}: cannot be read as an image ({type(error).__name__}: {error})") from None
        hologram = as_hologram(image, name=self.name(index), log=log)
        if self.shape is None:
            self.shape = hologram.shape
        elif hologram.shape != self.shape:
            raise InputError(f"{self.name(index)}: expected the first frame's shape {self.shape}, got {hologram.shape}")
        return hologram

    def check(self) -> None:
        """Refuse a recording whose frames differ in shape, from the files' headers (no frame is decoded).

        Run before any heavy work, so a bad frame late in a recording stops nothing half-way;
        a frame whose pixels cannot be decoded is still only found when it is read.
        """
        first = None
        for index in range(len(self)):
            source, local = self._locate(index)
            try:
                shape = source.shape(local)
            except Exception as error:  # an unreadable header is the file's fault: say which frame
                raise InputError(f"{self.name(index)}: cannot be read as an image ({type(error).__name__}: {error})") from None
            first = first or shape
            if shape != first:
                raise InputError(f"{self.name(index)}: expected the first frame's shape {first}, got {shape}")

    def close(self) -> None:
        for source in self._sources:
            source.close()

    def _locate(self, index: int):
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} of {len(self)}")
        position = int(np.searchsorted(self._starts, index, side="right")) - 1
        return self._sources[position], index - int(self._starts[position])


def _natural_key(path: Path) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def _source(path: Path):
    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return _VideoFile(path)
    if suffix in (".tif", ".tiff"):
        try:
            return _TiffPages(path)
        except Exception as error:  # not a TIFF after all, truncated: the file's fault
            raise InputError(f"{path}: cannot be read as a TIFF ({type(error).__name__}: {error})") from None
    if suffix in IMAGE_SUFFIXES:
        return _ImageFile(path)
    raise InputError(f"{path}: expected an image ({', '.join(IMAGE_SUFFIXES)}) or a video ({', '.join(VIDEO_SUFFIXES)})")


def open_frames(inputs: Sequence[str | Path] | np.ndarray) -> HologramFrames:
    """The frames of a recording, in input order.

    Parameters
    ----------
    inputs : sequence of paths, or (frames, rows, cols) array
        Each an image file (one frame), a multi-page TIFF (one frame per page), a video, a
        folder (its images, sorted naturally) or a glob pattern (``run/*.tif``, sorted
        naturally). An array is used as it is.

    Raises
    ------
    InputError
        A file that does not exist, a folder or pattern without images, a file of another kind.
    """
    if isinstance(inputs, np.ndarray):
        if inputs.ndim != 3 or inputs.shape[0] == 0:
            raise InputError(f"frames: expected a (frames, rows, cols) array, got shape {inputs.shape}")
        return HologramFrames([_ArrayFrames(inputs)])
    if isinstance(inputs, (str, Path)):
        inputs = [inputs]
    sources = []
    for entry in inputs:
        path = Path(entry)
        if path.is_dir():
            files = sorted((p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
            if not files:
                raise InputError(f"{path}: folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
        elif path.is_file():
            files = [path]
        elif glob.has_magic(str(entry)):
            files = sorted((Path(p) for p in glob.glob(str(entry)) if Path(p).is_file()), key=_natural_key)
            if not files:
                raise InputError(f"{entry}: no file matches")
        else:
            raise InputError(f"{path}: file not found")
        sources.extend(_source(file) for file in files)
    if not sources:
        raise InputError("frames: expected at least one input")
    return HologramFrames(sources)


def _window(index: int, *, count: int, window: int) -> tuple[int, int]:
    """The ``window`` frames around ``index`` (clamped inside ``[0, count)``): ``(first, stop)``."""
    size = min(window, count)
    first = min(max(index - size // 2, 0), count - size)
    return first, first + size


def sequence_background(frames: HologramFrames, *, samples: int = 32, index: int | None = None, window: int = 21) -> np.ndarray:
    """The background of a recording: the per-pixel median of its frames.

    Parameters
    ----------
    frames : HologramFrames
        The recording (`open_frames`).
    samples : int
        Global background (``index`` None): the median of this many frames spread evenly over
        the whole recording (all of them when it has fewer). Memory: ``samples`` frames.
    index : int, optional
        Running background: the median of the ``window`` frames centred on frame ``index``
        (shifted inside the recording at its ends).
    window : int
        Frames of a running background.

    Returns
    -------
    (rows, cols) float32 array, positive (a pixel dark in every frame gets the smallest
    positive value of the estimate, so dividing by it is always defined).
    """
    count = len(frames)
    if index is None:
        if samples < 1:
            raise InputError(f"samples: expected at least 1 frame, got {samples}")
        chosen = np.unique(np.linspace(0, count - 1, min(samples, count)).round().astype(int))
    else:
        if window < 1:
            raise InputError(f"window: expected at least 1 frame, got {window}")
        chosen = range(*_window(index, count=count, window=window))
    return _median(np.stack([frames.read(int(k)) for k in chosen]))


def _median(stack: np.ndarray) -> np.ndarray:
    median = np.median(stack, axis=0).astype(np.float32)
    positive = median[median > 0]
    floor = positive.min() if positive.size else np.float32(1.0)
    return np.maximum(median, floor)


@dataclass
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
        Wall time of this call.
    resumed : int
        Frames found finished in the work folder (not predicted again).
    """

    particles: dict[str, np.ndarray]
    provenance: dict
    seconds: float
    resumed: int


def _frame_particles(hologram: np.ndarray, model, config: ExperimentConfig, background: np.ndarray | None, device: str, should_stop: StopCallback | None = None) -> tuple[dict, dict]:
    """One frame's `predict_particles` (the dask task). ``model`` is the worker's copy, moved to ``device`` on first use; ``should_stop`` (threads of this process only) ends it between planes."""
    import torch

    from napari_lbs._core._network import resolve_device
    from napari_lbs._core._prediction import predict_particles

    torch.set_num_threads(1)  # the same rounding on every worker (module docstring)
    target = resolve_device(device)
    if next(model.network.parameters()).device != target:
        model.network.to(target)
    # predict_sequence checked the model against the config once, before any frame
    result = predict_particles(hologram, model, config, background=background, force=True, should_stop=should_stop)
    return result.particles, result.provenance


class _Work:
    """The work folder of a run: one ``.npz`` per finished frame, the background, the run's identity."""

    def __init__(self, folder: Path | None, identity: dict) -> None:
        self.folder = folder
        self.results: dict[int, dict] = {}  # without a folder
        self.first_provenance: dict | None = None
        if folder is None:
            return
        manifest = folder / "work.json"
        if manifest.is_file():
            previous = read_json_object(manifest, what="work folder manifest")
            if previous.get("format") != _WORK_FORMAT or previous.get("identity") != json.loads(json.dumps(identity)):
                raise InputError(f"{folder}: holds the frames of another run (other inputs, model or settings); delete it or choose another output")
        else:
            folder.mkdir(parents=True, exist_ok=True)
            write_json(manifest, {"format": _WORK_FORMAT, "napari_lbs": __version__, "identity": identity})

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
        with np.load(self.folder / f"frame_{index:07d}.npz") as data:
            return {name: data[name] for name in data.files}

    def background(self, compute) -> np.ndarray:
        """The global background, computed once and kept in the work folder for a resumed run."""
        if self.folder is None:
            return compute()
        path = self.folder / "background.npy"
        if path.is_file():
            return np.load(path)
        background = compute()
        with atomic_path(path) as temporary:
            with open(temporary, "wb") as handle:
                np.save(handle, background)
        return background


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

            if scheduler is not None:
                try:
                    self.client = Client(scheduler, timeout="10s")
                except OSError as error:
                    raise InputError(f"scheduler: cannot reach the dask scheduler at {scheduler} ({error})") from None
            else:
                self.cluster = local_cluster(workers, processes=local_processes)
                self.client = Client(self.cluster)
            self.model = self.client.scatter(model, broadcast=True, hash=False)  # sent once, kept by every worker
        self.local_threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        # the local scheduler runs a batch of one frame per core; a cluster keeps two frames per worker in flight
        self.slots = _IN_FLIGHT_PER_WORKER * max(1, len(self.client.scheduler_info()["workers"])) if self.client else self.local_threads
        self.description = (f"dask.distributed at {scheduler}" if scheduler else f"dask LocalCluster of {workers} workers" if workers
                            else f"dask local threaded scheduler ({self.local_threads} threads)")

    def share(self, value):
        """``value`` as every task will receive it: sent once to each worker (distributed), else as it is."""
        return value if self.client is None or value is None else self.client.scatter(value, broadcast=True, hash=False)

    def submit(self, index: int, hologram: np.ndarray, config: ExperimentConfig, background, device: str, should_stop: StopCallback | None = None):
        """Frame ``index``'s task: a future (distributed) or a delayed call (local, which ``should_stop`` can end between planes)."""
        arguments = (hologram, self.model, config, background, device)
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
        if self.client is not None:
            self.client.cancel(list(pending.values()))
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def predict_sequence(
    frames: HologramFrames | Sequence[str | Path] | np.ndarray,
    model,
    config: ExperimentConfig | None = None,
    *,
    background: str | np.ndarray = "global",
    background_window: int = 21,
    background_samples: int = 32,
    workers: int | None = None,
    scheduler: str | None = None,
    local_processes: bool = True,
    work_dir: str | Path | None = None,
    device: str = "auto",
    force: bool = False,
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
    background : {"global", "running", "none"} or (rows, cols) array
        What each frame is divided by before back-propagation: the median of
        ``background_samples`` frames spread over the recording, the running median of the
        ``background_window`` frames around each frame, nothing (each frame's own mean, as a
        single hologram), or a background image taken without particles. A recording of one
        frame has no median background (it would be the frame): ``none``.
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
    force : bool
        Run a model made for other optics or depths anyway (`predict_particles`).
    progress, should_stop
        One step per frame (resumed frames count as done at once). A stop raises `Stopped`:
        on the local threaded scheduler within a plane of the frames in flight, on dask
        workers when the next frame finishes (the others are cancelled); the finished frames
        stay in ``work_dir``.

    Returns
    -------
    SequenceResult
    """
    from napari_lbs._core._network import LoadedModel, check_model_matches, load_model

    start_time = time.perf_counter()
    if workers is not None and scheduler is not None:
        raise InputError("workers: give either a number of local workers or a scheduler address, not both")
    if workers is not None and workers < 1:
        raise InputError(f"workers: expected at least 1, got {workers}")
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
        count = len(frames)
        if count == 1 and mode in ("global", "running"):
            mode = "none"  # the median of one frame is that frame: dividing by it would leave nothing
        identity = {
            "sources": frames.describe(),
            "frames": count,
            "model_sha256": loaded.sha256,
            "config": config.to_dict(),
            "background": mode,
            "background_window": background_window if mode == "running" else None,
            "background_samples": background_samples if mode == "global" else None,
            "background_sha256": hashlib.sha256(static.tobytes()).hexdigest() if static is not None else None,
        }
        first = frames.read(0)  # the first frame's pixels (and the shape every read checks)
        if static is not None and static.shape != first.shape:
            raise InputError(f"background: expected the frames' shape {first.shape}, got {static.shape}")
        import torch

        cleanup.callback(torch.set_num_threads, torch.get_num_threads())  # the frames ran on one thread each in this process
        runner = _Scheduler(loaded, workers=workers, scheduler=scheduler, local_processes=local_processes)  # before the work folder: nothing left if unreachable
        pending: dict = {}
        cleanup.callback(runner.close, pending)
        work = _Work(Path(work_dir) if work_dir is not None else None, identity)
        finished = work.finished() & set(range(count))
        steps = Steps(count, progress=progress, should_stop=should_stop)
        steps.advance(len(finished))
        todo = [index for index in range(count) if index not in finished]
        if mode == "global" and todo:
            static = work.background(lambda: sequence_background(frames, samples=background_samples))
        shared_background = runner.share(static)
        buffer: dict[int, np.ndarray] = {}  # frames of the running window
        queue = iter(todo)
        loop_start = time.perf_counter()
        while True:
            for index in queue:
                if mode == "running":
                    low, high = _window(index, count=count, window=background_window)
                    buffer = {k: buffer[k] if k in buffer else frames.read(k) for k in range(low, high)}
                    hologram, frame_background = buffer[index], _median(np.stack(list(buffer.values())))
                else:
                    hologram, frame_background = frames.read(index), shared_background
                pending[index] = runner.submit(index, hologram, config, frame_background, device, should_stop)
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
        "background_window": identity["background_window"],
        "background_samples": identity["background_samples"],
        "scheduler": runner.description,
        "resumed_frames": len(finished),
        "seconds": round(seconds, 3),
        # frames predicted per second once the workers run (set-up, background estimate and assembly excluded)
        "frames_per_second": round(len(todo) / loop_seconds, 4) if todo and loop_seconds > 0 else None,
    })
    return SequenceResult(particles, provenance, seconds, len(finished))
