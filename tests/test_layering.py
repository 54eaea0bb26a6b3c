import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_core_imports_without_qt_napari_magicgui_or_torch():
    code = (
        "import sys, napari_lbs._core\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('napari', 'qtpy', 'PyQt5', 'PyQt6', 'PySide2', 'PySide6', 'magicgui', 'torch', 'vispy')]\n"
        "assert not bad, bad\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_import_layers_hold():
    """The contracts in .importlinter: no cycles, foundation below the rest, _core headless, fronts apart."""
    result = subprocess.run(
        [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports; sys.exit(lint_imports(config_filename='.importlinter', no_cache=True, no_logo=True))"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT / "src").with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _wing(module: str) -> str | None:
    """The wing of a module under ``napari_lbs._core`` (``physics`` for ``napari_lbs._core.physics._optics``), else None."""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[:2] == ["napari_lbs", "_core"] else None


def test_no_private_module_or_name_is_imported_across_wings():
    """Code outside a wing imports its names from the wing (``napari_lbs._core.physics``), never from its modules, and no name starting with ``_``."""
    import ast

    offences = []
    for path in sorted((ROOT / "src" / "napari_lbs").rglob("*.py")):
        importer = _module_name(path)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not (isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("napari_lbs._core.")):
                continue
            target = _wing(node.module)
            if target == _wing(importer):
                continue
            deep = node.module.count(".") > 2
            private = [alias.name for alias in node.names if alias.name.startswith("_")]
            if deep or private:
                offences.append(f"{importer}: from {node.module} import {', '.join(a.name for a in node.names)}")
    assert not offences, "\n".join(offences)


def test_every_wing_is_in_the_layers_contract_and_exports_what_it_names():
    """A new wing must be placed in .importlinter's wings contract; each wing's exports resolve."""
    import importlib

    config = (ROOT / ".importlinter").read_text(encoding="utf-8")
    wings = sorted(p.parent.name for p in (ROOT / "src" / "napari_lbs" / "_core").glob("*/__init__.py"))
    layers = config.split("[importlinter:contract:wings]")[1].split("[importlinter:")[0].split("layers =")[1]
    layered = {name.strip(" ()") for line in layers.splitlines() for name in line.replace(":", "|").split("|") if name.strip()}
    for wing in wings:
        assert wing in layered, f"wing {wing} is not in the wings contract"
        module = importlib.import_module(f"napari_lbs._core.{wing}")
        for name in module.__all__:
            assert getattr(module, name) is not None, f"{wing}.{name}"
