"""Reading holograms; reading and writing stacks and particle tables.

Every writer goes through `napari_lbs._core.foundation._files.atomic_path`, so an interrupted write
never leaves a half-written file where a good one was.
"""

from __future__ import annotations

import csv
import importlib.util
import io
import json
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from napari_lbs._core.foundation._errors import InputError
from napari_lbs._core.foundation._files import atomic_path, atomic_write_bytes, check_target, json_safe, read_text
from napari_lbs._core.foundation._validation import check_intensity_image

__all__ = [
    "InputError",
    "read_hologram",
    "as_hologram",
    "read_stack",
    "write_stack",
    "tiff_pages",
    "refusing_damaged_tiff",
    "read_particles",
    "write_particles",
    "check_table_name",
    "PARTICLE_COLUMNS",
]

PARTICLE_COLUMNS = ("x_um", "y_um", "z_um", "diameter_um")
_MIN_HOLOGRAM_PX = 16


def as_hologram(image: np.ndarray, *, name: str = "hologram", channel: int | None = None, log: Callable[[str], None] | None = None) -> np.ndarray:
    """Validate an image as a hologram and return it as a 2-D float32 array.

    RGB(A) images are reduced to one channel: ``channel`` if given, else the channel with the
    largest standard deviation (a colour sensor under a laser records the hologram in the
    channel of the laser's colour; the seed's hologram is red). ``log`` receives a message
    saying which channel was kept.

    Raises
    ------
    InputError
        Not 2-D (after the channel reduction), smaller than 16 px, or not an intensity
        (NaN/inf, every pixel equal, strongly negative: `check_intensity_image`).
    """
    array = np.asarray(image)
    if array.dtype.kind not in "uif" and array.dtype != bool:
        raise InputError(f"{name}: expected a numeric image, got dtype {array.dtype}")
    if array.ndim == 3 and array.shape[-1] in (3, 4):
        colour = array[..., :3].astype(np.float32)
        if channel is None:
            channel = int(np.argmax(colour.reshape(-1, 3).std(axis=0)))
        if not 0 <= channel < 3:
            raise InputError(f"{name}: expected channel 0, 1 or 2, got {channel}")
        if log is not None:
            log(f"{name}: RGB image reduced to its {('red', 'green', 'blue')[channel]} channel (index {channel})")
        array = colour[..., channel]
    if array.ndim != 2:
        raise InputError(f"{name}: expected a 2-D image (rows, cols) or RGB, got shape {array.shape}")
    if min(array.shape) < _MIN_HOLOGRAM_PX:
        raise InputError(f"{name}: expected at least {_MIN_HOLOGRAM_PX}x{_MIN_HOLOGRAM_PX} pixels, got {array.shape}")
    # Keep the input's precision: float64 stays float64; integers become float32.
    out = array if array.dtype in (np.float32, np.float64) else array.astype(np.float32)
    check_intensity_image(out, name=name)
    return out


@contextmanager
def refusing_damaged_tiff(name: str) -> Iterator[None]:
    """Refuse a TIFF that tifffile complains about while the block reads it: `InputError` naming ``name``.

    tifffile reports a damaged tag or strip as a logged warning and goes on with what it could
    parse, so what comes back is not the recorded image. Its warnings are kept off the
    terminal; the first one (and how many more) goes into the one-line refusal.
    """
    import logging

    complaints: list[str] = []

    class _Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            complaints.append(record.getMessage().strip().splitlines()[0] if record.getMessage().strip() else record.levelname)

    logger, handler = logging.getLogger("tifffile"), _Collect(logging.WARNING)
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate
    if complaints:
        more = f" and {len(complaints) - 1} more" if len(complaints) > 1 else ""
        raise InputError(f"{name}: cannot be read as an image (a damaged TIFF: {complaints[0]}{more})")


def read_hologram(path: str | Path, *, channel: int | None = None, log: Callable[[str], None] | None = None) -> np.ndarray:
    """Read a hologram from TIFF, PNG or BMP as a 2-D float array (see `as_hologram`)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    suffix = path.suffix.lower()
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            with refusing_damaged_tiff(str(path)), tifffile.TiffFile(path) as handle:
                pages = len(handle.pages)
                image = handle.asarray()
        else:
            from PIL import Image

            with Image.open(path) as handle:
                pages = getattr(handle, "n_frames", 1)
                # a palette image stores indices into a colour table: its colours are the intensities
                image = np.asarray(handle.convert("RGB") if handle.mode in ("P", "PA") else handle)
    except InputError:
        raise
    except Exception as error:  # any decoder failure is the file's fault: say which file
        raise InputError(f"{path}: cannot be read as an image ({type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''})") from None
    if pages > 1:
        raise InputError(f"{path}: holds {pages} pages; expected one hologram (split the pages into files)")
    return as_hologram(image, name=str(path), channel=channel, log=log)


@contextmanager
def tiff_pages(path: str | Path, shape: tuple[int, ...], *, description: dict, force: bool = False) -> Iterator[np.ndarray]:
    """The one TIFF writer: a float32 TIFF of ``shape`` to fill in place, renamed onto ``path`` when the block succeeds.

    Parameters
    ----------
    path : path
        The TIFF; nothing is left there if the block fails or is interrupted (`atomic_path`).
    shape : (rows, cols), or (pages, rows, cols)
        One hologram, or a stack of planes or frames (one page each).
    description : dict
        Provenance (and a stack's ``z_um``), stored as the first page's ImageDescription JSON.
    force : bool
        Replace an existing regular file at ``path`` (`check_target`, before any page is made).

    Yields
    ------
    numpy.memmap
        The pages on disk: a deep stack or a long recording is written plane by plane and
        never has to fit in memory.
    """
    import tifffile

    with atomic_path(Path(path), force=force) as temporary:
        pages = tifffile.memmap(temporary, shape=tuple(shape), dtype=np.float32, description=json.dumps(json_safe(description)), metadata=None, photometric="minisblack")
        yield pages
        pages.flush()


def write_stack(path: str | Path, stack: np.ndarray, *, z_um: Sequence[float], metadata: dict | None = None, force: bool = False) -> Path:
    """Write a float32 ``(z, y, x)`` stack as TIFF with ``{"z_um": [...], ...}`` as ImageDescription JSON (`tiff_pages`; an existing file only with ``force``)."""
    stack = np.asarray(stack)
    if stack.ndim != 3 or stack.shape[0] != len(z_um):
        raise InputError(f"stack: expected shape (len(z_um)={len(z_um)}, y, x), got {stack.shape}")
    with tiff_pages(path, stack.shape, description={"z_um": [float(z) for z in z_um], **(metadata or {})}, force=force) as pages:
        pages[:] = stack
    return Path(path)


def read_stack(path: str | Path) -> tuple[np.ndarray, dict]:
    """Read a stack written by `write_stack`; return ``(stack, description_dict)``."""
    import tifffile

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    with tifffile.TiffFile(path) as handle:
        stack = handle.asarray()
        text = handle.pages[0].description
    try:
        description = json.loads(text) if text else {}
    except json.JSONDecodeError:
        description = {}
    return stack, description


def write_particles(path: str | Path, table: dict[str, np.ndarray], *, metadata: dict | None = None, force: bool = False) -> Path:
    """Write a particle table (docs/formats.md): ``x_um,y_um,z_um,diameter_um`` then any other columns.

    Parameters
    ----------
    path : path
        ``.parquet``: an Apache Parquet file (pandas + pyarrow, the ``sequences`` extra), the
        columns' own types kept (``frame`` stays int64); any other name: CSV.
    table : dict of arrays
    metadata : dict, optional
        Parquet only: stored as JSON in the file's key-value metadata under ``napari_lbs``
        (e.g. the provenance; a CSV's goes in a JSON file beside it).
    force : bool
        Replace an existing regular file at ``path``; without it an existing file is refused
        (`check_target`), as are a link, a folder, a device or a FIFO in any case.
    """
    check_target(path, force=force)  # before the table is formatted
    _check_table_to_write(path, table)
    columns = list(PARTICLE_COLUMNS) + [c for c in table if c not in PARTICLE_COLUMNS]
    if _is_parquet(path):
        return _write_parquet(Path(path), {c: np.asarray(table[c]) for c in columns}, metadata, force=force)
    count = len(np.asarray(table["x_um"]))
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for i in range(count):
        writer.writerow([_format(table[c][i]) for c in columns])
    return atomic_write_bytes(Path(path), buffer.getvalue().encode("utf-8"), force=force)


def _is_parquet(path: str | Path) -> bool:
    return Path(path).suffix.lower() == ".parquet"


def _no_pyarrow(path: Path) -> InputError:
    return InputError(f"{path}: Parquet tables need pyarrow (pip install 'napari-lbs[sequences]')")


def check_table_name(path: str | Path) -> Path:
    """Refuse, before any work, a particle table that `write_particles` could not write: ``.parquet`` without pyarrow.

    Only looks pyarrow up (no import), so a command stays quick to refuse and to start.
    """
    path = Path(path)
    if _is_parquet(path) and importlib.util.find_spec("pyarrow") is None:
        raise _no_pyarrow(path)
    return path


def _pyarrow(path: Path):
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError:
        raise _no_pyarrow(path) from None
    return pyarrow


def _write_parquet(path: Path, table: dict[str, np.ndarray], metadata: dict | None, *, force: bool) -> Path:
    pyarrow = _pyarrow(path)
    arrow = pyarrow.table(table)
    if metadata is not None:
        arrow = arrow.replace_schema_metadata({**(arrow.schema.metadata or {}), b"napari_lbs": json.dumps(json_safe(metadata)).encode("utf-8")})
    with atomic_path(path, force=force) as temporary:
        pyarrow.parquet.write_table(arrow, temporary)
    return path


def _check_table_to_write(path: str | Path, table: dict) -> None:
    """Refuse a table `read_particles` would refuse, before anything is written (naming ``path`` and the column)."""
    if not isinstance(table, Mapping):
        raise InputError(f"{path}: expected a particle table (a mapping of column name to values), got {type(table).__name__}")
    missing = [c for c in PARTICLE_COLUMNS if c not in table]
    if missing:
        raise InputError(f"{path}: particle table: missing column {missing[0]}")
    names = [str(name).strip() for name in table]
    for name, stripped in zip(table, names, strict=True):
        if not isinstance(name, str) or not stripped or name != stripped or names.count(stripped) > 1:
            raise InputError(f"{path}: particle table: column name {name!r} is not a distinct, non-blank name without surrounding spaces")
    lengths = {name: np.shape(values) for name, values in table.items()}
    count = lengths["x_um"][0] if len(lengths["x_um"]) == 1 else -1
    for name, shape in lengths.items():
        if shape != (count,):
            raise InputError(f"{path}: particle table: column {name} has shape {shape}; expected {max(count, 0)} values, one per particle (as x_um)")
    for name in PARTICLE_COLUMNS:
        try:
            values = np.asarray(table[name], dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{path}: particle table: column {name} is not numeric") from None
        if name != "diameter_um" and not np.all(np.isfinite(values)):
            raise InputError(f"{path}: particle table: column {name} holds NaN or infinite values")


def _format(value: object) -> str:
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.9g}"  # sub-nanometre for any position in µm up to metres
    return str(value)


def read_particles(path: str | Path) -> dict[str, np.ndarray]:
    """Read a particle table (CSV, or Parquet when the name ends in ``.parquet``); numeric columns become float64 arrays.

    A CSV: UTF-8 with or without a byte-order mark (Excel's "CSV UTF-8"); blank lines are skipped.

    Raises
    ------
    InputError
        Naming the file (and the line or column): not UTF-8, empty, a required column missing,
        a column named twice, a row with more or fewer values than the header, a required
        column not numeric, a position (``x_um``, ``y_um``, ``z_um``) NaN or infinite, or
        a diameter infinite (NaN: not measured).
    """
    path = Path(path)
    if _is_parquet(path):
        return _checked(path, _read_parquet(path))
    reader = csv.reader(io.StringIO(read_text(path, what="particle table"), newline=""))
    header = next(reader, None)
    if not header:
        raise InputError(f"{path}: empty file, expected a header {','.join(PARTICLE_COLUMNS)}")
    header = [h.strip() for h in header]
    duplicated = next((name for index, name in enumerate(header) if name in header[:index]), None)
    if duplicated is not None:
        raise InputError(f"{path}: column {duplicated} appears twice in the header")
    _check_columns(path, header)
    rows = []
    for row in reader:
        if not any(cell.strip() for cell in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{path}: line {reader.line_num}: expected {len(header)} values (as the header), got {len(row)}")
        rows.append(row)
    table: dict[str, np.ndarray] = {}
    for index, name in enumerate(header):
        values = [row[index] for row in rows]
        try:
            table[name] = np.array(values, dtype=np.float64)
        except ValueError:
            if name in PARTICLE_COLUMNS:
                raise InputError(f"{path}: column {name} is not numeric") from None
            table[name] = np.array(values, dtype=object)
    return _checked(path, table)


def _check_columns(path: Path, header: list[str]) -> None:
    missing = [c for c in PARTICLE_COLUMNS if c not in header]
    if missing:
        raise InputError(f"{path}: missing column {missing[0]} (header: {','.join(header)})")


def _checked(path: Path, table: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``table`` once its positions are finite numbers and its diameters finite or NaN (not measured; its columns already checked)."""
    for name in PARTICLE_COLUMNS[:3]:
        if not np.all(np.isfinite(table[name])):
            raise InputError(f"{path}: column {name} holds NaN or infinite values")
    if np.any(np.isinf(table["diameter_um"])):
        raise InputError(f"{path}: column diameter_um holds infinite values")
    return table


def _read_parquet(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise InputError(f"{path}: particle table file not found" + (" (it is a folder)" if path.is_dir() else ""))
    pyarrow = _pyarrow(path)
    try:
        frame = pyarrow.parquet.read_table(path).to_pandas()
    except (OSError, pyarrow.ArrowException) as error:
        raise InputError(f"{path}: cannot be read as a Parquet table ({error})") from None
    _check_columns(path, [str(name) for name in frame.columns])
    table = {}
    for name in frame.columns:
        values = frame[name].to_numpy()
        if values.dtype.kind in "fiub":
            table[str(name)] = values.astype(np.float64)
        elif str(name) in PARTICLE_COLUMNS:
            raise InputError(f"{path}: column {name} is not numeric")
        else:
            table[str(name)] = values.astype(object)
    return table
