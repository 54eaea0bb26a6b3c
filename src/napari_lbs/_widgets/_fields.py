"""The fields of a step's form: making them, reading what they name, and why an input or output is unusable.

Each ``*_problem`` function returns the reason Run stays disabled (None when the field is
fine); the readers turn a field's text into the path, config, effects or hologram it names.
"""

from __future__ import annotations

import inspect
import os
import re
from pathlib import Path

import numpy as np
from magicgui.widgets import FileEdit, Label, LineEdit
from qtpy.QtWidgets import QSizePolicy

from napari_lbs._core import load_config
from napari_lbs._core.foundation import as_hologram

__all__ = [
    "chosen", "config_from", "config_problem", "doc_of", "effects_problem", "hologram_data", "hologram_problem", "missing", "model_config", "model_problem", "output_problem",
    "parsed_effects", "path_edit", "replacing", "wrapping_label",
]


def doc_of(obj, name: str) -> str:
    """The description of ``name`` in the Parameters/Attributes section of ``obj``'s numpy docstring ("" if absent)."""
    lines = (inspect.getdoc(obj) or "").splitlines()
    for index, line in enumerate(lines):
        match = re.match(r"^([\w, ]+?)\s*(?::\s*(.*))?$", line)
        if not match or line.startswith(" ") or name not in [n.strip() for n in match.group(1).split(",")]:
            continue
        body = []
        for following in lines[index + 1 :]:
            if following and not following.startswith(" "):
                break
            body.append(following.strip())
        text = " ".join(part for part in body if part).replace("``", "").replace("`", "")
        kind = match.group(2)
        return f"{text} ({kind})" if text and kind else text or (kind or "")
    return ""


def wrapping_label() -> Label:
    """A status label that wraps and never widens its dock (long paths are cut, the whole text is the tooltip)."""
    label = Label(value="")
    label.native.setWordWrap(True)
    label.native.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
    label.native.setMinimumWidth(40)
    return label


def path_edit(*, label: str, name: str, mode: str = "r", filter: str | None = None, value: str = "", placeholder: str = "", tooltip: str = "") -> FileEdit:
    """A path field whose empty text means "none" (magicgui would show the current folder); ``placeholder`` says what empty means."""
    edit = FileEdit(label=label, name=name, mode=mode, filter=filter, nullable=True, value=None, tooltip=tooltip)
    edit.line_edit.value = value
    edit.line_edit.native.setPlaceholderText(placeholder)
    return edit


def chosen(edit: FileEdit) -> Path | None:
    """The path a field names, or None when its text is empty."""
    text = edit.line_edit.value.strip()
    return Path(text).expanduser() if text else None


def missing(edit: FileEdit, label: str) -> str | None:
    """Why an optional input file is invalid (named but absent), or None."""
    path = chosen(edit)
    return f"{label}: {path} not found" if path is not None and not path.is_file() else None


def output_problem(edit: FileEdit, label: str, *, folder: bool = False, suffix: str | None = None) -> str | None:
    """Why an output path cannot be written (empty, a folder where a file is meant, no parent folder), or None."""
    path = chosen(edit)
    if path is None:
        return f"{label}: choose where to save"
    if folder:
        return f"{label}: {path} is a file, expected a folder" if path.is_file() else None
    if path.is_dir():
        return f"{label}: {path} is a folder, expected a file name"
    if suffix and path.suffix != suffix:
        return f"{label}: expected a name ending in {suffix}"
    if not path.absolute().parent.is_dir():
        return f"{label}: folder {path.absolute().parent} does not exist"
    return None


def config_from(edit: FileEdit):
    """The config a field names (empty: the defaults)."""
    return load_config(chosen(edit))


def model_config(edit: FileEdit):
    """The config a field names, or None when it is empty (the model's own config is used)."""
    path = chosen(edit)
    return load_config(path) if path is not None else None


def model_problem(edit: FileEdit) -> str | None:
    """Why a model field cannot be used (empty, or naming no file), or None."""
    if chosen(edit) is None:
        return "model file: choose a model (.pt) that Training wrote"
    return missing(edit, "model")


def parsed_effects(edit: LineEdit) -> dict:
    """The catalog effects typed into ``edit`` as on the command line (`parse_effects`), separated by ';'; raises `InputError` naming the field and the culprit."""
    from napari_lbs._core import parse_effects

    return parse_effects(edit.value.split(";"), flag=f"{edit.label}:")


def effects_problem(edit: LineEdit) -> str | None:
    """What is wrong with the effects typed into ``edit`` (`parsed_effects`), else None."""
    from napari_lbs._core import InputError

    try:
        parsed_effects(edit)
    except InputError as error:
        return str(error)
    return None


def config_problem(edit: FileEdit) -> str | None:
    problem = missing(edit, "config")
    if problem:
        return problem
    try:
        config_from(edit)
    except ValueError as error:
        return str(error)
    return None


def hologram_problem(layer) -> str | None:
    if layer is None:
        return "choose a hologram Image layer"
    if layer.rgb:
        return None  # reduced to one channel by as_hologram, with a notification
    if layer.ndim != 2:
        return f"hologram: expected a 2-D image, got {layer.ndim}-D layer {layer.name!r}"
    return None


def hologram_data(layer) -> np.ndarray:
    """A hologram layer's data as a 2-D array; an RGB reduction is told in a notification."""
    from napari.utils.notifications import show_info

    return as_hologram(np.asarray(layer.data), name=layer.name, log=show_info)


def replacing(paths) -> str | None:
    """The question before a run replaces files that exist (None when none does); confirmed, the run's request gets ``replace``.

    A path typed into a field was never asked about by a save dialog, so every step asks here.
    """
    existing = [str(path) for path in paths if os.path.lexists(path)]
    return f"{', '.join(existing)} exist{'s' if len(existing) == 1 else ''} and will be replaced" if existing else None

