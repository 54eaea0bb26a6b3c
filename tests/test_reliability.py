"""Reliability: bad input is a one-line refusal naming the culprit, with nothing written;
files users share keep the umask's mode; outputs never overwrite inputs; SIGTERM unwinds like
Ctrl-C; the CLI starts fast. The property tests throw generated bad inputs at the readers and at
each sub-command's flags (docs/reliability.md)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from napari_lbs._cli import main
from napari_lbs._core import InputError
from napari_lbs._core.foundation._files import write_json
from napari_lbs._core.foundation._io import PARTICLE_COLUMNS


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
        (["--out", str(tmp_path / "m.csv")], f"{log}: exists; add --force"),
        (["--out", str(tmp_path / "m.csv"), "--force"], "is not this table's provenance"),
        (["--out", str(tmp_path / "p.json")], "expected a particle table"),
        (["--out", str(hologram)], f"would overwrite the input {hologram}"),
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


# --- start-up -------------------------------------------------------------------------------

def test_the_cli_starts_without_numpy_scipy_or_torch():
    code = "import sys, napari_lbs._cli; print(sorted(m for m in ('numpy', 'scipy', 'torch', 'tifffile') if m in sys.modules))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "[]", loaded

    def seconds(*command):
        start = time.perf_counter()
        subprocess.run([sys.executable, *command], capture_output=True, check=True)
        return time.perf_counter() - start

    baseline = min(seconds("-c", "pass") for _ in range(3))
    version = min(seconds("-m", "napari_lbs._cli", "--version") for _ in range(3))
    print(f"napari-lbs --version: {version:.3f} s, bare python: {baseline:.3f} s")
    assert version - baseline < 0.5  # half a second over bare Python, generous on a busy machine


# --- one-line refusals: generated bad inputs --------------------------------------------------

FAST = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def refusal(capsys, argv) -> str:
    """Run ``napari-lbs ARGV`` in-process; assert exit 2 and one line on stderr; return that line."""
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exit_:  # argparse refuses a flag value itself
        code = exit_.code
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err)
    assert out == ""
    return lines[0]


@pytest.fixture
def workspace(tmp_path):
    config = tmp_path / "c.toml"
    assert main(["config", "--write", str(config)]) == 0
    hologram = tmp_path / "h.tif"
    tifffile.imwrite(hologram, 1.0 + 0.1 * np.random.default_rng(0).random((64, 64), np.float32))
    truth = tmp_path / "truth.csv"
    truth.write_text("x_um,y_um,z_um,diameter_um\n10,20,3000,25\n")
    return tmp_path


def nothing_written(folder, before: set) -> bool:
    return {p.name for p in folder.rglob("*")} == before


_GOOD_ROW = ["1.5", "2", "3000", "25"]
def _spells_a_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


_BAD_TABLES = st.one_of(
    st.integers(1, 3).map(lambda k: ("short row", ",".join(PARTICLE_COLUMNS) + "\n" + ",".join(_GOOD_ROW) + "\n" + ",".join(_GOOD_ROW[:k]) + "\n")),
    st.integers(1, 3).map(lambda k: ("long row", ",".join(PARTICLE_COLUMNS) + "\n" + ",".join(_GOOD_ROW + ["9"] * k) + "\n")),
    st.sampled_from(PARTICLE_COLUMNS).map(lambda c: ("duplicate", ",".join(PARTICLE_COLUMNS) + f",{c}\n" + ",".join(_GOOD_ROW) + ",1\n")),
    st.sampled_from(PARTICLE_COLUMNS).map(lambda c: ("missing", ",".join(x for x in PARTICLE_COLUMNS if x != c) + "\n1,2,3\n")),
    # letters that spell a number ("INF", "nan") are numbers: the finite cases below cover them
    st.tuples(st.sampled_from(PARTICLE_COLUMNS), st.text(st.characters(whitelist_categories=("L",)), min_size=1, max_size=5).filter(lambda t: not _spells_a_number(t))).map(
        lambda a: ("not numeric", ",".join(PARTICLE_COLUMNS) + "\n" + ",".join(a[1] if c == a[0] else "1" for c in PARTICLE_COLUMNS) + "\n")),
    st.sampled_from(["nan", "inf", "-inf"]).map(lambda v: ("not finite", ",".join(PARTICLE_COLUMNS) + f"\n{v},1,3000,25\n")),
    st.sampled_from(["inf", "-INF", "Infinity"]).map(lambda v: ("infinite diameter", ",".join(PARTICLE_COLUMNS) + f"\n1,1,3000,{v}\n")),
    st.just(("empty", "")),
)


@FAST
@given(case=_BAD_TABLES, latin1=st.booleans())
def test_bad_particle_tables_are_refused_naming_the_file(workspace, capsys, case, latin1):
    _, text = case
    bad = workspace / "bad.csv"
    # a non-UTF-8 file (Latin-1 with an accented column name) is refused as such, whatever else is wrong
    bad.write_bytes(text.encode("utf-8") if not latin1 else ("x_um,y_um,z_um,diameter_um,dur\xe9e\n1,2,3000,25,1\n" + text).encode("latin-1", errors="replace"))
    before = {p.name for p in workspace.rglob("*")}
    line = refusal(capsys, ["evaluate", str(bad), str(workspace / "truth.csv"), "--json"])
    assert "bad.csv" in line
    assert nothing_written(workspace, before)


def test_a_byte_order_mark_is_accepted_and_an_empty_reference_gives_strict_json(workspace, capsys):
    table = workspace / "excel.csv"
    table.write_bytes("\ufeffx_um,y_um,z_um,diameter_um\r\n10,20,3000,25\r\n".encode("utf-8"))
    empty = workspace / "empty.csv"
    empty.write_text("x_um,y_um,z_um,diameter_um\n")
    capsys.readouterr()
    assert main(["evaluate", str(table), str(workspace / "truth.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["tp"] == 1
    assert main(["evaluate", str(table), str(empty), "--json"]) == 0
    json.loads(capsys.readouterr().out, parse_constant=lambda name: pytest.fail(f"{name} in the metrics JSON"))


_BAD_NUMBERS = st.one_of(st.sampled_from([float("nan"), float("inf"), -float("inf"), "0.5", None, [1.0], True]), st.floats(-1e6, -1.01), st.floats(20.01, 1e6))


@FAST
@given(key=st.sampled_from(["N_R", "N_sigma", "gamma"]), value=_BAD_NUMBERS, drop=st.booleans())
def test_bad_calibration_parameters_are_refused_before_any_work(workspace, capsys, key, value, drop):
    params = {"N_R": -0.5, "N_sigma": 0.3, "gamma": 0.9}
    if drop:
        del params[key]
    else:
        params[key] = value
    calibration = workspace / "calib.json"
    calibration.write_text(json.dumps({"params": params}))  # NaN and Infinity as Python's json writes them
    out = workspace / "data"
    line = refusal(capsys, ["generate", "--config", str(workspace / "c.toml"), "--calibration", str(calibration), "--groups", "2", "--out", str(out)])
    assert "calib.json" in line and key in line
    assert not out.exists()


# (sub-command and its other arguments, flag, values the flag must refuse)
_FLAGS = [
    (["simulate", "--config", "{c}", "--out", "{out}"], "--size", st.integers(-10, 15)),
    (["simulate", "--config", "{c}", "--out", "{out}"], "--particles", st.integers(-100, -1)),
    (["simulate", "--config", "{c}", "--out", "{out}"], "--seed", st.integers(-(2**40), -1)),
    (["calibrate", "{h}", "--config", "{c}", "--out", "{out}.json"], "--population", st.integers(-5, 3)),
    (["calibrate", "{h}", "--config", "{c}", "--out", "{out}.json"], "--generations", st.integers(-5, 0)),
    (["calibrate", "{h}", "--config", "{c}", "--out", "{out}.json"], "--runs", st.integers(-5, 0)),
    (["generate", "--config", "{c}", "--out", "{out}"], "--groups", st.integers(-5, 0)),
    (["generate", "--config", "{c}", "--out", "{out}"], "--workers", st.integers(-5, 0)),
    (["generate", "--config", "{c}", "--out", "{out}"], "--context-planes", st.integers(-5, -1) | st.integers(65, 10**6)),
    (["train", "{out}", "--out", "{out}.pt"], "--epochs", st.integers(-5, 0)),
    (["train", "{out}", "--out", "{out}.pt"], "--batch-size", st.integers(-5, 0)),
    (["train", "{out}", "--out", "{out}.pt"], "--minutes", st.floats(-1e9, -1e-9) | st.sampled_from([float("nan"), float("inf")])),
    (["train", "{out}", "--out", "{out}.pt"], "--learning-rate", st.floats(-1e3, 0.0) | st.floats(1.0, 1e3) | st.just(float("nan"))),
    (["train", "{out}", "--out", "{out}.pt"], "--foreground-weight", st.floats(-1e3, 0.999) | st.just(float("nan"))),
    (["diagnose", "{h}", "--config", "{c}", "--out", "{out}"], "--tile", st.integers(-5, 0) | st.integers(33, 10**6)),  # h.tif: 64 px a side
    (["evaluate", "{t}", "{t}"], "--axial-tol-um", st.floats(-1e6, 0.0) | st.sampled_from([float("nan"), float("inf"), -float("inf")])),
    (["evaluate", "{t}", "{t}"], "--lateral-tol-um", st.floats(-1e6, 0.0) | st.sampled_from([float("nan"), float("inf")])),
]


@FAST
@given(data=st.data(), case=st.sampled_from(_FLAGS), garbage=st.sampled_from([None, "x", "", "1,5", "0x10"]))
def test_bad_flag_values_exit_2_naming_the_flag(workspace, capsys, data, case, garbage):
    command, flag, values = case
    value = garbage if garbage is not None else str(data.draw(values))
    out = workspace / "out"
    names = {"c": workspace / "c.toml", "h": workspace / "h.tif", "t": workspace / "truth.csv", "out": out}
    before = {p.name for p in workspace.rglob("*")}
    line = refusal(capsys, [a.format(**names) for a in command] + [flag, value])
    assert flag in line, line
    assert nothing_written(workspace, before)


_NOT_INTENSITIES = st.one_of(
    st.floats(0, 1e6).map(lambda v: np.full((64, 64), v, np.float32)),  # all-zero or constant
    st.floats(0.5, 1e3).map(lambda s: -s * np.random.default_rng(1).random((64, 64)).astype(np.float32)),  # negative
    st.sampled_from([np.nan, np.inf]).map(lambda v: np.where(np.eye(64) > 0, v, 1.0).astype(np.float32)),
)


@FAST
@given(image=_NOT_INTENSITIES, command=st.sampled_from(["diagnose", "backprop", "calibrate", "predict"]))
def test_images_that_are_no_intensity_are_refused_by_every_command(workspace, capsys, image, command):
    bad = workspace / "bad.tif"
    tifffile.imwrite(bad, image)
    out = workspace / ("out.csv" if command == "predict" else "out.tif" if command == "backprop" else "out.json" if command == "calibrate" else "out")
    extra = ["--model", str(workspace / "never-loaded.pt")] if command == "predict" else ["--config", str(workspace / "c.toml")]
    before = {p.name for p in workspace.rglob("*")}
    line = refusal(capsys, [command, str(bad), *extra, "--out", str(out)])
    assert "bad.tif" in line
    assert nothing_written(workspace, before)


_META_DAMAGE = st.sampled_from([
    ("widths", None), ("widths", "small"), ("widths", [4096, 4096, 4096]), ("widths", [8, 16]), ("tile_size", None), ("tile_size", 10**9),
    ("in_channels", 0), ("in_channels", "3"), ("out_channels", 10**6), ("config", None), ("config", {"optics": {"wavelength_um": float("nan")}}),
    ("formulation", "magic"),
])


@FAST
@given(damage=_META_DAMAGE, as_text=st.sampled_from(["json", "not json", "missing", "list"]))
def test_damaged_model_files_are_refused_before_a_network_is_built(tmp_path, damage, as_text):
    import torch

    from napari_lbs._core import load_config, load_model

    meta = {"preset": "small", "widths": [8, 16, 32, 64, 64], "tile_size": 48, "config": load_config(None).to_dict()}
    key, value = damage
    if value is None:
        del meta[key]
    else:
        meta[key] = value
    text = {"json": json.dumps(meta), "not json": json.dumps(meta)[:-1], "missing": None, "list": json.dumps([meta])}[as_text]
    payload = {"format": "napari-lbs-model", "version": 2, "state_dict": {}}
    if text is not None:
        payload["meta"] = text
    path = tmp_path / "damaged.pt"
    torch.save(payload, path)
    with pytest.raises(InputError) as refused:
        load_model(path)
    message = str(refused.value)
    assert "damaged.pt" in message and "\n" not in message
    if as_text == "json":
        assert key in message or (key == "preset")


@FAST
@given(step=st.floats(1e-9, 0.49))
def test_a_config_asking_for_too_many_planes_is_refused_by_config_check(workspace, capsys, step):
    config = workspace / "tiny-step.toml"
    config.write_text((workspace / "c.toml").read_text().replace("z_step_um = 50.0", f"z_step_um = {step!r}"))
    assert "volume.z_step_um" in refusal(capsys, ["config", "--check", str(config)])


# --- outputs, faults, strict JSON -------------------------------------------------------------

def test_outputs_are_refused_before_any_work(workspace, capsys):
    existing = workspace / "existing"
    existing.write_text("keep")
    folder = workspace / "folder"
    folder.mkdir()
    config, hologram = str(workspace / "c.toml"), str(workspace / "h.tif")
    cases = [
        (["simulate", "--config", config, "--out", str(existing)], "is a file; expected a folder"),
        (["diagnose", hologram, "--config", config, "--out", str(existing)], "is a file; expected a folder"),
        (["backprop", hologram, "--config", config, "--out", str(existing / "x.tif")], "existing is a file, not a folder"),
        (["calibrate", hologram, "--config", config, "--out", str(folder)], f"--out {folder}: is a folder"),
        (["backprop", hologram, "--config", config, "--out", hologram], "would overwrite the input"),
        (["config", "--write", str(folder)], "is a folder"),
    ]
    before = {p.name for p in workspace.rglob("*")}
    for argv, message in cases:
        line = refusal(capsys, argv)
        assert message in line, line
    assert nothing_written(workspace, before) and existing.read_text() == "keep"


# Every writing command: its file (or a file it writes into its folder) and the --out naming it.
_WRITERS = {
    "config": (["config"], "--write", "c2.toml", None),
    "simulate": (["simulate", "--config", "{config}", "--size", "32", "--particles", "2"], "--out", "sim", "particles.csv"),
    "backprop": (["backprop", "{holo}", "--config", "{config}"], "--out", "mine.tif", None),
    "calibrate": (["calibrate", "{holo}", "--config", "{config}"], "--out", "calib.json", None),
    "train": (["train", "{tmp}/data"], "--out", "model.pt", None),
    "predict": (["predict", "{holo}", "--model", "{tmp}/m.pt"], "--out", "mine.csv", None),
    "track": (["track", "{tmp}/truth.csv"], "--out", "tracks.csv", None),
    "diagnose": (["diagnose", "{holo}", "--config", "{config}"], "--out", "report", "report.md"),
    "demo": (["demo", "--quick"], "--out", "demo", "summary.json"),
}


def _writer(workspace, command: str, kind: str):
    """``napari-lbs COMMAND`` whose output file is a ``kind`` (exists, null, fifo, symlink); the argv, the target and the victim a link points to."""
    head, flag, name, inner = _WRITERS[command]
    argv = [part.format(config=workspace / "c.toml", holo=workspace / "h.tif", tmp=workspace) for part in head] + [flag, str(workspace / name)]
    if inner:
        (workspace / name).mkdir()
    target = workspace / name / inner if inner else workspace / name
    victim = workspace / "victim.txt"
    victim.write_text("keep")
    if kind == "exists":
        target.write_text("mine")
    elif kind == "fifo":
        os.mkfifo(target)
    elif kind == "symlink":
        target.symlink_to(victim)
    elif kind == "null":
        if inner:
            target.symlink_to("/dev/null")
        else:
            argv[-1] = "/dev/null"
            target = Path("/dev/null")
    return argv, target, victim


@pytest.mark.parametrize("kind", ["exists", "null", "fifo", "symlink"])
@pytest.mark.parametrize("command", list(_WRITERS))
def test_no_command_writes_through_a_device_fifo_or_link_or_replaces_a_file_without_force(workspace, capsys, command, kind):
    import stat

    argv, target, victim = _writer(workspace, command, kind)
    line = refusal(capsys, argv)
    assert str(target) in line, line
    expected = {"exists": "exists; add --force", "null": "not a regular file" if target == Path("/dev/null") else "symbolic link", "fifo": "not a regular file",
                "symlink": "symbolic link"}[kind]
    assert expected in line, line
    if kind != "exists":  # --force replaces regular files only
        assert expected in refusal(capsys, [*argv, "--force"])
    assert victim.read_text() == "keep" and stat.S_ISCHR(os.stat("/dev/null").st_mode)
    if kind == "exists":
        assert target.read_text() == "mine"
    elif kind == "fifo":
        assert stat.S_ISFIFO(os.lstat(target).st_mode)
    elif target != Path("/dev/null"):
        assert target.is_symlink()


def test_force_replaces_a_regular_file_keeping_its_mode_and_a_folder_holding_none_of_the_outputs_is_used(workspace, capsys, umask_002):
    config = workspace / "c.toml"
    config.write_text(config.read_text().replace("z_step_um = 50.0", "z_step_um = 1000.0"))
    stack = workspace / "mine.tif"
    stack.write_text("old")
    stack.chmod(0o640)
    argv = ["backprop", str(workspace / "h.tif"), "--config", str(config), "--out", str(stack)]
    assert "add --force" in refusal(capsys, argv)
    assert main([*argv, "--force"]) == 0
    assert tifffile.imread(stack).shape == (4, 64, 64) and stack.stat().st_mode & 0o777 == 0o640
    written = workspace / "c2.toml"
    assert main(["config", "--write", str(written)]) == 0 and written.stat().st_mode & 0o777 == 0o664
    assert "add --force" in refusal(capsys, ["config", "--write", str(written)])
    assert main(["config", "--write", str(written), "--force"]) == 0
    sim = workspace / "sim"
    sim.mkdir()
    (sim / "notes.txt").write_text("mine")
    simulate = ["simulate", "--config", str(config), "--out", str(sim), "--size", "32", "--particles", "2"]
    assert main(simulate) == 0 and (sim / "notes.txt").read_text() == "mine"
    assert "hologram.tif: exists; add --force" in refusal(capsys, simulate)
    assert main([*simulate, "--force", "--seed", "1"]) == 0
    assert not [p for p in workspace.rglob(".*") if p.is_file()]  # no temporary file left


def test_the_file_helpers_refuse_links_devices_and_fifos_and_clobber_only_with_force(tmp_path):
    from napari_lbs._core.foundation import atomic_write_bytes, check_target

    fifo, link, victim = tmp_path / "fifo", tmp_path / "link", tmp_path / "victim"
    os.mkfifo(fifo)
    victim.write_bytes(b"keep")
    link.symlink_to(victim)
    for path, message in ((fifo, "not a regular file"), (link, "symbolic link"), (tmp_path, "is a folder"), ("/dev/null", "not a regular file")):
        for force in (False, True):
            with pytest.raises(InputError, match=message):
                atomic_write_bytes(path, b"x", force=force)
    with pytest.raises(InputError, match=r"exists; add force=True"):  # a Python caller is told the keyword
        atomic_write_bytes(victim, b"x", force=False)
    with pytest.raises(InputError, match="exists; add --force"):
        check_target(victim, flag="--out")
    assert victim.read_bytes() == b"keep" and link.is_symlink() and check_target(tmp_path / "new") == tmp_path / "new"
    assert atomic_write_bytes(tmp_path / "new", b"new", force=False).read_bytes() == b"new"
    assert atomic_write_bytes(victim, b"x", force=True).read_bytes() == b"x"


def _public_writers(folder: Path) -> dict:
    """Each public function that writes a file, as ``name: (path, write(path, force))``."""
    from napari_lbs._core import write_config, write_particles, write_stack

    table = {name: np.array([1.0, 2.0]) for name in PARTICLE_COLUMNS}
    return {
        "write_config": (folder / "c.toml", lambda path, force: write_config(path, force=force)),
        "write_stack": (folder / "s.tif", lambda path, force: write_stack(path, np.ones((2, 16, 16), np.float32), z_um=[1.0, 2.0], force=force)),
        "write_particles": (folder / "p.csv", lambda path, force: write_particles(path, table, force=force)),
    }


@pytest.mark.parametrize("writer", ["write_config", "write_stack", "write_particles"])
def test_the_public_writers_replace_a_file_only_with_force_and_never_write_through_a_link_fifo_or_device(tmp_path, umask_002, writer):
    import stat

    path, write = _public_writers(tmp_path)[writer]
    path.write_text("mine")
    path.chmod(0o640)
    with pytest.raises(InputError, match=rf"^{path}: exists; add force=True to replace it"):
        write(path, False)
    assert path.read_text() == "mine"
    assert write(path, True) == path and path.read_bytes() != b"mine" and path.stat().st_mode & 0o777 == 0o640  # replaced, keeping its mode
    fresh = tmp_path / "new" / path.name
    assert write(fresh, False) == fresh and fresh.stat().st_mode & 0o777 == 0o664
    victim, fifo, link = tmp_path / "victim", tmp_path / f"fifo{path.suffix}", tmp_path / f"link{path.suffix}"
    victim.write_text("keep")
    os.mkfifo(fifo)
    link.symlink_to(victim)
    for target, message in ((link, "symbolic link"), (fifo, "not a regular file"), (Path("/dev/null"), "not a regular file"), (tmp_path / "new", "is a folder")):
        for force in (False, True):
            with pytest.raises(InputError, match=message):
                write(target, force)
    assert victim.read_text() == "keep" and link.is_symlink() and stat.S_ISFIFO(os.lstat(fifo).st_mode) and stat.S_ISCHR(os.stat("/dev/null").st_mode)
    assert not [p for p in tmp_path.rglob(".*")]  # no temporary left


def test_unexpected_errors_exit_1_with_one_line_and_debug_prints_the_traceback(monkeypatch, capsys, tmp_path):
    import napari_lbs._cli as cli

    def broken(args):
        raise RuntimeError("a bug\nwith two lines")

    monkeypatch.setattr(cli, "_cmd_config", broken)
    assert main(["config", "--write", str(tmp_path / "c.toml")]) == 1
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "please report" in error[0] and "RuntimeError: a bug" in error[0]
    assert main(["--debug", "config", "--write", str(tmp_path / "c.toml")]) == 1
    error = capsys.readouterr().err
    assert "Traceback" in error and "please report" in error.strip().splitlines()[-1]


def test_stale_temporaries_of_a_killed_run_are_removed_and_json_is_strict(tmp_path):
    target = tmp_path / "r.json"
    stale, live, other = tmp_path / ".r.json.abcd1234.part.json", tmp_path / ".r.json.live5678.part.json", tmp_path / ".r.json.notours"
    for path in (stale, live, other):
        path.write_bytes(b"x" * 64)
    os.utime(stale, (time.time() - 3600, time.time() - 3600))  # a killed run's, from before this one
    os.utime(live, (time.time() + 3600, time.time() + 3600))  # another writer's, still being written
    write_json(target, {"gap": float("nan"), "list": [float("inf"), 1.0], "nested": {"x": -float("inf")}})
    assert not stale.exists() and live.exists() and other.exists()
    payload = json.loads(target.read_text(), parse_constant=lambda name: pytest.fail(f"{name} written"))
    assert payload == {"gap": None, "list": [None, 1.0], "nested": {"x": None}}


def test_every_file_a_command_writes_honours_the_umask(tmp_path, umask_002):
    config = tmp_path / "c.toml"
    assert main(["config", "--write", str(config)]) == 0
    config.write_text(config.read_text().replace("z_step_um = 50.0", "z_step_um = 1000.0"))
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "sim"), "--size", "32", "--particles", "2"]) == 0
    assert main(["backprop", str(tmp_path / "sim" / "hologram.tif"), "--config", str(config), "--out", str(tmp_path / "deep" / "stack.tif")]) == 0
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert len(files) == 4 and all(p.stat().st_mode & 0o777 == 0o664 for p in files), [(p.name, oct(p.stat().st_mode)) for p in files]


def test_training_warns_of_an_incomplete_data_set_and_refuses_a_corrupt_resume_file(tmp_path, capsys):
    config = tmp_path / "c.toml"
    assert main(["config", "--write", str(config)]) == 0
    text = config.read_text().replace("z_max_um = 4800.0", "z_max_um = 2200.0").replace("z_step_um = 50.0", "z_step_um = 100.0")
    config.write_text(text.replace("size = 256", "size = 32").replace("per_tile = 12", "per_tile = 2"))
    data = tmp_path / "data"
    assert main(["generate", "--config", str(config), "--groups", "4", "--out", str(data), "--layout", "layers"]) == 0
    (data / "groups" / "group_00001.tif").unlink()
    capsys.readouterr()

    def train(*extra):
        return main(["train", str(data), "--out", str(tmp_path / "m.pt"), "--formulation", "seed", "--device", "cpu", "--validation-groups", "1", *extra])

    assert train("--epochs", "1") == 0
    assert "warning: 3 of 4 groups present" in capsys.readouterr().err
    (tmp_path / "m.last.pt").write_bytes(b"PK\x03\x04 truncated")
    model_before = (tmp_path / "m.pt").read_bytes()
    assert train("--epochs", "2", "--resume") == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]  # after the incomplete set's warning
    assert "m.last.pt" in line and "train without --resume" in line
    assert (tmp_path / "m.pt").read_bytes() == model_before


@pytest.mark.parametrize("command", ["backprop", "calibrate", "diagnose"])
def test_sigterm_during_a_long_command_leaves_nothing(tmp_path, command):
    from napari_lbs._core.foundation._samples import sample_hologram_path

    config = tmp_path / "c.toml"
    assert main(["config", "--write", str(config)]) == 0
    if command == "backprop":  # 61 planes take about a second on 2 idle cores: 301 outlast the signal sent after one
        config.write_text(config.read_text().replace("z_step_um = 50.0", "z_step_um = 10.0"))
    out = tmp_path / {"backprop": "stack.tif", "calibrate": "calib.json", "diagnose": "report"}[command]
    process = subprocess.Popen([sys.executable, "-m", "napari_lbs._cli", command, str(sample_hologram_path()), "--config", str(config), "--out", str(out)],
                               stderr=subprocess.PIPE, text=True)
    # the RGB sample's channel message comes once the command runs, with the SIGTERM handler in place
    assert "reduced to its red channel" in process.stderr.readline()
    time.sleep(1.0)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr
    assert "interrupted" in stderr and "Traceback" not in stderr
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["c.toml"]


def _catches_sigterm(pid: int) -> bool:
    """Whether the process has a handler for SIGTERM (Linux: the SigCgt mask in /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    return False


def _terminated(command: list[str], *, ready, timeout_s: float = 120.0) -> str:
    """Run a CLI command, send SIGTERM once ``ready()`` holds (polled), return its stderr; it must exit 130 cleanly."""
    process = subprocess.Popen([sys.executable, "-m", "napari_lbs._cli", *command], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + timeout_s
    while not _catches_sigterm(process.pid):  # a loaded machine may take seconds to start; the handler comes first
        assert process.poll() is None and time.monotonic() < deadline, "the command ended before it installed its handler"
        time.sleep(0.01)
    while not ready():
        assert process.poll() is None and time.monotonic() < deadline, "the command ended before it could be interrupted"
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=timeout_s)
    assert process.returncode == 130, stderr
    assert "interrupted" in stderr and "Traceback" not in stderr
    return stderr


def test_sigterm_during_simulate_train_and_predict_leaves_no_partial_file(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text("[tile]\nsize = 64\n[particles]\nper_tile = 3\nlayer_step_um = 100.0\n[volume]\nz_min_um = 1800.0\nz_max_um = 2000.0\nz_step_um = 100.0\n")
    started = lambda: time.sleep(0.8) or True  # noqa: E731 (0.8 s after the handler is installed: into the work)
    # a 4096² simulation takes ~6 s on 2 idle cores: still running at 0.8 s
    _terminated(["simulate", "--config", str(config), "--out", str(tmp_path / "sim"), "--size", "4096", "--particles", "6000"], ready=started)
    assert not (tmp_path / "sim").exists() or not any((tmp_path / "sim").iterdir())
    assert main(["generate", "--config", str(config), "--groups", "3", "--out", str(tmp_path / "data")]) == 0
    # training: stopped during its second epoch, after the first wrote the model; what exists is whole
    log = tmp_path / "m.json"
    _terminated(["train", str(tmp_path / "data"), "--out", str(tmp_path / "m.pt"), "--epochs", "200", "--patch-size", "32", "--validation-groups", "1"], ready=log.is_file)
    assert json.loads(log.read_text())["epochs"] and (tmp_path / "m.pt").stat().st_size > 0
    hologram = tmp_path / "h.tif"
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "h"), "--size", "1024", "--particles", "10"]) == 0
    _terminated(["predict", str(tmp_path / "h" / "hologram.tif"), "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "p.csv")], ready=started)
    assert not (tmp_path / "p.csv").exists() and not (tmp_path / "p.json").exists()
    assert not [p.name for p in tmp_path.rglob(".*")]  # no temporary file anywhere


def _group_processes(group: int) -> set[int]:
    """The live processes of process group ``group`` (Linux /proc): a command's children stay in its group, even once orphaned."""
    members = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
        except (OSError, IndexError):  # ended meanwhile
            continue
        if int(fields[2]) == group and fields[0] != "Z":
            members.add(int(stat.parent.name))
    return members


def test_ctrl_c_while_the_local_cluster_starts_exits_130_within_2_s_and_leaves_no_process(tmp_path, detector):
    recording = tmp_path / "rec.tif"
    tifffile.imwrite(recording, 1.0 + 0.1 * np.random.default_rng(0).random((3, 64, 64), np.float32), photometric="minisblack")
    command = ["predict", str(recording), "--model", str(detector.path), "--out", str(tmp_path / "p.csv"), "--workers", "2"]
    errors = tmp_path / "stderr.txt"  # a file, not a pipe: the workers write there too, and may outlive the command
    with errors.open("w") as stream:
        process = subprocess.Popen([sys.executable, "-m", "napari_lbs._cli", *command], stderr=stream, start_new_session=True)
    deadline = time.monotonic() + 120
    while not _catches_sigterm(process.pid):  # SIGINT is caught from Python's start; the command's handlers for both come together
        assert process.poll() is None and time.monotonic() < deadline, "the command ended before it installed its handler"
        time.sleep(0.01)
    while not _group_processes(process.pid) - {process.pid}:  # the cluster's first worker process: the cluster is starting
        assert process.poll() is None and time.monotonic() < deadline, "the command ended before it started a cluster"
        time.sleep(0.01)
    process.send_signal(signal.SIGINT)
    sent = time.monotonic()
    try:
        process.wait(timeout=60)
        seconds = time.monotonic() - sent
        # a worker still starting Python when its parent ended leaves by itself once it runs (dask watches its parent's pipe)
        while _group_processes(process.pid) and time.monotonic() < sent + 20:
            time.sleep(0.1)
    finally:
        left = _group_processes(process.pid)
        for pid in left:  # never leave them to the next test
            os.kill(pid, signal.SIGKILL)
    stderr = errors.read_text()
    assert process.returncode == 130 and seconds < 2.0, (process.returncode, seconds, stderr)
    assert "interrupted" in stderr and "Traceback" not in stderr, stderr
    assert not left, f"{len(left)} processes of the run left"
    assert not (tmp_path / "p.csv").exists()


def test_an_interrupt_inside_an_import_waits_for_the_import_to_end(tmp_path, monkeypatch):
    """SIGTERM inside a module's top level is raised only once the import is over (an extension's initialisation would abort)."""
    import importlib

    from napari_lbs._core.foundation import interruptible

    (tmp_path / "slow_module.py").write_text(
        "import os, signal, time\n"
        "os.kill(os.getpid(), signal.SIGTERM)\n"
        "time.sleep(0.3)  # the handler ran here, inside the import\n"
        "FINISHED = True\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    before, imported = signal.getsignal(signal.SIGTERM), []
    with pytest.raises(KeyboardInterrupt), interruptible():
        imported.append(importlib.import_module("slow_module").FINISHED)
        time.sleep(2.0)  # the interrupt, looked at again every 50 ms, lands here
    assert imported == [True]
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.parametrize("where", ["created", "removed"])
def test_an_interrupt_as_a_temporary_file_is_created_or_removed_leaves_no_file(tmp_path, monkeypatch, where):
    """SIGTERM landing between a temporary's creation and its name's keeping, or amid its removal, is raised once that step is over: no file is left."""
    import tempfile

    from napari_lbs._core.foundation import interruptible
    from napari_lbs._core.foundation import _files
    from napari_lbs._core.foundation._files import write_json

    def signalled(function):
        def wrapper(*args, **kwargs):
            result = function(*args, **kwargs)
            if ".part" in str(result if where == "created" else args[0]):  # the temporary's own step
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.2)  # the handler runs here, inside the step
            return result
        return wrapper

    if where == "created":
        monkeypatch.setattr(_files.tempfile, "mkstemp", signalled(tempfile.mkstemp))
    else:  # the write fails, and the interrupt lands as its temporary is looked for
        monkeypatch.setattr(_files, "_commit", lambda *a, **k: (_ for _ in ()).throw(OSError("disk full")))
        monkeypatch.setattr(_files.Path, "exists", signalled(Path.exists))
    with pytest.raises(KeyboardInterrupt), interruptible():
        write_json(tmp_path / "m.json", {"epochs": 1})
    monkeypatch.undo()
    assert not list(tmp_path.iterdir())


# --- values that make NaN or all-zero data, hangs, memory, garbage ------------------------------

@pytest.mark.parametrize("params, culprit", [
    ({"quantization": {"bits": 0, "saturation": 2}}, "quantization.bits"),
    ({"quantization": {"bits": -3, "saturation": 2}}, "quantization.bits"),
    ({"parasitic_fringes": {"amplitude": 0.1, "period_px": 0, "angle_rad": 0}}, "parasitic_fringes.period_px"),
    ({"shot_noise": {"log10_photons": -2}}, "shot_noise.log10_photons"),
    ({"illumination": {"depth": 1e308, "x0": 0, "y0": 0}}, "illumination.depth"),
    ({"shot_noise": {"log10_photons": 10**400}}, "shot_noise.log10_photons"),
    ({"shot_noise": [1.0]}, "shot_noise: params"),
])
def test_effect_values_outside_their_physical_limits_are_refused_from_a_report(workspace, capsys, params, culprit):
    effect_id = next(iter(params))
    report = workspace / "report.json"
    report.write_text(json.dumps({"verdict": {"id": effect_id}, "effects": [{"id": effect_id, "params": params[effect_id]}]}))
    before = {p.name for p in workspace.rglob("*")}
    line = refusal(capsys, ["generate", "--config", str(workspace / "c.toml"), "--groups", "1", "--out", str(workspace / "d"), "--effects-from", str(report)])
    assert str(report) in line and culprit in line, line
    assert nothing_written(workspace, before)


def test_effect_flags_outside_their_physical_limits_are_refused_and_every_parameter_has_limits(workspace, capsys):
    from napari_lbs._core.physics._effects import EFFECTS, LIMITS, check_effects

    for flag in ["sensor_blur:sigma_px=1e7", "coherence:theta_mrad=1e6"]:
        line = refusal(capsys, ["generate", "--config", str(workspace / "c.toml"), "--groups", "1", "--out", str(workspace / "d"), "--effect", flag])
        assert flag.split(":")[0] in line and "1e+0" in line and "[0, 50]" in line, line
    for effect in EFFECTS.values():  # the fit ranges, neutral values and injections lie within the limits
        assert set(LIMITS[effect.id]) == set(effect.bounds)
        for name, (low, high) in effect.bounds.items():
            lowest, highest = LIMITS[effect.id][name]
            assert lowest <= low <= high <= highest and lowest <= effect.neutral[name] <= highest, (effect.id, name)
        for injection in effect.injections:
            check_effects({effect.id: injection})
    with pytest.raises(InputError, match=r"quantization.bits: expected a finite number in \[1, 16\], got nan"):
        check_effects({"quantization": {"bits": float("nan"), "saturation": 2}})


def test_a_group_that_is_not_finite_is_refused_before_it_is_put_in_place(tmp_path, monkeypatch):
    from napari_lbs._core import load_config
    from napari_lbs._core.learning import _dataset

    real = _dataset.synthetic_group

    def poisoned(*args, **kwargs):
        inputs, labels, particles = real(*args, **kwargs)
        return np.full_like(inputs, np.nan), labels, particles

    monkeypatch.setattr(_dataset, "synthetic_group", poisoned)
    with pytest.raises(InputError, match="NaN or infinite"):
        _dataset.generate_dataset(tmp_path / "d", load_config(None), groups=1)
    assert not list((tmp_path / "d").rglob("group_*"))


def test_track_refuses_absurd_frames_links_across_long_gaps_at_once_and_stops_between_frames(workspace, capsys):
    from napari_lbs._core.foundation import Stopped
    from napari_lbs._core.recordings import link_tracks

    table = workspace / "p.csv"
    table.write_text("x_um,y_um,z_um,diameter_um,frame\n1,1,1,20,0\n2,2,2,20,1000000000000000\n")
    line = refusal(capsys, ["track", str(table), "--out", str(workspace / "t.csv")])
    assert str(table) in line and "frame" in line and "10000000" in line, line
    table.write_text("x_um,y_um,z_um,diameter_um,frame\n1,1,1,20,0\n2,2,2,20,1\n")
    for flag in ("--search-range-um", "--axial-search-range-um"):  # their squares would overflow
        line = refusal(capsys, ["track", str(table), "--out", str(workspace / "t.csv"), flag, "1e308"])
        assert "search_range_um: expected a positive distance up to 1e+06 µm, got 1e+308" in line, line
    rows = {"x_um": np.array([1.0, 2.0, 3.0]), "y_um": np.ones(3), "z_um": np.ones(3), "diameter_um": np.ones(3), "frame": np.array([0, 1, 5_000_000])}
    started = time.monotonic()
    tracks = link_tracks(rows, search_range_um=60.0, memory=3)  # trackpy alone steps through every empty frame of the gap
    assert time.monotonic() - started < 2.0 and tracks["track"].tolist() == [0, 0, 1]
    rng = np.random.default_rng(0)
    many = {name: rng.random(2000) * 500 for name in ("x_um", "y_um", "z_um", "diameter_um")} | {"frame": rng.integers(0, 1000, 2000)}
    asked = []
    with pytest.raises(Stopped):
        link_tracks(many, search_range_um=5.0, should_stop=lambda: asked.append(1) or len(asked) > 3)
    assert len(asked) == 4  # heard after the third frame, not at the end


def test_predict_refuses_what_would_not_fit_in_memory_and_simulate_bounds_the_particles(workspace, capsys, detector, monkeypatch):
    from napari_lbs._core import predict_particles
    from napari_lbs._core.foundation import _validation
    from napari_lbs._core.learning._prediction import _prediction_bytes

    optics = {"wavelength_um": 0.66, "pixel_um": 2.2, "medium_index": 1.33}
    planes = list(detector.config.volume.planes_um())
    assert _prediction_bytes((20000, 20000), planes, detector, optics) > 24 * 2**30  # the size that was killed for memory
    hologram = 1.0 + 0.1 * np.random.default_rng(0).random((64, 64), np.float32)
    monkeypatch.setattr(_validation, "_available_memory_bytes", lambda: 2**20)
    with pytest.raises(InputError, match=r"predicting a 64x64 hologram .*GiB of memory needed, 0.0 GiB available; crop the hologram"):
        predict_particles(hologram, detector)
    monkeypatch.undo()
    line = refusal(capsys, ["simulate", "--config", str(workspace / "c.toml"), "--particles", "100000000", "--out", str(workspace / "s")])
    assert "--particles" in line and "100000" in line, line
    big = workspace / "big.toml"
    big.write_text((workspace / "c.toml").read_text().replace("per_tile = 12", "per_tile = 100000000"))
    line = refusal(capsys, ["config", "--check", str(big)])
    assert "particles.per_tile" in line, line
    assert not (workspace / "s").exists()


def test_a_recording_refuses_more_workers_than_cores_and_a_refused_run_leaves_no_work_folder(tmp_path, capsys, detector):
    from napari_lbs._core import predict_sequence
    from napari_lbs._core.foundation import available_threads

    frames = 1.0 + 0.1 * np.random.default_rng(0).random((3, 64, 64), np.float32)
    with pytest.raises(InputError, match=rf"workers: expected an integer in \[1, {available_threads()}\]"):
        predict_sequence(frames, detector, workers=1000)
    frames[2] = 0.0  # refused when the frame is reached, after the work folder was made
    tifffile.imwrite(tmp_path / "rec.tif", frames, photometric="minisblack")
    out = tmp_path / "p.csv"
    line = refusal(capsys, ["predict", str(tmp_path / "rec.tif"), "--model", str(detector.path), "--out", str(out), "--sequence-background", "none"])
    assert "every pixel is 0" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.tif"]
    line = refusal(capsys, ["predict", str(tmp_path / "rec.tif"), "--model", str(detector.path), "--out", str(out), "--threshold", "1.5"])
    assert "threshold" in line and "(0, 1)" in line, line


def test_api_calls_and_inputs_that_used_to_end_in_internal_errors_raise_input_error(workspace, capsys, detector):
    from napari_lbs._core import backpropagate, load_config, predict_particles, random_particle_field, refine_particles, simulate_hologram
    from napari_lbs._core.foundation._files import read_json_object
    from napari_lbs._core.recordings._sequence import _Work

    hologram = 1.0 + 0.1 * np.random.default_rng(0).random((64, 64), np.float32)
    table = {"x_um": np.array([50.0]), "y_um": np.array([50.0]), "z_um": np.array([2000.0]), "diameter_um": np.array([25.0])}
    calls = [
        (lambda: backpropagate(hologram, [1000.0], wavelength_um=-1, pixel_um=2.2), "wavelength_um: expected a finite number above 0"),
        (lambda: backpropagate(hologram, [1000.0], wavelength_um=0.66, pixel_um=0), "pixel_um: expected a finite number above 0"),
        (lambda: simulate_hologram(None, wavelength_um=0.66), "field: expected a ParticleField"),
        (lambda: refine_particles(hologram, table, config=None), "config: expected an ExperimentConfig"),
        (lambda: predict_particles(hologram, detector, planes_um=[]), "planes_um: expected a non-empty list"),
        (lambda: random_particle_field((64, 64), count=2, diameter_min_um=30, diameter_max_um=20, layers_um=[2000.0], pixel_um=2.2), "diameter_max_um"),
    ]
    for call, message in calls:
        with pytest.raises(InputError, match=message):
            call()
    deep_toml, deep_json, huge = workspace / "deep.toml", workspace / "deep.json", workspace / "huge.toml"
    deep_toml.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    deep_json.write_text("[" * 100000 + "]" * 100000)
    huge.write_text("[tile]\nsize = " + "9" * 400 + "\n")
    for path, read, culprit in ((deep_toml, load_config, "deep.toml"), (deep_json, lambda p: read_json_object(p, what="report"), "deep.json"), (huge, load_config, "tile.size")):
        with pytest.raises(ValueError, match=culprit):  # ConfigError and InputError are ValueErrors naming the file or key
            read(path)
    (workspace / "loop1").symlink_to(workspace / "loop2")
    (workspace / "loop2").symlink_to(workspace / "loop1")
    for argv in (["backprop", str(workspace / "loop1"), "--config", str(workspace / "c.toml"), "--out", str(workspace / "x.tif")],
                 ["track", str(workspace / "loop1"), "--out", str(workspace / "t.csv")]):
        assert "is a loop of symbolic links" in refusal(capsys, argv)
    work = _Work(workspace / "parts", {"run": 1})
    work.save(0, {"x_um": np.zeros(3)})
    part = workspace / "parts" / "frame_0000000.npz"
    part.write_bytes(part.read_bytes()[:40])
    with pytest.raises(InputError, match="frame_0000000.npz: a damaged finished frame"):
        work.load(0)


def test_garbage_is_refused_damaged_tiffs_huge_floats_nan_weights_and_tables_the_reader_would_refuse(workspace, capsys, detector):
    from napari_lbs._core import load_model
    from napari_lbs._core.foundation import read_particles, write_particles
    from napari_lbs._core.learning._network import save_model

    good = workspace / "good.tif"
    tifffile.imwrite(good, 1.0 + np.random.default_rng(0).random((64, 64), np.float32), rowsperstrip=16)
    data = bytearray(good.read_bytes())
    data[8 + 2 + 12 * 3 + 2 : 8 + 2 + 12 * 3 + 4] = bytes(2)  # one tag's data type made invalid: tifffile warns and reads on
    damaged = workspace / "damaged.tif"
    damaged.write_bytes(bytes(data))
    huge = workspace / "huge.tif"
    tifffile.imwrite(huge, (1e38 * (0.5 + np.random.default_rng(1).random((64, 64)))).astype(np.float32))
    for image, message in ((damaged, "damaged.tif: cannot be read as an image (a damaged TIFF"), (huge, "huge.tif: has intensities up to")):
        before = {p.name for p in workspace.rglob("*")}
        line = refusal(capsys, ["backprop", str(image), "--config", str(workspace / "c.toml"), "--out", str(workspace / "stack.tif")])
        assert message in line, line
        assert nothing_written(workspace, before)
    with torch_no_grad():
        broken = load_model(detector.path)
        next(iter(broken.network.parameters())).fill_(float("nan"))
    save_model(workspace / "nan.pt", broken.network, broken.meta)
    with pytest.raises(InputError, match="nan.pt: weights .* hold NaN or infinite values"):
        load_model(workspace / "nan.pt")
    table = {"x_um": np.array([1.0, np.nan]), "y_um": np.zeros(2), "z_um": np.zeros(2), "diameter_um": np.ones(2)}
    for bad, message in ((table, "column x_um holds NaN"), ({**table, "x_um": np.ones(3)}, "column y_um has shape"), ({**table, "x_um": np.ones(2), " y": np.ones(2)}, "column name ' y'")):
        with pytest.raises(InputError, match=message):
            write_particles(workspace / "p.csv", bad)
        assert not (workspace / "p.csv").exists()
    write_particles(workspace / "p.csv", {**table, "x_um": np.ones(2), "note": np.array(["a,b", "c\\nd"], dtype=object)})
    assert read_particles(workspace / "p.csv")["note"].tolist() == ["a,b", "c\\nd"]


def _damage_tag(path: Path, page: int, tag: int) -> None:
    """Give tag number ``tag`` of page ``page`` an invalid data type: tifffile warns and reads on."""
    import struct

    with tifffile.TiffFile(path) as handle:
        offset = handle.pages[page].offset
    data = bytearray(path.read_bytes())
    at = offset + 2 + 12 * tag + 2  # past the tag count, then the tag's code
    data[at:at + 2] = struct.pack("<H", 0)
    path.write_bytes(bytes(data))


def test_a_recording_refuses_a_damaged_page_naming_the_file_and_page(tmp_path, capsys, detector):
    from napari_lbs._core import open_frames

    recording, single = tmp_path / "rec.tif", tmp_path / "one.tif"
    frames = 1.0 + 0.1 * np.random.default_rng(0).random((3, 64, 64), np.float32)
    tifffile.imwrite(recording, frames, photometric="minisblack")
    tifffile.imwrite(single, frames[0], photometric="minisblack")
    _damage_tag(recording, page=1, tag=9)  # XResolution: the pixels still decode, so nothing else would notice
    _damage_tag(single, page=0, tag=9)
    with open_frames([recording]) as opened:
        assert np.array_equal(opened.read(0), frames[0]) and np.array_equal(opened.read(2), frames[2])
        with pytest.raises(InputError, match=rf"^{recording}\[page 1\]: cannot be read as an image \(a damaged TIFF: .*invalid data type 0"):
            opened.read(1)
        with pytest.raises(InputError, match=rf"^{recording}\[page 1\]: cannot be read as an image \(a damaged TIFF"):
            opened.check()  # from the page's tags, before any frame is predicted
    for path, culprit in ((recording, f"{recording}[page 1]"), (single, f"{single}")):  # the first page is parsed as the file opens
        before = {p.name for p in tmp_path.rglob("*")}
        line = refusal(capsys, ["predict", str(path), "--model", str(detector.path), "--out", str(tmp_path / "p.csv")])
        assert line.startswith(f"napari-lbs predict: error: {culprit}: cannot be read as an image (a damaged TIFF"), line
        assert nothing_written(tmp_path, before)


def torch_no_grad():
    import torch

    return torch.no_grad()
