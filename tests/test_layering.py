import subprocess
import sys


def test_core_imports_without_qt_napari_magicgui_or_torch():
    code = (
        "import sys, napari_lbs._core\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('napari', 'qtpy', 'PyQt5', 'PyQt6', 'PySide2', 'PySide6', 'magicgui', 'torch', 'vispy')]\n"
        "assert not bad, bad\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_core_sources_never_import_gui_packages():
    from pathlib import Path

    import napari_lbs._core as core

    for path in Path(core.__file__).parent.glob("*.py"):
        text = path.read_text()
        for banned in ("import napari\n", "from napari ", "from napari.", "import napari.", "qtpy", "magicgui", "PyQt"):
            assert banned not in text, f"{path.name} imports {banned.strip()}"
