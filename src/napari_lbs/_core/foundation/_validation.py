"""Input validation: every reader and entry point checks here, before any heavy work.

One message per refusal, one line, naming the culprit (a file, a flag or a key): an
`InputError`. The checks cover what users hand the tool (holograms, calibration JSON, data
set manifests, model and resume files), the bounds on work
their inputs imply (memory and disk for a stack, widths of a network) and the outputs they
name (a folder where a file goes, a file where a folder goes, an input about to be
overwritten, a link or device, an existing file without ``--force``). docs/reliability.md lists every case and what the user gets.

This module imports only the standard library at import time (numpy and torch inside the
functions that need them), so the CLI can use it and still start fast.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from collections.abc import Collection, Iterable, Mapping
from pathlib import Path

from napari_lbs._core.foundation._errors import ConfigError, InputError
from napari_lbs._core.foundation._files import check_target

__all__ = [
    "InputError",
    "HOLO_PARAM_RANGES",
    "check_intensity_image",
    "check_holo_params",
    "check_calibration",
    "check_memory",
    "check_disk",
    "check_output_path",
    "check_dataset_manifest",
    "check_model_payload",
    "check_prediction_meta",
    "load_resume_state",
    "check_resume_matches",
]

# Holo-processing parameters (`HoloParams`): the noise mean as a multiple of the hologram's
# peak-to-peak range, the noise width as a multiple of its standard deviation, and the gamma.
# The fit searches well inside these (the seed's bounds, `PARAM_BOUNDS`); outside them the
# "noise" swamps the hologram or the gamma flattens or saturates every plane.
HOLO_PARAM_RANGES = {"N_R": (-1.0, 1.0), "N_sigma": (0.0, 5.0), "gamma": (0.05, 20.0)}
# Dark-frame subtraction leaves small negative counts; an image far below zero is no intensity.
_NEGATIVE_TOLERANCE = 0.1  # of the image's maximum
_LARGEST_INTENSITY = 1.8e19  # about the square root of float32's largest value (3.4e38)
_GIB = 1024.0**3


def check_intensity_image(image, *, name: str) -> None:
    """Refuse an image that cannot be a recorded intensity.

    Parameters
    ----------
    image : 2-D float array
        Intensities (any unit).
    name : str
        The file or layer, for the message.

    Raises
    ------
    InputError
        NaN or infinite pixels; every pixel equal (all-zero included: nothing was recorded);
        negative values below -10 % of the maximum (dark-frame noise stays above that); or
        values whose square overflows float32 (above 1.8e19).
    """
    import numpy as np

    finite = np.isfinite(image)
    if not finite.all():
        raise InputError(f"{name}: contains NaN or infinite values ({int(np.count_nonzero(~finite))} pixels)")
    low, high = float(image.min()), float(image.max())
    if low == high:
        raise InputError(f"{name}: every pixel is {low:g}; expected a recorded hologram (an image with fringes)")
    if low < -_NEGATIVE_TOLERANCE * max(high, 0.0):
        raise InputError(f"{name}: has negative intensities down to {low:g} (maximum {high:g}); expected a recorded intensity (>= 0)")
    if max(high, -low) > _LARGEST_INTENSITY:  # the propagation squares fields: beyond this the float32 squares overflow to inf and planes come out 0
        raise InputError(f"{name}: has intensities up to {max(high, -low):g}; expected at most {_LARGEST_INTENSITY:.3g} (their squares must fit in float32): rescale the image")


def _finite_number(value, *, key: str, low: float, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not hasattr(value, "__float__"):
        raise InputError(f"{key}: expected a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number) or not low <= number <= high:
        raise InputError(f"{key}: expected a finite number in [{low:g}, {high:g}], got {number!r}")
    return number


def check_number(value, *, key: str, low: float = -math.inf, high: float = math.inf, above: bool = False) -> float:
    """``value`` as a finite float in ``[low, high]`` (``(low, high]`` with ``above``); `InputError` naming ``key`` otherwise.

    The wording is the console script's for a flag, so the API and the flags refuse alike.
    """
    try:
        number = float(value) if not isinstance(value, (bool, str)) and value is not None else math.nan
    except (TypeError, ValueError, OverflowError):
        number = math.nan
    if not math.isfinite(number) or number < low or (above and number == low) or number > high:
        bounds = f"{'above' if above else 'at least'} {low:g}" + (f" and at most {high:g}" if math.isfinite(high) else "") if math.isfinite(low) else f"at most {high:g}"
        shown = f"{number:g}" if math.isfinite(number) or isinstance(value, float) else repr(value)[:40]
        raise InputError(f"{key}: expected a finite number {bounds}, got {shown}")
    return number


def check_holo_params(params: Mapping, *, name: str) -> dict[str, float]:
    """Check Holo-processing parameters (``N_R``, ``N_sigma``, ``gamma``) against `HOLO_PARAM_RANGES`.

    Returns
    -------
    dict
        The three values as floats.

    Raises
    ------
    InputError
        A parameter missing, not a number, NaN/infinite or outside its range; the message reads
        ``NAME.gamma: expected a finite number in [0.05, 20], got nan``.
    """
    if not isinstance(params, Mapping):
        raise InputError(f"{name}: expected an object with N_R, N_sigma and gamma, got {type(params).__name__}")
    values = {}
    for key, (low, high) in HOLO_PARAM_RANGES.items():
        if key not in params:
            raise InputError(f"{name}.{key}: missing; expected N_R, N_sigma and gamma")
        values[key] = _finite_number(params[key], key=f"{name}.{key}", low=low, high=high)
    return values


def check_calibration(payload: Mapping, *, name: str) -> None:
    """Check a calibration JSON (docs/formats.md) before anything uses it: ``params`` present and in range."""
    if "params" not in payload:
        raise InputError(f"{name}: not a calibration file (no params)")
    check_holo_params(payload["params"], name=f"{name}: params")


def _available_memory_bytes() -> int:
    try:  # Linux: what can be allocated without swapping
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_memory(required_bytes: float, *, what: str, remedy: str) -> None:
    """Refuse work whose arrays would not fit in the memory available now.

    Parameters
    ----------
    required_bytes : float
        An estimate of the peak memory the work needs (bytes).
    what : str
        What needs it, e.g. ``"61 planes of 1024x1024 pixels"``.
    remedy : str
        What to change, naming the flag or key, e.g. ``"raise volume.z_step_um"``.
    """
    available = _available_memory_bytes()
    if required_bytes > available:
        raise InputError(f"{what}: about {required_bytes / _GIB:.1f} GiB of memory needed, {available / _GIB:.1f} GiB available; {remedy}")


def check_disk(required_bytes: float, path: Path, *, what: str, remedy: str) -> None:
    """Refuse writing ``required_bytes`` (bytes) to ``path`` when its file system has less free space."""
    folder = Path(path).parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    free = shutil.disk_usage(folder).free
    if required_bytes > free:
        raise InputError(f"{path}: {what}: {required_bytes / _GIB:.1f} GiB to write, {free / _GIB:.1f} GiB free there; {remedy}")


def _resolved(path: Path, *, culprit: str) -> Path:
    """``path.resolve()``, with a loop of symbolic links refused naming ``culprit``."""
    try:
        return path.resolve()
    except (RuntimeError, OSError) as error:  # Python 3.11 raises RuntimeError for a loop, 3.13 OSError
        raise InputError(f"{culprit}: is a loop of symbolic links ({type(error).__name__}); name the file itself") from None


def check_output_path(path: str | Path, *, flag: str, folder: bool = False, inputs: Iterable[str | Path | None] = (), force: bool = False,
                      writes: Iterable[str] = ()) -> Path:
    """Refuse an output before any work: the one rule every writer follows.

    A file output must be a new name or, with ``force``, an existing regular file
    (`check_target`: never a link, a device or a FIFO). A folder output may exist; the files
    the command writes into it (``writes``) follow the file rule, so a folder holding none of
    them is used as it is, and one holding any of them needs ``force``.

    Parameters
    ----------
    path : path
        Where the command will write.
    flag : str
        The flag that named it (``--out``), for the message.
    folder : bool
        The output is a folder (created if needed) rather than a file.
    inputs : paths
        The command's inputs; an output on any of them is refused, ``force`` or not.
    force : bool
        Replace existing outputs (the user's ``--force``).
    writes : names
        A folder output: the names of the files the command writes into it.

    Raises
    ------
    InputError
        The output is one of the inputs; a folder where a file goes or a file where a folder
        goes; a link, device or FIFO where a file goes; an existing output without ``force``;
        a parent that is a file; a parent folder that cannot be written.
    """
    path = Path(path)
    resolved = _resolved(path, culprit=f"{flag} {path}")
    targets = [path / name for name in writes] if folder else [path]
    for name in inputs:
        if name and any(_resolved(Path(name), culprit=str(name)) in (resolved, _resolved(target, culprit=f"{flag} {target}")) for target in targets):
            raise InputError(f"{flag} {path}: would overwrite the input {name}")
    if folder and path.exists() and not path.is_dir():
        raise InputError(f"{flag} {path}: is a file; expected a folder")
    for target in targets:
        check_target(target, force=force, flag=flag)
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise InputError(f"{flag} {path}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {path}: cannot write in {ancestor} (permission denied)")
    return path


def _integer(value, *, key: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise InputError(f"{key}: expected an integer in [{low}, {high}], got {value!r}")
    return value


def _is_finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _numbers(value, *, key: str) -> list[float]:
    if not isinstance(value, list) or not value or not all(_is_finite_number(v) for v in value):
        raise InputError(f"{key}: expected a non-empty list of finite numbers")
    return value


def _mapping(value, *, key: str) -> dict:
    if not isinstance(value, dict):
        raise InputError(f"{key}: expected an object, got {type(value).__name__}")
    return value


def check_dataset_manifest(spec: dict, *, name: str, formats: Mapping[str, Collection[int]]) -> dict:
    """Check a data set's ``dataset.json`` before any group is opened.

    Parameters
    ----------
    spec : dict
        The parsed manifest (`read_json_object`).
    name : str
        The manifest's path, for messages.
    formats : mapping
        ``{format tag: readable versions}``.

    Raises
    ------
    InputError
        Another format or version, or a key the readers need missing or ill-typed
        (``groups``, ``tile_size``, ``planes_um``, ``config``, ``processing``).
    """
    tag, version = spec.get("format"), spec.get("version")
    if tag not in formats or version not in formats[tag]:
        expected = "; ".join(f"{t} version {' or '.join(map(str, v))}" for t, v in formats.items())
        raise InputError(f"{name}: expected format {expected}, got {tag} {version}")
    _integer(spec.get("groups"), key=f"{name}: groups", low=0, high=10**7)
    _integer(spec.get("tile_size"), key=f"{name}: tile_size", low=16, high=8192)
    _numbers(spec.get("planes_um"), key=f"{name}: planes_um")
    _mapping(spec.get("config"), key=f"{name}: config")
    _mapping(spec.get("processing"), key=f"{name}: processing")
    return spec


def check_model_payload(
    payload, *, name: str, formats: Mapping[str, Collection[int]], presets: Mapping[str, tuple[int, ...]], formulations: Collection[str]
) -> dict:
    """Check a loaded model file's dict and return its ``meta``, before any network is built.

    Parameters
    ----------
    payload : object
        What ``torch.load(..., weights_only=True)`` returned.
    name : str
        The file, for messages.
    formats : mapping
        ``{format tag: readable versions}``.
    presets : mapping
        The network presets; ``meta.widths`` must be one of them, so no file can make us
        allocate a network larger than the largest preset.
    formulations : collection of str
        Known formulations; a file without one is the ``seed`` formulation (version 1).

    Returns
    -------
    dict
        ``meta``, with ``formulation`` filled in.

    Raises
    ------
    InputError
        Another format or version; ``state_dict`` not a mapping; ``meta`` not a JSON object;
        ``widths`` not a preset's; channel counts not small positive integers; ``config``
        not a valid experiment config; an unknown formulation.
    """
    from napari_lbs._core.foundation._config import ExperimentConfig

    if not isinstance(payload, dict) or payload.get("format") not in formats or payload.get("version") not in formats[payload.get("format")]:
        expected = "; ".join(f"a {t} file of version {' or '.join(map(str, v))}" for t, v in formats.items())
        raise InputError(f"{name}: expected {expected}")
    if not isinstance(payload.get("state_dict"), dict):
        raise InputError(f"{name}: has no weights (state_dict is not a mapping)")
    text = payload.get("meta")
    try:
        meta = json.loads(text) if isinstance(text, (str, bytes)) else None
    except json.JSONDecodeError:
        meta = None
    if not isinstance(meta, dict):
        raise InputError(f"{name}: its meta is not a JSON object")
    if meta.setdefault("formulation", "seed") not in formulations:
        raise InputError(f"{name}: unknown formulation {meta['formulation']!r}; expected one of {', '.join(formulations)}")
    widths = meta.get("widths")
    allowed = {tuple(w): preset for preset, w in presets.items()}
    if not isinstance(widths, list) or not all(isinstance(w, int) and not isinstance(w, bool) for w in widths) or tuple(widths) not in allowed:
        raise InputError(f"{name}: meta.widths {str(widths)[:60]} is not a preset's ({', '.join(f'{p} {list(w)}' for p, w in presets.items())})")
    _integer(meta.setdefault("in_channels", 1), key=f"{name}: meta.in_channels", low=1, high=256)
    _integer(meta.setdefault("out_channels", 1), key=f"{name}: meta.out_channels", low=1, high=8)
    _integer(meta.get("tile_size"), key=f"{name}: meta.tile_size", low=16, high=8192)
    try:
        ExperimentConfig.from_dict(_mapping(meta.get("config"), key=f"{name}: meta.config"))
    except ConfigError as error:
        raise InputError(f"{name}: meta.config: {error}") from None
    return meta


_PREDICTION_KEYS = {
    "seed": {"threshold": "number", "output_scale": "number", "full_value": "number"},
    "focus": {"threshold": "number", "step_um": "number", "diameter_scale_um": "number", "lateral_um": "number", "context": "integers"},
}


def check_prediction_meta(meta: dict, *, name: str) -> None:
    """Refuse a model whose meta lacks what prediction reads (a file saved before training finished an epoch, or edited)."""
    _numbers(meta.get("planes_um"), key=f"{name}: meta.planes_um")
    processing = _mapping(meta.get("processing"), key=f"{name}: meta.processing")
    if not isinstance(processing.get("invert_experiment"), bool) or processing.get("mode") not in ("robust", "seed"):
        raise InputError(f"{name}: meta.processing: expected invert_experiment (true/false) and mode (robust or seed)")
    for key, kind in _PREDICTION_KEYS[meta["formulation"]].items():
        value = meta.get(key)
        if kind == "integers":
            if not isinstance(value, list) or not value or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
                raise InputError(f"{name}: meta.{key}: expected a non-empty list of integers")
        else:
            _finite_number(value, key=f"{name}: meta.{key}", low=-math.inf, high=math.inf)


_RESUME_KEYS = {"state_dict": dict, "optimizer": dict, "schedule": dict, "epoch": int, "log": str, "numpy_rng": str}


def load_resume_state(path: str | Path) -> dict:
    """Read a training state (``MODEL.last.pt``) without executing code, and check its shape.

    Returns
    -------
    dict
        The state as saved (``log`` and ``numpy_rng`` are JSON text, checked to parse).

    Raises
    ------
    InputError
        Not a torch file, a pickle with code, truncated, or a key missing or ill-typed; the
        message names the file and says to delete it or train without ``--resume``.
    """
    import torch

    path = Path(path)
    remedy = "delete it or train without --resume"
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # truncated, another format, or a pickle that would run code: all refused alike
        raise InputError(f"{path}: not a training state ({type(error).__name__}); {remedy}") from None
    if not isinstance(state, dict):
        raise InputError(f"{path}: not a training state (a {type(state).__name__}); {remedy}")
    for key, kind in _RESUME_KEYS.items():
        if not isinstance(state.get(key), kind) or isinstance(state.get(key), bool):
            raise InputError(f"{path}: {key} missing or not a {kind.__name__}; {remedy}")
    if not isinstance(state.get("torch_rng"), torch.Tensor) or state["torch_rng"].dtype != torch.uint8:
        raise InputError(f"{path}: torch_rng missing or not a byte tensor; {remedy}")
    try:
        log, rng = json.loads(state["log"]), json.loads(state["numpy_rng"])
    except json.JSONDecodeError:
        raise InputError(f"{path}: log or numpy_rng is not valid JSON; {remedy}") from None
    if not isinstance(log, dict) or not isinstance(log.get("settings"), dict) or "dataset" not in log or not isinstance(rng, dict):
        raise InputError(f"{path}: its log has no settings or data set; {remedy}")
    return state


def check_resume_matches(state: dict, log: dict, *, name: str, free: Collection[str]) -> None:
    """Refuse to resume from a training state made otherwise, or one that has nothing left to do.

    Parameters
    ----------
    state : dict
        From `load_resume_state`.
    log : dict
        The new run's log so far, with its ``settings`` and ``dataset``.
    name : str
        The state file, for messages.
    free : collection of str
        Settings that may change between the runs (the budget: epochs, minutes, patience).

    Raises
    ------
    InputError
        Naming the first setting that differs (``device='auto', the state has 'cpu'``), a
        different data set, or ``epochs`` no larger than the epochs the state has finished.
    """
    previous = json.loads(state["log"])
    current = json.loads(json.dumps(log["settings"]))
    for key in sorted(set(previous["settings"]) | set(current)):
        if key not in free and previous["settings"].get(key) != current.get(key):
            raise InputError(f"{name}: was made with {key}={previous['settings'].get(key)!r}, this run has {current.get(key)!r}; use the same setting or delete it to train afresh")
    if previous["dataset"] != json.loads(json.dumps(log["dataset"])):
        raise InputError(f"{name}: was made with another data set (or other groups of it); delete it to train afresh")
    if state["epoch"] >= current["epochs"]:
        raise InputError(f"{name}: has finished {state['epoch']} epochs already; ask for more epochs to continue (epochs={current['epochs']})")
