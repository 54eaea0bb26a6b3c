"""Reading recordings: frames one at a time from files, folders, glob patterns, TIFF pages or videos.

A recording is any list of inputs — image files, folders of images (sorted naturally,
``frame2`` before ``frame10``), glob patterns, multi-page TIFFs (read page by page) and
videos (read frame by frame through OpenCV) — numbered 0, 1, ... in input order
(`open_frames`). Nothing reads a whole file: a frame is decoded when it is needed.
"""

from __future__ import annotations

import glob
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import as_hologram, refusing_damaged_tiff

__all__ = ["HologramFrames", "open_frames", "IMAGE_SUFFIXES", "VIDEO_SUFFIXES"]

IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".bmp", ".jpg", ".jpeg", ".webp")
VIDEO_SUFFIXES = (".avi", ".mp4", ".mov", ".mkv", ".m4v")


class _TiffPages:
    """The pages of one (multi-page) TIFF, decoded one at a time from an open file."""

    def __init__(self, path: Path) -> None:
        import tifffile

        self.path = path
        self._handle = None
        try:
            with refusing_damaged_tiff(str(path)):  # a damaged header or page list
                self._handle = tifffile.TiffFile(path)
                self._handle.pages.cache = False  # keep only page offsets, never the pages read
                self.count = len(self._handle.pages)
        except BaseException:
            self.close()
            raise

    def read(self, index: int) -> np.ndarray:
        with refusing_damaged_tiff(f"{self.path}[page {index}]"):  # a damaged strip or tag reads on as other pixels
            return self._handle.pages[index].asarray()

    def shape(self, index: int) -> tuple[int, int]:
        with refusing_damaged_tiff(f"{self.path}[page {index}]"):
            page = self._handle.pages[index]  # its tags only
            return int(page.imagelength), int(page.imagewidth)

    def close(self) -> None:
        if self._handle is not None:
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
            except InputError:
                raise
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
        except InputError:
            raise
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
