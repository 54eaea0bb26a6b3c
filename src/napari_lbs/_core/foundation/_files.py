"""Files: safe atomic writes, strict JSON, and reading UTF-8 text and JSON objects.

Every writer goes to a temporary name beside the target and renames it into place, so an
interrupted write never leaves a half-written file where a good one was. A target is a new
name or an existing regular file: a symbolic link is never written through (nor replaced),
a device, FIFO or socket never replaced, and an existing file replaced only when the caller
says so (`check_target`). Readers refuse a missing file, a folder or another encoding with
one line naming the file.

This module imports only the standard library, so every other module may use it.
"""

from __future__ import annotations

import glob
import json
import math
import os
import re
import stat
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

from napari_lbs._core.foundation._errors import InputError
from napari_lbs._core.foundation._interrupts import deferred_interrupts

__all__ = ["check_target", "atomic_path", "atomic_write_bytes", "json_safe", "write_json", "read_text", "read_json_object"]

_RUN_STARTED = time.time()  # temporaries older than this are a killed run's leftovers


def _new_file_mode() -> int:
    """The mode a newly created file gets under the process's umask (0666 & ~umask)."""
    try:  # Linux reports the umask without changing it (os.umask would, racing other threads)
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def _remove_stale_temporaries(path: Path) -> None:
    """Remove temporary files of ``path`` that a killed run (SIGKILL, power cut) left behind.

    Only names `atomic_path` makes (``.NAME.XXXXXXXX.partSUFFIX``) last modified before this
    process started using this module, so another process writing ``path`` now keeps its own.
    """
    pattern = re.compile(re.escape(f".{path.name}.") + r"[a-z0-9_]{8}" + re.escape(".part" + path.suffix))
    for candidate in path.parent.glob(f".{glob.escape(path.name)}.*"):
        try:
            if pattern.fullmatch(candidate.name) and candidate.is_file() and candidate.stat().st_mtime < _RUN_STARTED:
                candidate.unlink()
        except OSError:  # gone already, or not ours to remove: leave it
            pass


def check_target(path: str | Path, *, force: bool = False, flag: str | None = None) -> Path:
    """Refuse a file output unless it is a new name, or an existing regular file and ``force``: the one rule every writer follows.

    The last component is examined without following a link (``lstat``, as ``O_NOFOLLOW``
    would), so ``/dev/null``, a FIFO or a link to another file is never written through.

    Parameters
    ----------
    path : path
        The file about to be written.
    force : bool
        Replace an existing regular file (the user asked: ``--force``, ``force=True``, or a
        save dialog that asked already).
    flag : str, optional
        The flag that named it (``--out``), for the message; the refusal of an existing file
        then names ``--force``, else the keyword ``force=True``.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputError
        A symbolic link, a folder, anything else that is not a regular file (a device, a
        FIFO, a socket), or an existing regular file without ``force``; one line naming the path.
    """
    path = Path(path)
    name = f"{flag} {path}" if flag else str(path)
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):  # a new name (a parent that is a file is refused when the folder is made)
        return path
    if stat.S_ISLNK(mode):
        raise InputError(f"{name}: is a symbolic link; name the file itself (a link is never written through)")
    if stat.S_ISDIR(mode):
        raise InputError(f"{name}: is a folder; expected a file name")
    if not stat.S_ISREG(mode):
        raise InputError(f"{name}: is not a regular file (a device, FIFO or socket); choose a file name")
    if not force:  # the console script names its flag; a Python caller, the keyword
        raise InputError(f"{name}: exists; add {'--force' if flag else 'force=True'} to replace it, or choose another name")
    return path


def _commit(temporary: Path, path: Path, *, force: bool) -> None:
    """Put the finished ``temporary`` at ``path``, re-checking the target as it is now (another process may have made it meanwhile)."""
    try:
        existing = os.lstat(path)
    except FileNotFoundError:
        existing = None
    # a replaced file keeps its own mode; a new one gets 0666 less the umask (mkstemp made it 0600)
    os.chmod(temporary, existing.st_mode & 0o7777 if existing is not None and stat.S_ISREG(existing.st_mode) else _new_file_mode())
    if not force:
        try:  # a hard link fails on any existing name, link or file: no clobber, atomically
            os.link(temporary, path)
            return
        except FileExistsError:
            check_target(path, force=False)  # raises, naming what is there
        except OSError:  # a file system without hard links: check, then rename
            check_target(path, force=False)
    check_target(path, force=True)
    os.replace(temporary, path)


@contextmanager
def atomic_path(path: Path, *, force: bool = True):
    """Yield a temporary path beside ``path``; put it at ``path`` only if the block succeeds.

    ``path`` is checked before (`check_target`) and again when the temporary is put in place:
    a symbolic link, a folder, a device, a FIFO or a socket is refused, and with ``force``
    false so is an existing file. The result has the mode an ordinary write would give it:
    a replaced file's own mode, else 0666 less the umask (a temporary file is created 0600,
    which would hide results from the lab members sharing a folder). Temporaries of ``path``
    that a killed earlier run left are removed first.

    Parameters
    ----------
    path : Path
        The file to write.
    force : bool
        Replace an existing regular file. Steps that rewrite their own files as they go (a
        model per epoch, a data set's manifest) keep the default; a step writing a user's
        output passes the user's choice after checking it with `check_target` up front.
    """
    path = Path(path)
    check_target(path, force=force)
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temporaries(path)
    temporary = None
    try:
        # an interrupt between the file's creation and its name's keeping, or amid its removal, would leave it behind
        with deferred_interrupts():
            handle, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part" + path.suffix, dir=path.parent)
            os.close(handle)
            temporary = Path(name)
        yield temporary
        _commit(temporary, path, force=force)
    finally:
        with deferred_interrupts():
            if temporary is not None and temporary.exists():
                temporary.unlink()


def atomic_write_bytes(path: Path, data: bytes, *, force: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically (`atomic_path`); return ``path``."""
    with atomic_path(path, force=force) as temporary:
        temporary.write_bytes(data)
    return Path(path)


def json_safe(value: object) -> object:
    """``value`` with every NaN or infinite float replaced by ``None``: strict JSON (``null``), never ``NaN``."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    return value


def write_json(path: str | Path, payload: dict, *, force: bool = True) -> Path:
    """Write ``payload`` as indented strict JSON, atomically (`atomic_path`); non-finite numbers become ``null`` (`json_safe`)."""
    text = json.dumps(json_safe(payload), indent=2, sort_keys=False, allow_nan=False)
    return atomic_write_bytes(Path(path), (text + "\n").encode("utf-8"), force=force)


def read_text(path: str | Path, *, what: str) -> str:
    """The UTF-8 text of a file (a byte-order mark, as Excel writes, is dropped).

    Raises
    ------
    InputError
        Missing, a folder, or not UTF-8 (e.g. Latin-1 or UTF-16), naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found" + (" (it is a folder)" if path.is_dir() else ""))
    try:
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as error:
        raise InputError(f"{path}: not UTF-8 text (byte {error.start}); save the {what} file as UTF-8") from None


def read_json_object(path: str | Path, *, what: str) -> dict:
    """A JSON object from a UTF-8 file; anything else (a list, invalid JSON, other encodings) is refused naming the file."""
    path = Path(path)
    try:
        payload = json.loads(read_text(path, what=what))
    except json.JSONDecodeError as error:
        raise InputError(f"{path}: not valid JSON ({error})") from None
    except RecursionError:  # arrays or objects nested thousands deep
        raise InputError(f"{path}: not a {what} (values nested too deeply)") from None
    except ValueError as error:  # an integer of more digits than Python converts
        raise InputError(f"{path}: not a {what} ({str(error).splitlines()[0]})") from None
    if not isinstance(payload, dict):
        raise InputError(f"{path}: expected a JSON object ({what}), got a {type(payload).__name__}")
    return payload
