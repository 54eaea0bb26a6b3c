"""A hostile-input probe of the console script: every command given bad paths and bad numbers.

Each case runs ``napari-lbs COMMAND ...`` in a fresh copy of a tiny workspace (a 64² hologram,
a config of three planes, a particle table, a seed model and a data set of two groups) with:

- an input that is ``/dev/null``, a FIFO, a folder, a missing or unreadable file, or a
  truncated TIFF, BMP, CSV, JSON, TOML or model file (a symbolic link to a good input must work);
- an output that is ``/dev/null``, a FIFO, a symbolic link (to a victim file), a folder where a
  file goes (or a file where a folder goes), or an existing file without ``--force``;
- every numeric flag (found in the parser) set to NaN, inf, 1e308, -1 and -1e308.

It records the exit status, the first line on stderr, what changed in the workspace besides
the asked output, and the wall time, and classifies each result:

``security``  a victim behind a link changed, or a link, FIFO or device was replaced or written through;
``data-loss`` an existing file (an input, an output not asked to be replaced) changed or vanished;
``hang``      the case ran past its time limit (``--timeout``);
``exit-1``    an internal error: exit 1 (or another status than 0, 2 and 130), a traceback, or a refusal longer than one line;
``ok``        a one-line refusal (exit 2) or a run that worked (exit 0).

Usage::

    python benchmarks/probe_hostile.py [--out benchmarks/results/reliability] [--jobs 2] [--timeout 40]

Writes ``probe_hostile.json`` (every case) and ``probe_hostile_counts.json`` into ``--out``
and prints the counts and every case that is not ``ok``.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = [sys.executable, "-m", "napari_lbs._cli"]
CONFIG = "[tile]\nsize = 64\n[particles]\nper_tile = 3\nlayer_step_um = 100.0\n[volume]\nz_min_um = 1800.0\nz_max_um = 2000.0\nz_step_um = 100.0\n"
NUMBERS = ["nan", "inf", "1e308", "-1", "-1e308"]
KINDS = ("ok", "security", "data-loss", "hang", "exit-1")

# Each command on good inputs: its argv (placeholders: {h} hologram, {c} config, {m} model, {t} table with frames,
# {p} a prediction, {d} data set), the output flag and whether it names a folder. Heavy commands run only to be refused.
COMMANDS = {
    "config": (["config"], "--write", False),
    "simulate": (["simulate", "--config", "{c}", "--size", "32", "--particles", "2"], "--out", True),
    "backprop": (["backprop", "{h}", "--config", "{c}"], "--out", False),
    "calibrate": (["calibrate", "{h}", "--config", "{c}", "--generations", "2", "--population", "4", "--runs", "1"], "--out", False),
    "generate": (["generate", "--config", "{c}", "--groups", "2"], "--out", True),
    "train": (["train", "{d}", "--epochs", "1", "--patch-size", "32", "--validation-groups", "1", "--device", "cpu", "--formulation", "seed"], "--out", False),
    "predict": (["predict", "{h}", "--model", "{m}", "--device", "cpu"], "--out", False),
    "refine": (["refine", "{h}", "--config", "{c}"], "--out", False),
    "track": (["track", "{t}"], "--out", False),
    "evaluate": (["evaluate", "{p}", "{t}"], None, False),
    "diagnose": (["diagnose", "{h}", "--config", "{c}"], "--out", True),
    "demo": (["demo", "--quick"], "--out", True),
}
OUTPUT_NAMES = {"config": "new.toml", "backprop": "stack.tif", "calibrate": "calib.json", "train": "new.pt", "predict": "out.csv", "refine": "out.csv",
                "track": "tracks.csv", "simulate": "sim", "generate": "gen", "diagnose": "report", "demo": "demo"}
FOLDER_FILE = {"simulate": "particles.csv", "generate": "dataset.json", "diagnose": "report.md", "demo": "summary.json"}  # a file each writes in its folder
LIGHT = {"backprop", "predict", "refine", "track", "evaluate"}  # run to the end on good inputs within a few seconds
INPUTS = {"{h}": "h.tif", "{c}": "c.toml", "{m}": "m.pt", "{t}": "t.csv", "{p}": "p.csv", "{d}": "data"}


def make_workspace(folder: Path, timeout: float) -> None:
    """The good inputs every case starts from, and the damaged ones the cases swap in."""
    import numpy as np
    import tifffile
    from PIL import Image

    folder.mkdir(parents=True)
    (folder / "c.toml").write_text(CONFIG)
    rng = np.random.default_rng(0)
    hologram = (1.0 + 0.2 * rng.random((64, 64))).astype(np.float32)
    tifffile.imwrite(folder / "h.tif", hologram)
    Image.fromarray((hologram * 100).astype(np.uint8)).save(folder / "h.bmp")
    rows = "".join(f"{10 + k},{20 + 2 * f},{1900 + k},25,{f}\n" for f in range(3) for k in range(2))
    (folder / "t.csv").write_text("x_um,y_um,z_um,diameter_um,frame\n" + rows)
    (folder / "p.csv").write_text("x_um,y_um,z_um,diameter_um\n10,20,1900,25\n")
    (folder / "victim.txt").write_text("keep")
    data = ["generate", "--config", str(folder / "c.toml"), "--groups", "2", "--out", str(folder / "data")]
    subprocess.run([*CLI, *data], capture_output=True, timeout=timeout * 4, check=True)
    train = ["train", str(folder / "data"), "--out", str(folder / "m.pt"), "--epochs", "1", "--patch-size", "32", "--validation-groups", "1", "--device", "cpu",
             "--formulation", "seed"]
    subprocess.run([*CLI, *train], capture_output=True, timeout=timeout * 4, check=True)
    damaged = folder / "damaged"
    damaged.mkdir()
    for name in ("h.tif", "h.bmp", "t.csv", "m.pt"):
        data_bytes = (folder / name).read_bytes()
        (damaged / name).write_bytes(data_bytes[: len(data_bytes) // 2])
    (damaged / "c.toml").write_text(CONFIG[: CONFIG.index("[volume]") + 4])  # cut inside a table's name: no longer TOML
    (damaged / "calib.json").write_text('{"params": {"N_R": 0.1, "N_sig')
    (damaged / "report.json").write_text('{"effects": [')
    (damaged / "data").mkdir()
    (damaged / "data" / "dataset.json").write_text('{"groups": 2, "spec"')


def cases() -> list[dict]:
    """Every case: ``{"id", "command", "argv" (placeholders), "out" (or None), "force", "setup" (what to make before)}``."""
    result = []

    def add(command: str, case: str, argv: list[str], *, out: str | None, setup: list | None = None, expect_ok: bool = False) -> None:
        result.append({"id": f"{command}:{case}", "command": command, "argv": argv, "out": out, "setup": setup or [], "expect_ok": expect_ok})

    for command, (head, flag, folder) in COMMANDS.items():
        out = OUTPUT_NAMES.get(command)
        with_out = [*head, flag, "{w}/" + out] if flag else list(head)
        # inputs: each placeholder in turn made hostile
        for placeholder, name in INPUTS.items():
            if placeholder not in head:
                continue
            at = head.index(placeholder)
            for kind, replacement, setup in (
                ("devnull", "/dev/null", []), ("fifo", "{w}/in.fifo", [("fifo", "in.fifo")]), ("folder", "{w}/adir", [("dir", "adir")]),
                ("missing", "{w}/missing" + Path(name).suffix, []), ("unreadable", "{w}/locked" + Path(name).suffix, [("locked", name, "locked" + Path(name).suffix)]),
                ("truncated", "{w}/damaged/" + name, []),
            ):
                argv = list(with_out)
                argv[at] = replacement
                add(command, f"{placeholder[1]}-{kind}", argv, out=out, setup=setup)
            if placeholder == "{h}":
                argv = list(with_out)
                argv[at] = "{w}/damaged/h.bmp"
                add(command, "h-truncated-bmp", argv, out=out)
            if command in LIGHT:  # a link to a good input is used like the file
                argv = list(with_out)
                argv[at] = "{w}/link" + Path(name).suffix
                add(command, f"{placeholder[1]}-symlink", argv, out=out, setup=[("link", "link" + Path(name).suffix, name)], expect_ok=True)
        if command == "generate":
            for option, name in (("--calibration", "calib.json"), ("--effects-from", "report.json")):
                add(command, f"{option}-truncated", [*with_out, option, "{w}/damaged/" + name], out=out)
                add(command, f"{option}-fifo", [*with_out, option, "{w}/in.fifo"], out=out, setup=[("fifo", "in.fifo")])
        if command == "train":
            add(command, "d-truncated-manifest", [with_out[0], "{w}/damaged/data", *with_out[2:]], out=out)
        # outputs
        if flag:
            target = out + "/" + FOLDER_FILE[command] if folder else out
            for kind, setup in (("devnull", None), ("fifo", [("fifo", target)]), ("symlink", [("link", target, "victim.txt")]), ("existing", [("file", target)]),
                                ("wrong-kind", [("file", out)] if folder else [("dir", out)])):
                argv = list(with_out)
                if kind == "devnull":
                    if folder:
                        setup = [("link", target, "/dev/null")]
                    else:
                        argv[-1] = "/dev/null"
                        setup = []
                add(command, f"out-{kind}", argv, out=out, setup=(([("dir", out)] if folder and kind != "wrong-kind" else []) + setup))
                if kind in ("devnull", "fifo", "symlink"):
                    add(command, f"out-{kind}-force", [*argv, "--force"], out=out, setup=(([("dir", out)] if folder else []) + setup))
        # numeric flags
        for option, nargs in numeric_flags(command):
            for number in NUMBERS:
                add(command, f"{option}={number}", [*with_out, option, *([number] * (nargs or 1))], out=out)
    return result


def numeric_flags(command: str) -> list[tuple[str, int | None]]:
    """The flags of ``command`` whose values the parser checks as numbers (``_integer``/``_number``), with their nargs."""
    import argparse

    from napari_lbs._cli import _parser

    parser = _parser()
    sub = next(action for action in parser._actions if isinstance(action, argparse._SubParsersAction))
    return [(action.option_strings[-1], action.nargs) for action in sub.choices[command]._actions
            if action.option_strings and action.type is not None and getattr(action.type, "__name__", "") == "parse"]


def snapshot(folder: Path) -> dict[str, tuple]:
    """Every path under ``folder`` with its kind, size, content time and inode (links not followed)."""
    state = {}
    for path in [folder, *folder.rglob("*")]:
        try:
            info = os.lstat(path)
        except FileNotFoundError:
            continue
        kind = "link" if stat.S_ISLNK(info.st_mode) else "dir" if stat.S_ISDIR(info.st_mode) else "fifo" if stat.S_ISFIFO(info.st_mode) else "file"
        state[str(path.relative_to(folder))] = (kind, info.st_size if kind == "file" else 0, info.st_mtime_ns if kind == "file" else 0, info.st_ino,
                                                os.readlink(path) if kind == "link" else None)
    return state


def run_case(case: dict, workspace: Path, timeout: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="probe-") as scratch:
        work = Path(scratch) / "w"
        shutil.copytree(workspace, work, symlinks=True)
        for step in case["setup"]:
            kind, name = step[0], work / step[1]
            name.parent.mkdir(parents=True, exist_ok=True)
            if kind == "fifo":
                os.mkfifo(name)
            elif kind == "dir":
                name.mkdir(exist_ok=True)
            elif kind == "file":
                name.write_text("mine")
            elif kind == "link":
                name.symlink_to(step[2] if step[2].startswith("/") else work / step[2])
            elif kind == "locked":  # no permission to read (root reads it anyway: see "as_root")
                (shutil.copytree if (work / step[1]).is_dir() else shutil.copy)(work / step[1], work / step[2])
                (work / step[2]).chmod(0)
        argv = [part.replace("{w}", str(work)) for part in case["argv"]]
        argv = [str(work / INPUTS[part]) if part in INPUTS else part for part in argv]
        devnull_before = os.stat("/dev/null").st_mode
        before = snapshot(work)
        started = time.perf_counter()
        try:
            process = subprocess.run(["timeout", "-k", "5", str(timeout), *CLI, *argv], capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=timeout + 20)
            status, stderr = process.returncode, process.stderr
        except subprocess.TimeoutExpired as expired:
            status, stderr = 124, (expired.stderr or b"").decode("utf-8", "replace") if isinstance(expired.stderr, bytes) else (expired.stderr or "")
        seconds = time.perf_counter() - started
        after = snapshot(work)
        victim = (work / "victim.txt").read_text() if (work / "victim.txt").is_file() else None
    out = case["out"]
    asked = [] if out is None else [out, out.rsplit(".", 1)[0] + "."]  # the output, and what a command writes beside it (provenance, a training log)
    changed = sorted(name for name in set(before) | set(after) if before.get(name) != after.get(name) and name != ".")
    outside = [name for name in changed if not any(name == a or name.startswith(a.rstrip(".") + "/") or (a.endswith(".") and name.startswith(a)) for a in asked)]
    lost = [name for name in outside if name in before]
    lines = [line for line in stderr.strip().splitlines() if line.strip()]
    record = {"id": case["id"], "command": case["command"], "argv": ["napari-lbs", *[a.replace(str(work), "WORK") for a in argv]], "exit": status,
              "stderr_first_line": lines[0].replace(str(work), "WORK") if lines else "", "stderr_lines": len(lines), "seconds": round(seconds, 2),
              "written_outside": [n for n in outside if n not in lost], "changed_existing": lost}
    replaced_special = [n for n in changed if before.get(n, ("file",))[0] in ("link", "fifo") and after.get(n, (None,))[0] != before[n][0]]
    if victim != "keep" or os.stat("/dev/null").st_mode != devnull_before or replaced_special:
        kind = "security"
    elif lost:
        kind = "data-loss"
    elif status in (124, 137) or seconds >= timeout:
        kind = "hang"
    elif status not in (0, 2, 130) or "Traceback" in stderr or (status == 2 and len(lines) != 1):
        kind = "exit-1"
    elif case["expect_ok"] and status != 0:
        kind = "exit-1"  # a good input behind a link refused
    else:
        kind = "ok"
    record["class"] = kind
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "reliability")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=40.0, help="seconds a case may run before it counts as a hang")
    parser.add_argument("--only", default=None, help="run only the cases whose id contains this text")
    args = parser.parse_args()
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="probe-workspace-") as scratch:
        workspace = Path(scratch) / "w"
        make_workspace(workspace, args.timeout)
        todo = [case for case in cases() if args.only is None or args.only in case["id"]]
        print(f"{len(todo)} cases, {args.jobs} at a time, {args.timeout:g} s each at most", flush=True)
        with concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
            records = list(pool.map(lambda case: run_case(case, workspace, args.timeout), todo))  # a fault of the probe itself ends it
    counts = {kind: sum(r["class"] == kind for r in records) for kind in KINDS}
    summary = {"cases": len(records), "counts": counts, "seconds": round(time.perf_counter() - started, 1), "as_root": os.geteuid() == 0,
               "timeout_s": args.timeout, "jobs": args.jobs}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "probe_hostile.json").write_text(json.dumps({"summary": summary, "cases": records}, indent=1) + "\n")
    (args.out / "probe_hostile_counts.json").write_text(json.dumps(summary, indent=1) + "\n")
    for record in records:
        if record["class"] != "ok":
            print(f"{record['class']:9} {record['id']:45} exit {record['exit']:4} {record['seconds']:6.1f} s  {record['stderr_first_line'][:150]}")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
