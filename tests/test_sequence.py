"""Recordings: frames read one at a time, the background from the frames, prediction on dask
(same table whatever the workers, resumed after a stop), ground-truth flows, tracks, and the CLI."""

import csv
import json
import tracemalloc

import numpy as np
import pytest
import tifffile

from napari_lbs._core import (
    InputError,
    ParticleField,
    Stopped,
    link_tracks,
    open_frames,
    predict_sequence,
    sequence_background,
    simulate_hologram,
    simulate_sequence,
)
from napari_lbs._core.recordings._flow import flow_positions


@pytest.fixture(scope="module")
def vortex(tiny_config):
    return simulate_sequence(tiny_config, frames=5, flow="vortex", size=96, count=6, speed_um=6.0, seed=1)


# --- reading -----------------------------------------------------------------------------------


def test_a_multipage_tiff_is_read_page_by_page_without_loading_the_file(tmp_path):
    frames = np.random.default_rng(0).uniform(0.5, 1.5, (40, 256, 256)).astype(np.float32)
    tifffile.imwrite(tmp_path / "run.tif", frames, photometric="minisblack")
    frame_bytes = frames[0].nbytes
    tracemalloc.start()
    with open_frames([tmp_path / "run.tif"]) as recording:
        assert len(recording) == 40
        for k in range(len(recording)):
            assert recording.read(k)[5, 7] == frames[k, 5, 7]
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < 3 * frame_bytes  # the file is 40 frames
        for k in (0, 39, 17):  # any order
            np.testing.assert_array_equal(recording.read(k), frames[k])
    assert recording.name(17) == f"{tmp_path / 'run.tif'}[frame 17]"


def test_a_video_is_decoded_frame_by_frame(tmp_path):
    import cv2

    rng = np.random.default_rng(1)
    frames = np.clip(128 + 60 * np.sin(np.arange(128)[None, :, None] / 4.0 + np.arange(16)[:, None, None]) + rng.normal(0, 1, (16, 128, 128)), 0, 255).astype(np.uint8)
    writer = cv2.VideoWriter(str(tmp_path / "run.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (128, 128), isColor=False)
    for frame in frames:
        writer.write(frame)
    writer.release()
    with open_frames([tmp_path / "run.avi"]) as recording:
        assert len(recording) == 16 and recording.name(3) == f"{tmp_path / 'run.avi'}[frame 3]"
        tracemalloc.start()
        decoded = [recording.read(k).mean() for k in range(16)]
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < 4 * 128 * 128 * 3 * 4  # a frame at a time (RGB float32), never the whole video (16 frames)
        np.testing.assert_allclose(decoded, frames.mean(axis=(1, 2)), atol=2.0)  # MJPG is lossy
        back = recording.read(2)  # going back reopens the video
        assert np.mean(np.abs(back - frames[2])) < 3.0 and np.mean(np.abs(back - frames[3])) > 20.0


def test_folders_and_globs_sort_naturally_and_files_keep_input_order(tmp_path):
    for k in (10, 2, 1):
        tifffile.imwrite(tmp_path / f"f{k}.tif", np.full((32, 32), float(k), np.float32) + np.eye(32, dtype=np.float32))
    values = lambda r: [float(r.read(k)[0, 1]) for k in range(len(r))]  # noqa: E731
    assert values(open_frames([tmp_path])) == [1.0, 2.0, 10.0]
    assert values(open_frames([str(tmp_path / "f*.tif"), tmp_path / "f1.tif"])) == [1.0, 2.0, 10.0, 1.0]
    with pytest.raises(InputError, match="no file matches"):
        open_frames([str(tmp_path / "g*.tif")])
    tifffile.imwrite(tmp_path / "other.tif", np.ones((16, 40), np.float32) + np.eye(16, 40, dtype=np.float32))
    with pytest.raises(InputError, match=r"other.tif: expected the first frame's shape \(32, 32\)"):
        values(open_frames([tmp_path]))


# --- background --------------------------------------------------------------------------------


def test_the_median_background_removes_a_static_pattern(vortex, tiny_config):
    rows, cols = np.indices((96, 96))
    pattern = (0.6 + 0.3 * np.sin(rows / 5.0) * np.cos(cols / 7.0) + 0.1 * (cols / 96)).astype(np.float32)  # fringes + vignetting
    clean = simulate_sequence(tiny_config, frames=9, flow="uniform", size=96, count=4, speed_um=30.0, seed=3).frames
    frames = clean * pattern
    recording = open_frames(frames)
    assert np.corrcoef(frames[4].ravel(), pattern.ravel())[0, 1] > 0.5  # the pattern dominates the raw frame
    for background in (sequence_background(recording), sequence_background(recording, index=4, window=7)):
        assert np.median(np.abs(background / pattern - 1)) < 0.05  # the particles' fringes average out
        corrected = frames[4] / background
        assert abs(np.corrcoef(corrected.ravel(), pattern.ravel())[0, 1]) < 0.1
        assert np.median(np.abs(corrected - clean[4])) < 0.05  # the particles' own hologram is left


def test_the_flat_field_keeps_every_particle_and_removes_the_envelope(tiny_config):
    from napari_lbs._core.recordings._background import flat_field

    clean = simulate_sequence(tiny_config, frames=1, flow="uniform", size=256, count=4, speed_um=0.0, seed=3).frames[0]
    rows, cols = np.indices(clean.shape)
    envelope = (0.5 + 0.4 * cols / 256 + 0.1 * rows / 256).astype(np.float32)  # vignetting and a tilted lamp
    assert np.median(np.abs(clean * envelope / np.mean(clean * envelope) - clean)) > 0.1  # dividing by the mean leaves it
    corrected = clean * envelope / flat_field(clean * envelope)
    assert np.median(np.abs(corrected - clean)) < 0.02  # the envelope is gone
    assert np.corrcoef(corrected.ravel(), clean.ravel())[0, 1] > 0.97  # and every particle's hologram is left
    with pytest.raises(InputError, match="sigma_px"):
        flat_field(clean, sigma_px=0.0)


def test_auto_takes_the_median_only_when_it_has_static_structure_and_no_particles(tiny_config):
    from napari_lbs._core.recordings._background import choose_background

    rows, cols = np.indices((96, 96))
    pattern = (0.6 + 0.3 * np.sin(rows / 5.0) * np.cos(cols / 7.0) + 0.1 * (cols / 96)).astype(np.float32)  # a setup's static fringes
    fast = simulate_sequence(tiny_config, frames=16, flow="uniform", size=96, count=3, speed_um=40.0, seed=3).frames
    mode, background, measures = choose_background(open_frames(fast * pattern))
    assert mode == "global" and measures["ratio"] < 0.5 and measures["residue"] < 0.6 and measures["frames"] == 16
    np.testing.assert_array_equal(background, sequence_background(open_frames(fast * pattern)))
    mode, background, measures = choose_background(open_frames(fast))  # uniform light: nothing static for the median to remove
    assert mode == "flat" and background is None and measures["ratio"] > 1.5 and measures["residue"] < 0.6
    slow = simulate_sequence(tiny_config, frames=8, flow="uniform", size=96, count=3, speed_um=6.0, seed=3).frames * pattern
    mode, background, measures = choose_background(open_frames(slow))  # static fringes, but the particles are still in the median
    assert mode == "flat" and measures["ratio"] < 1.0 and measures["residue"] > 1.4
    assert choose_background(open_frames(fast[:3]))[0] == "flat"  # too few frames to split in two
    assert choose_background(open_frames(fast * pattern), residue=0.3)[0] == "flat"
    assert choose_background(open_frames(slow), residue=2.0)[0] == "global"


# --- prediction on dask ------------------------------------------------------------------------


def _assert_same_table(a, b):
    assert list(a) == list(b)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


@pytest.mark.parametrize("background", ["auto", "flat"])
def test_the_same_table_from_one_worker_and_two_with_a_per_frame_background(vortex, detector, background):
    local = predict_sequence(vortex.frames, detector, background=background)
    assert local.provenance["background_used"] == "flat" and len(local.particles["x_um"]) > 20
    one = predict_sequence(vortex.frames, detector, background=background, workers=1, local_processes=False)
    two = predict_sequence(vortex.frames, detector, background=background, workers=2, local_processes=False)
    _assert_same_table(local.particles, one.particles)
    _assert_same_table(local.particles, two.particles)


def test_the_same_table_from_one_worker_and_two(vortex, detector):
    local = predict_sequence(vortex.frames, detector, background="global")
    assert len(local.particles["x_um"]) > 20 and set(np.unique(local.particles["frame"])) == set(range(5))
    assert np.all(np.diff(local.particles["frame"]) >= 0)
    two = predict_sequence(vortex.frames, detector, background="global", workers=2, local_processes=False)
    _assert_same_table(local.particles, two.particles)
    assert two.provenance["scheduler"] == "dask LocalCluster of 2 workers" and two.provenance["model_sha256"] == detector.sha256
    # each frame is what predict_particles makes of it on one torch thread, divided by the median of the frames
    import torch

    from napari_lbs._core import predict_particles

    threads = torch.get_num_threads()
    background = np.median(vortex.frames, axis=0)
    torch.set_num_threads(1)
    try:
        alone = predict_particles(vortex.frames[3], detector, background=background)
    finally:
        torch.set_num_threads(threads)
    np.testing.assert_array_equal(local.particles["x_um"][local.particles["frame"] == 3], alone.particles["x_um"])


def test_a_stopped_run_resumes_without_redoing_finished_frames(vortex, detector, tmp_path, monkeypatch):
    import napari_lbs._core.recordings._sequence as sequence

    work = tmp_path / "p.csv.parts"
    seen = []
    with pytest.raises(Stopped, match=r"stopped after \d of 5 frames") as stop:
        predict_sequence(vortex.frames, detector, background="running", background_window=3, work_dir=work, progress=lambda d, t: seen.append(d), should_stop=lambda: seen[-1] > 0)
    done = seen[-1]  # the first batch of frames (one per core, at most 4 here)
    assert 0 < done < 5 and f"after {done} of 5" in str(stop.value)
    assert sorted(p.name for p in work.glob("frame_*.npz")) == [f"frame_{k:07d}.npz" for k in range(done)]
    predicted = []
    original = sequence._frame_particles
    monkeypatch.setattr(sequence, "_frame_particles", lambda hologram, *rest: predicted.append(hologram) or original(hologram, *rest))
    resumed = predict_sequence(vortex.frames, detector, background="running", background_window=3, work_dir=work)
    assert len(predicted) == 5 - done and resumed.resumed == done
    assert any(np.array_equal(hologram, vortex.frames[done]) for hologram in predicted)
    fresh = predict_sequence(vortex.frames, detector, background="running", background_window=3)
    _assert_same_table(resumed.particles, fresh.particles)
    with pytest.raises(InputError, match="holds the frames of another run"):
        predict_sequence(vortex.frames, detector, background="global", work_dir=work)


def test_a_killed_cli_run_resumes_where_it_stopped(tmp_path, detector, tiny_config, monkeypatch):
    import os
    import signal
    import subprocess
    import sys
    import time

    from napari_lbs._cli import main

    frames = simulate_sequence(tiny_config, frames=10, flow="uniform", size=96, count=4, speed_um=6.0, seed=4).frames
    tifffile.imwrite(tmp_path / "rec.tif", frames, photometric="minisblack")
    command = ["predict", str(tmp_path / "rec.tif"), "--model", str(detector.path), "--out", str(tmp_path / "p.csv")]
    parts = tmp_path / "p.csv.parts"
    environ = {**os.environ, "NAPARI_LBS_THREADS": "1", "OMP_NUM_THREADS": "1"}
    run = subprocess.Popen([sys.executable, "-c", "from napari_lbs._cli import console_main; console_main()", *command], env=environ,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while run.poll() is None and len(list(parts.glob("frame_*.npz"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    run.send_signal(signal.SIGKILL)  # no handler runs: what is on disk is all a resumed run has
    run.wait()
    assert run.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    done = sorted(int(p.stem.split("_")[1]) for p in parts.glob("frame_*.npz"))
    assert 2 <= len(done) < 10 and not list(parts.glob("*.tmp*"))
    predicted = []
    import napari_lbs._core.recordings._sequence as sequence

    original = sequence._frame_particles
    monkeypatch.setattr(sequence, "_frame_particles", lambda hologram, *rest: predicted.append(hologram) or original(hologram, *rest))
    assert main(command) == 0
    monkeypatch.undo()
    assert len(predicted) == 10 - len(done)  # no frame done twice
    assert not any(np.array_equal(hologram, frames[k]) for hologram in predicted for k in done)
    provenance = json.loads((tmp_path / "p.json").read_text())
    assert provenance["resumed_frames"] == len(done) and provenance["background"] == "auto" and not parts.exists()
    assert main([*command[:-1], str(tmp_path / "fresh.csv")]) == 0
    assert _rows(tmp_path / "p.csv") == _rows(tmp_path / "fresh.csv")


# --- ground truth and tracks -------------------------------------------------------------------


def test_a_simulated_vortex_turns_rigidly_and_each_frame_is_its_hologram(vortex):
    truth = vortex.truth
    assert vortex.frames.shape == (5, 96, 96) and vortex.frames.dtype == np.float32
    assert np.array_equal(np.unique(truth["track"]), np.arange(6))  # nobody leaves a vortex
    centre = 95 * 2.2 / 2
    radius = np.hypot(truth["x_um"] - centre, truth["y_um"] - centre).reshape(5, 6)
    np.testing.assert_allclose(radius, radius[:1].repeat(5, axis=0), atol=1e-9)
    step = np.hypot(np.diff(truth["x_um"].reshape(5, 6), axis=0), np.diff(truth["y_um"].reshape(5, 6), axis=0))
    assert step.max() <= 6.0 + 1e-9 and step.min() > 0
    here = truth["frame"] == 2
    field = ParticleField(truth["x_um"][here], truth["y_um"][here], truth["z_um"][here], truth["diameter_um"][here], (96, 96), 2.2)
    np.testing.assert_array_equal(vortex.frames[2], simulate_hologram(field, wavelength_um=0.66))


def test_tracks_are_recovered_exactly_on_a_clean_sequence():
    rng = np.random.default_rng(2)
    start = ParticleField(rng.uniform(0, 200, 30), rng.uniform(0, 200, 30), rng.uniform(1800, 2200, 30), np.full(30, 25.0), (100, 100), 2.2)
    truth = flow_positions(start, flow="uniform", frames=12, speed_um=10.0, z_range_um=(1800.0, 2200.0))
    assert truth["track"].max() >= 30  # some particles left the window and came back as new tracks
    shuffled = rng.permutation(truth["x_um"].size)
    table = {name: values[shuffled] for name, values in truth.items() if name != "track"}
    linked = link_tracks(table, search_range_um=12.0)
    true_track = truth["track"][shuffled][np.argsort(table["frame"], kind="stable")]
    pairs = set(zip(linked["track"].tolist(), true_track.tolist(), strict=True))
    assert len(pairs) == len(set(linked["track"].tolist())) == len(set(true_track.tolist()))  # a one-to-one map of tracks
    moving = ~np.isnan(linked["dx_um"])
    np.testing.assert_allclose(np.stack([linked[k][moving] for k in ("dx_um", "dy_um", "dz_um")], axis=1), np.tile([6.0, 4.8, 6.4], (int(moving.sum()), 1)), atol=1e-9)
    assert (~moving).sum() == len(set(true_track.tolist()))  # one end per track
    # a search range below the step breaks every track: the test can fail
    assert len(set(link_tracks(table, search_range_um=5.0)["track"].tolist())) == truth["x_um"].size
    empty = link_tracks({name: values[:0] for name, values in table.items()}, search_range_um=12.0)
    assert empty["track"].size == 0 and empty["dx_um"].size == 0  # a recording where nothing was found
    # depths that jump by a plane (as predicted ones do) need a longer search along z only
    jumpy = dict(table, z_um=table["z_um"] + 50.0 * (table["frame"] % 2))
    assert len(set(link_tracks(jumpy, search_range_um=12.0)["track"].tolist())) > 2 * len(set(true_track.tolist()))
    along_z = link_tracks(jumpy, search_range_um=12.0, axial_search_range_um=80.0)
    assert len(set(zip(along_z["track"].tolist(), true_track.tolist(), strict=True))) == len(set(along_z["track"].tolist())) == len(set(true_track.tolist()))


# --- CLI ---------------------------------------------------------------------------------------


def _rows(path):
    with open(path, newline="", encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


def test_cli_simulate_frames_predict_and_track(tmp_path, detector):
    from napari_lbs._cli import main
    from napari_lbs._core import write_config

    config = write_config(tmp_path / "c.toml")
    config.write_text(config.read_text().replace("z_min_um = 1800.0", "z_min_um = 1800.0").replace("z_max_um = 4800.0", "z_max_um = 2200.0").replace("z_step_um = 50.0", "z_step_um = 100.0").replace("size = 256", "size = 48"))
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "sim"), "--frames", "3", "--flow", "shear", "--size", "64", "--particles", "4", "--seed", "2"]) == 0
    with tifffile.TiffFile(tmp_path / "sim" / "frames.tif") as handle:
        assert len(handle.pages) == 3 and handle.pages[0].shape == (64, 64) and handle.pages[0].dtype == np.float32
    truth = _rows(tmp_path / "sim" / "particles.csv")
    assert list(truth[0])[:4] == ["x_um", "y_um", "z_um", "diameter_um"] and {"frame", "track"} <= set(truth[0])
    assert [row["frame"] for row in truth] == ["0"] * 4 + ["1"] * 4 + ["2"] * 4
    assert main(["simulate", "--config", str(config), "--out", str(tmp_path / "x"), "--flow", "vortex"]) == 2  # a flow needs --frames

    assert main(["predict", str(tmp_path / "sim" / "frames.tif"), "--model", str(detector.path), "--out", str(tmp_path / "p.csv")]) == 0
    particles = _rows(tmp_path / "p.csv")
    assert {row["frame"] for row in particles} == {"0", "1", "2"} and not (tmp_path / "p.csv.parts").exists()
    assert main(["track", str(tmp_path / "p.csv"), "--out", str(tmp_path / "t.csv"), "--search-range-um", "8"]) == 0  # the eager model: dozens a frame
    tracks = _rows(tmp_path / "t.csv")
    assert len(tracks) == len(particles) and {"track", "dx_um", "dy_um", "dz_um"} <= set(tracks[0])
    last = {}
    for row in tracks:
        last[row["track"]] = row
    assert all(row["dx_um"] == "" for row in last.values())
    sidecar = json.loads((tmp_path / "t.json").read_text())  # what linked them, and what detected them
    assert sidecar["tracks"]["search_range_um"] == 8.0 and sidecar["prediction"] == json.loads((tmp_path / "p.json").read_text())
    assert main(["track", str(tmp_path / "sim" / "particles.csv"), "--out", str(tmp_path / "sim" / "particles.csv")]) == 2
    before = (tmp_path / "p.json").read_bytes()
    assert main(["track", str(tmp_path / "p.csv"), "--out", str(tmp_path / "p.parquet")]) == 2  # its sidecar would be p.json
    assert (tmp_path / "p.json").read_bytes() == before and not (tmp_path / "p.parquet").exists()


def test_a_parquet_table_round_trips_with_its_frame_column_and_metadata(tmp_path):
    import pandas as pd
    import pyarrow.parquet as pq

    from napari_lbs._core import read_particles, write_particles

    table = {"x_um": np.array([1.5, 2.25, 3.0]), "y_um": np.array([4.0, 5.0, 6.0]), "z_um": np.array([1800.0, 1850.0, 1900.0]),
             "diameter_um": np.array([20.0, 25.0, 30.0]), "score": np.array([0.9, 0.8, np.nan]), "frame": np.array([0, 0, 7], np.int64)}
    path = write_particles(tmp_path / "p.parquet", table, metadata={"model_sha256": "abc", "planes_um": [1800.0, 2200.0, 5]})
    stored = pd.read_parquet(path)
    assert list(stored.columns) == list(table) and stored["frame"].dtype == np.int64  # columns in order, their own types
    assert json.loads(pq.read_schema(path).metadata[b"napari_lbs"]) == {"model_sha256": "abc", "planes_um": [1800.0, 2200.0, 5]}
    back = read_particles(path)
    assert list(back) == list(table)
    for name in table:
        np.testing.assert_array_equal(back[name], table[name].astype(np.float64), err_msg=name)  # as a CSV reads: float64
    with pytest.raises(InputError, match="missing column z_um"):
        write_particles(tmp_path / "bad.parquet", {k: v for k, v in table.items() if k != "z_um"})
    pd.DataFrame({"x_um": [1.0], "y_um": [2.0], "diameter_um": [3.0]}).to_parquet(tmp_path / "other.parquet")
    with pytest.raises(InputError, match="other.parquet: missing column z_um"):
        read_particles(tmp_path / "other.parquet")
    (tmp_path / "broken.parquet").write_text("x_um,y_um\n")
    with pytest.raises(InputError, match="broken.parquet: cannot be read as a Parquet table"):
        read_particles(tmp_path / "broken.parquet")


def test_cli_refuses_a_parquet_output_without_pyarrow_before_any_work(tmp_path, monkeypatch, capsys):
    import sys

    from napari_lbs._cli import main

    monkeypatch.setitem(sys.modules, "pyarrow", None)  # as if not installed
    tifffile.imwrite(tmp_path / "holo.tif", np.ones((48, 48), np.float32))
    (tmp_path / "p.csv").write_text("x_um,y_um,z_um,diameter_um,frame\n1,2,1800,20,0\n")
    for command in (["predict", str(tmp_path / "holo.tif"), "--model", str(tmp_path / "absent.pt")], ["track", str(tmp_path / "p.csv")]):
        assert main([*command, "--out", str(tmp_path / "out.parquet")]) == 2
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and "out.parquet: Parquet tables need pyarrow" in error[0], error  # before the model is even looked at
    assert not list(tmp_path.glob("out*"))


def test_cli_predicts_and_tracks_into_parquet_and_reads_a_one_frame_video(tmp_path, detector, vortex):
    import cv2
    import pyarrow.parquet as pq

    from napari_lbs._cli import main
    from napari_lbs._core import read_particles

    tifffile.imwrite(tmp_path / "run.tif", vortex.frames[:3], photometric="minisblack")
    assert main(["predict", str(tmp_path / "run.tif"), "--model", str(detector.path), "--out", str(tmp_path / "p.parquet")]) == 0
    provenance = json.loads((tmp_path / "p.json").read_text())  # the sidecar, as for a CSV
    assert json.loads(pq.read_schema(tmp_path / "p.parquet").metadata[b"napari_lbs"]) == provenance and provenance["frames"] == 3
    particles = read_particles(tmp_path / "p.parquet")
    assert set(particles["frame"]) == {0.0, 1.0, 2.0}
    assert main(["track", str(tmp_path / "p.parquet"), "--out", str(tmp_path / "t.parquet"), "--search-range-um", "10"]) == 0
    tracks = read_particles(tmp_path / "t.parquet")
    assert len(tracks["track"]) == len(particles["x_um"]) and np.isnan(tracks["dx_um"]).sum() == len(np.unique(tracks["track"]))  # NaN at each track's end
    stored = json.loads(pq.read_schema(tmp_path / "t.parquet").metadata[b"napari_lbs"])
    assert stored["tracks"]["search_range_um"] == 10.0 and stored["prediction"] == provenance and stored == json.loads((tmp_path / "t.json").read_text())

    # a video of one frame is one hologram, read through the recording's reader
    frame = np.clip(vortex.frames[0] * 128, 0, 255).astype(np.uint8)
    writer = cv2.VideoWriter(str(tmp_path / "one.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, frame.shape[::-1], isColor=False)
    writer.write(frame)
    writer.release()
    assert main(["predict", str(tmp_path / "one.avi"), "--model", str(detector.path), "--out", str(tmp_path / "one.csv")]) == 0
    one = _rows(tmp_path / "one.csv")
    assert "frame" not in one[0] and json.loads((tmp_path / "one.json").read_text())["source"] == str(tmp_path / "one.avi")


def test_a_bad_frame_late_in_a_recording_is_refused_before_any_work(tmp_path, detector):
    from napari_lbs._cli import main

    rng = np.random.default_rng(4)
    for k in range(5):
        tifffile.imwrite(tmp_path / f"f{k}.tif", rng.uniform(0.5, 1.5, (64, 64)).astype(np.float32))
    tifffile.imwrite(tmp_path / "f5.tif", rng.uniform(0.5, 1.5, (64, 48)).astype(np.float32))  # the last frame
    (tmp_path / "f6.png").write_bytes(b"not a png")
    steps = []
    with pytest.raises(InputError, match=r"f5.tif: expected the first frame's shape \(64, 64\), got \(64, 48\)"):
        predict_sequence([tmp_path / f"f{k}.tif" for k in range(6)], detector, progress=lambda d, t: steps.append(d))
    assert steps == []  # refused from the headers: not one frame predicted
    with pytest.raises(InputError, match="f6.png: cannot be read as an image"):
        predict_sequence([tmp_path / "f0.tif", tmp_path / "f6.png"], detector, progress=lambda d, t: steps.append(d))
    assert steps == []
    assert main(["predict", str(tmp_path / "f*.tif"), "--model", str(detector.path), "--out", str(tmp_path / "p.csv")]) == 2
    assert not list(tmp_path.glob("p.*"))  # nothing written, not even the work folder


def test_the_packaged_sample_hologram_webp_reads_as_one_frame_like_the_sample_loader():
    from napari_lbs._core import load_sample_hologram, open_frames
    from napari_lbs._core.foundation._samples import sample_hologram_path

    frames = open_frames([sample_hologram_path()])  # what `predict` does with one file
    assert len(frames) == 1
    np.testing.assert_array_equal(frames.read(0), load_sample_hologram())
