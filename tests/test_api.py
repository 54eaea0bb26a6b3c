"""The scripting API: `napari_lbs._core.__all__` is curated, every name resolves, and docs/api.md documents exactly those names."""

import re
import subprocess
import sys
from pathlib import Path

import napari_lbs._core as core

API_DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def test_all_is_curated_and_every_name_resolves():
    assert 8 <= len(core.__all__) <= 60
    assert len(set(core.__all__)) == len(core.__all__)
    for name in core.__all__:
        assert not name.startswith("_")
        assert getattr(core, name) is not None


def test_api_page_documents_exactly_the_listed_names():
    documented = re.findall(r"^### `([A-Za-z_][A-Za-z0-9_]*)`$", API_DOC.read_text(), re.M)
    assert len(documented) == len(set(documented)), "a name documented twice in docs/api.md"
    assert sorted(documented) == sorted(core.__all__), (
        f"in __all__ but not in docs/api.md: {sorted(set(core.__all__) - set(documented))}; "
        f"in docs/api.md but not in __all__: {sorted(set(documented) - set(core.__all__))}"
    )


def test_api_page_examples_import_only_listed_names():
    for block in re.findall(r"```python\n(.*?)```", API_DOC.read_text(), re.S):
        for names in re.findall(r"^from napari_lbs\._core import (.+)$", block, re.M):
            unknown = {name.strip() for name in names.split(",")} - set(core.__all__)
            assert not unknown, f"docs/api.md imports private names {unknown}"


def test_private_names_are_not_handed_out():
    code = "import napari_lbs._core as c\ntry:\n    c.write_json\nexcept AttributeError:\n    pass\nelse:\n    raise SystemExit('write_json is public')\n"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_api_page_examples_run_in_order(tmp_path, monkeypatch):
    """Each section's example runs as it stands (the later ones use the files the earlier ones wrote)."""
    monkeypatch.chdir(tmp_path)
    for number, block in enumerate(re.findall(r"```python\n(.*?)```", API_DOC.read_text(), re.S)):
        exec(compile(block, f"docs/api.md example {number}", "exec"), {})
