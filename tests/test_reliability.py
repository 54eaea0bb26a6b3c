"""Files users share: modes under the umask, outputs that never overwrite inputs, SIGTERM like Ctrl-C."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from napari_lbs._cli import main
from napari_lbs._core import InputError, write_json


@pytest.fixture
def umask_002():
    previous = os.umask(0o002)
    yield
    os.umask(previous)


def test_written_files_honour_the_umask_and_keep_an_existing_mode(tmp_path, umask_002):
    new = write_json(tmp_path / "new.json", {"a": 1})
    assert new.stat().st_mode & 0o777 == 0o664  # group members can read a lab's results
    existing = tmp_path / "existing.json"
    existing.write_text("{}")
    existing.chmod(0o640)
    write_json(existing, {"b": 2})
    assert existing.stat().st_mode & 0o777 == 0o640 and json.loads(existing.read_text()) == {"b": 2}
    with pytest.raises(InputError, match="is a folder"):
        write_json(tmp_path, {})
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_predict_never_overwrites_a_model_log_an_input_or_writes_a_table_as_json(tmp_path, capsys):
    model, log, hologram = tmp_path / "m.pt", tmp_path / "m.json", tmp_path / "h.tif"
    model.write_bytes(b"not loaded: the output check comes first")
    log.write_text(json.dumps({"epochs": []}))
    hologram.write_bytes(b"")
    cases = [
        (["--out", str(tmp_path / "m.csv")], "is not this table's provenance"),
        (["--out", str(tmp_path / "p.json")], "expected a particle table"),
        (["--out", str(hologram)], "would overwrite the input HOLO"),
    ]
    for extra, message in cases:
        capsys.readouterr()
        assert main(["predict", str(hologram), "--model", str(model), *extra]) == 2
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and message in error[0], error
    assert json.loads(log.read_text()) == {"epochs": []}
    assert hologram.read_bytes() == b""


def test_sigterm_stops_a_command_like_ctrl_c_and_leaves_no_temporary_file(tmp_path):
    config = tmp_path / "c.toml"
    assert main(["config", "--write", str(config)]) == 0
    out = tmp_path / "data"
    process = subprocess.Popen([sys.executable, "-m", "napari_lbs._cli", "generate", "--config", str(config), "--groups", "200", "--out", str(out)],
                               stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list((out / "groups").glob("group_*.tif")) if (out / "groups").is_dir() else True:
        assert time.monotonic() < deadline and process.poll() is None
        time.sleep(0.1)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert "interrupted" in stderr and "Traceback" not in stderr
    leftovers = [p.name for p in out.rglob(".*")]
    assert not leftovers, leftovers
    assert json.loads((out / "dataset.json").read_text())["complete"] is False
