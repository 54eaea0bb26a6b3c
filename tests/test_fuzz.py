"""Fuzzing the readers and the console script's numeric flags: whatever the bytes, a reader
returns a valid result or raises `InputError` / `ConfigError` (one line naming the culprit),
never another exception; a flag value never ends in an internal error. Each test is bounded
(``max_examples``) so the file runs in well under a minute on two cores."""

import json
import math

import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from napari_lbs._cli import main
from napari_lbs._core import InputError
from napari_lbs._core.foundation import PARTICLE_COLUMNS

BOUNDED = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
_REFUSALS = (ValueError,)  # InputError and ConfigError are both ValueErrors


def _one_line(error: BaseException) -> None:
    text = str(error)
    assert text and "\n" not in text and "Traceback" not in text, text


def _read_or_refused(read, path):
    """``read(path)``, or None when it refuses in one line naming the file; any other exception fails the test."""
    try:
        return read(path)
    except _REFUSALS as error:
        _one_line(error)
        assert path.name in str(error), error
        return None


# --- TIFF -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiff_bytes(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("tiff") / "h.tif"
    tifffile.imwrite(path, 1.0 + np.random.default_rng(0).random((32, 32), np.float32), rowsperstrip=8, description="{}")
    return path.read_bytes()


@BOUNDED
@given(data=st.data())
def test_a_damaged_tiff_is_read_as_a_valid_hologram_or_refused(tmp_path, tiff_bytes, data):
    from napari_lbs._core.foundation import read_hologram

    damaged = bytearray(tiff_bytes)
    for _ in range(data.draw(st.integers(1, 6))):
        at = data.draw(st.integers(0, len(damaged) - 1))
        damaged[at] = data.draw(st.integers(0, 255))
    cut = data.draw(st.none() | st.integers(0, len(damaged)))
    path = tmp_path / "fuzz.tif"
    path.write_bytes(bytes(damaged[:cut]))
    image = _read_or_refused(read_hologram, path)
    if image is not None:
        assert image.ndim == 2 and np.all(np.isfinite(image)) and float(np.abs(image).max()) < 1.9e19


# --- BMP ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bmp_bytes(tmp_path_factory) -> dict[str, bytes]:
    """A 32x32 hologram as an 8-bit grey (a palette) and a 24-bit colour BMP."""
    from PIL import Image

    folder = tmp_path_factory.mktemp("bmp")
    grey = (100 + 100 * np.random.default_rng(0).random((32, 32))).astype(np.uint8)
    images = {"L": Image.fromarray(grey), "RGB": Image.fromarray(np.stack([grey, grey // 2, grey // 3], axis=-1))}
    for mode, image in images.items():
        image.save(folder / f"{mode}.bmp")
    return {mode: (folder / f"{mode}.bmp").read_bytes() for mode in images}


@BOUNDED
@given(data=st.data())
def test_a_damaged_bmp_is_read_as_a_valid_hologram_or_refused_by_both_readers(tmp_path, bmp_bytes, data):
    from napari_lbs._core.foundation import read_hologram
    from napari_lbs._core.recordings import open_frames

    damaged = bytearray(bmp_bytes[data.draw(st.sampled_from(sorted(bmp_bytes)))])
    for _ in range(data.draw(st.integers(1, 6))):
        at = data.draw(st.integers(0, 60) | st.integers(0, len(damaged) - 1))  # the headers often: sizes, offsets, depth, compression
        damaged[at] = data.draw(st.integers(0, 255))
    cut = data.draw(st.none() | st.integers(0, len(damaged)))
    path = tmp_path / "fuzz.bmp"
    path.write_bytes(bytes(damaged[:cut]))

    def frame(path):
        with open_frames([path]) as frames:
            frames.check()
            return frames.read(0)

    for read in (read_hologram, frame):
        image = _read_or_refused(read, path)
        if image is not None:
            assert image.ndim == 2 and min(image.shape) >= 16 and np.all(np.isfinite(image)), image.shape


# --- CSV particle tables ----------------------------------------------------------------------------

_CELLS = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-(10**30), 10**30).map(str),
                   st.text(st.characters(blacklist_categories=("Cs",)), max_size=6), st.sampled_from(["", " ", "nan", "1e999", '"', "1,2"]))


@BOUNDED
@given(header=st.lists(st.sampled_from([*PARTICLE_COLUMNS, "frame", "score", " x_um", ""]), min_size=0, max_size=7),
       rows=st.lists(st.lists(_CELLS, min_size=0, max_size=8), max_size=5), encoding=st.sampled_from(["utf-8", "utf-8-sig", "latin-1", "utf-16"]))
def test_a_particle_table_is_read_whole_or_refused(tmp_path, header, rows, encoding):
    from napari_lbs._core.foundation import read_particles

    path = tmp_path / "fuzz.csv"
    path.write_bytes("\n".join(",".join(cells) for cells in [header, *rows]).encode(encoding, errors="replace"))
    table = _read_or_refused(read_particles, path)
    if table is not None:
        assert all(np.all(np.isfinite(table[name])) for name in PARTICLE_COLUMNS[:3])
        assert len({len(values) for values in table.values()}) == 1


# --- TOML configs -----------------------------------------------------------------------------------

_TOML_VALUES = st.one_of(st.integers(-(10**400), 10**400), st.floats(allow_nan=True, allow_infinity=True), st.booleans(), st.text(max_size=5))


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    return str(value)


@BOUNDED
@given(sections=st.dictionaries(st.sampled_from(["optics", "volume", "particles", "tile", "extra"]),
                                st.dictionaries(st.sampled_from(["wavelength_um", "pixel_um", "medium_index", "z_min_um", "z_max_um", "z_step_um", "per_tile",
                                                                 "diameter_min_um", "diameter_max_um", "layer_step_um", "size", "colour"]), _TOML_VALUES, max_size=4),
                                max_size=4),
       nesting=st.integers(0, 3000))
def test_a_config_is_loaded_valid_or_refused_naming_the_key_or_file(tmp_path, sections, nesting):
    from napari_lbs._core import load_config

    text = "".join(f"[{name}]\n" + "".join(f"{key} = {_toml(value)}\n" for key, value in values.items()) for name, values in sections.items())
    path = tmp_path / "fuzz.toml"
    path.write_text(f"deep = {'[' * nesting}{']' * nesting}\n" + text if nesting > 1 else text, encoding="utf-8")
    try:
        config = load_config(path)
    except _REFUSALS as error:
        _one_line(error)
    else:
        assert 0 <= config.particles.per_tile <= 100_000 and len(config.volume.planes_um()) <= 6100


# --- report.json (effects for generate) ----------------------------------------------------------

_JSON = st.recursive(st.none() | st.booleans() | st.integers(-(10**400), 10**400) | st.floats() | st.text(max_size=4),
                     lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3), max_leaves=8)


@BOUNDED
@given(data=st.data())
def test_a_diagnosis_report_gives_effects_within_their_limits_or_is_refused(data):
    from napari_lbs._core.physics._effects import EFFECTS, LIMITS, effects_from_report

    effect = data.draw(st.sampled_from(sorted(EFFECTS)))
    params = data.draw(st.dictionaries(st.sampled_from([*EFFECTS[effect].bounds, "baseline.gamma", "other"]), _JSON, max_size=4) | _JSON)
    report = data.draw(st.sampled_from([{"verdict": {"id": effect}, "effects": [{"id": effect, "params": params}]}, {"verdict": params, "effects": params}, params]))
    try:
        effects = effects_from_report(json.loads(json.dumps(report)), name="r.json")
    except _REFUSALS as error:
        _one_line(error)
        assert str(error).startswith("r.json: ")
    else:
        for effect_id, values in effects.items():
            for name, value in values.items():
                low, high = LIMITS[effect_id][name]
                assert low <= value <= high


# --- the console script's numeric flags ----------------------------------------------------------

_NUMERIC_FLAGS = {
    "simulate": ["--size", "--particles", "--seed", "--frames", "--speed-um"],
    "calibrate": ["--seed", "--generations", "--population", "--runs"],
    "generate": ["--groups", "--seed", "--context-planes", "--workers", "--impurities", "--neighbours-margin-px"],
    "train": ["--epochs", "--minutes", "--patience", "--batch-size", "--learning-rate", "--seed", "--validation-groups", "--patch-size", "--foreground-weight"],
    "predict": ["--background-window", "--workers", "--threshold", "--material"],
    "track": ["--search-range-um", "--axial-search-range-um", "--memory"],
    "diagnose": ["--tile", "--seed"],
    "evaluate": ["--lateral-tol-um", "--axial-tol-um"],
}
_FLAG_VALUES = st.one_of(st.integers(-(10**30), 10**30).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                         st.sampled_from(["", "x", "1,5", "0x10", "1e400", "-0", "1_000", " 7 "]))


@BOUNDED
@given(data=st.data(), command=st.sampled_from(sorted(_NUMERIC_FLAGS)))
def test_any_numeric_flag_value_exits_0_or_2_with_one_line_never_an_internal_error(tmp_path, capsys, data, command):
    flags = data.draw(st.lists(st.sampled_from(_NUMERIC_FLAGS[command]), min_size=1, max_size=3, unique=True))
    absent = str(tmp_path / "absent")  # every input missing: after the flags, the command stops at its first input
    positional = {"calibrate": [absent], "train": [absent], "predict": [absent], "track": [absent], "diagnose": [absent], "evaluate": [absent, absent]}.get(command, [])
    argv = [command, *positional, "--out", str(tmp_path / "out" / "o.csv")]
    if command in ("simulate", "calibrate", "generate", "diagnose"):
        argv += ["--config", absent + ".toml"]
    if command == "predict":
        argv += ["--model", absent + ".pt"]
    values = {flag: data.draw(_FLAG_VALUES) for flag in flags}
    for flag, value in values.items():
        argv.append(f"{flag}={value}")
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "internal error" not in err[0], (argv, err)
    assert not (tmp_path / "out").exists()
