"""The experiment config: optics, sample volume, synthetic particles and tile size.

One TOML file describes an optical setup and a sample volume (docs/formats.md, "The
experiment config"). Every length is in micrometres.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from napari_lbs._core.foundation._errors import ConfigError
from napari_lbs._core.foundation._files import atomic_write_bytes, read_text

__all__ = [
    "ConfigError",
    "ExperimentConfig",
    "OpticsConfig",
    "ParticlesConfig",
    "TileConfig",
    "VolumeConfig",
    "load_config",
    "write_config",
    "MAX_PLANES",
]

# The most reconstruction planes (or particle layers) a config may ask for: 100 times the
# seed's 61. A 1024² stack of this depth is 24 GiB; commands also check the memory they need.
MAX_PLANES = 6100
# particles in one simulated field: a 1024² window holds about 1500 of 25 µm side by side at
# 2.2 µm pixels, so this is far beyond any sample while a simulation of it stays minutes long
MAX_PARTICLES = 100_000


def _require(condition: bool, key: str, message: str, value: object) -> None:
    if not condition:
        raise ConfigError(f"{key}: expected {message}, got {value!r}")


@dataclass(frozen=True)
class OpticsConfig:
    """Illumination and sampling.

    Attributes
    ----------
    wavelength_um : float
        Vacuum wavelength (µm). The seed experiment: 0.66.
    pixel_um : float
        Pixel pitch at the sample (µm): the sensor pitch of a lensless setup, the camera pitch
        divided by `magnification` behind an objective. Every computation uses this pitch. A
        pitch below half the medium wavelength is allowed: the angular spectrum is then cut at
        the medium's ``n/λ`` (the evanescent part carries no light to the sensor).
    medium_index : float
        Refractive index used for propagation; depths are then optical distances.
    magnification : float
        Lateral magnification between the sample and the camera (1: lensless). Recorded with
        the config so the camera pitch ``pixel_um * magnification`` (`camera_pixel_um`) is known.
    """

    wavelength_um: float = 0.66
    pixel_um: float = 2.2
    medium_index: float = 1.0
    magnification: float = 1.0

    def __post_init__(self) -> None:
        _require(0.0 < self.wavelength_um < 20.0, "optics.wavelength_um", "a wavelength in (0, 20) µm", self.wavelength_um)
        _require(0.0 < self.pixel_um < 1000.0, "optics.pixel_um", "a pixel pitch at the sample in (0, 1000) µm", self.pixel_um)
        _require(1.0 <= self.medium_index < 5.0, "optics.medium_index", "a refractive index in [1, 5)", self.medium_index)
        _require(0.0 < self.magnification <= 1000.0, "optics.magnification", "a magnification in (0, 1000]", self.magnification)

    @property
    def camera_pixel_um(self) -> float:
        """The camera's pixel pitch (µm): ``pixel_um * magnification``."""
        return self.pixel_um * self.magnification


def _plane_count(range_um: float, step_um: float) -> int:
    """Planes ``0, step, 2 step, ...`` within ``range_um`` (µm), both ends included."""
    return int(math.floor(range_um / step_um + 1e-9)) + 1


@dataclass(frozen=True)
class VolumeConfig:
    """Reconstruction depths (µm, distance from the particle to the sensor)."""

    z_min_um: float = 1800.0
    z_max_um: float = 4800.0
    z_step_um: float = 50.0

    def __post_init__(self) -> None:
        _require(self.z_min_um > 0.0, "volume.z_min_um", "a positive depth", self.z_min_um)
        _require(self.z_max_um > self.z_min_um, "volume.z_max_um", f"a depth larger than z_min_um={self.z_min_um}", self.z_max_um)
        _require(math.isfinite(self.z_max_um), "volume.z_max_um", "a finite depth", self.z_max_um)
        _require(self.z_step_um > 0.0, "volume.z_step_um", "a positive step", self.z_step_um)
        _require(
            self.z_step_um <= self.z_max_um - self.z_min_um,
            "volume.z_step_um",
            f"a step no larger than the range z_max_um - z_min_um = {self.z_max_um - self.z_min_um}",
            self.z_step_um,
        )
        _require(
            _plane_count(self.z_max_um - self.z_min_um, self.z_step_um) <= MAX_PLANES,
            "volume.z_step_um",
            f"a step of at least {(self.z_max_um - self.z_min_um) / (MAX_PLANES - 1):.3g} µm (at most {MAX_PLANES} planes)",
            self.z_step_um,
        )

    def planes_um(self, step_um: float | None = None) -> tuple[float, ...]:
        """Depths ``z_min_um, z_min_um + step, ...`` up to and including ``z_max_um`` (µm)."""
        step = self.z_step_um if step_um is None else step_um
        return tuple(self.z_min_um + i * step for i in range(_plane_count(self.z_max_um - self.z_min_um, step)))


@dataclass(frozen=True)
class ParticlesConfig:
    """What synthetic particle fields look like."""

    diameter_min_um: float = 20.0
    diameter_max_um: float = 30.0
    per_tile: int = 12
    layer_step_um: float = 200.0

    def __post_init__(self) -> None:
        _require(self.diameter_min_um > 0.0, "particles.diameter_min_um", "a positive diameter", self.diameter_min_um)
        _require(
            self.diameter_max_um >= self.diameter_min_um,
            "particles.diameter_max_um",
            f"a diameter >= diameter_min_um={self.diameter_min_um}",
            self.diameter_max_um,
        )
        _require(math.isfinite(self.diameter_max_um), "particles.diameter_max_um", "a finite diameter", self.diameter_max_um)
        _require(isinstance(self.per_tile, int) and not isinstance(self.per_tile, bool) and 0 <= self.per_tile <= MAX_PARTICLES, "particles.per_tile",
                 f"an integer in [0, {MAX_PARTICLES}]", self.per_tile)
        _require(self.layer_step_um > 0.0, "particles.layer_step_um", "a positive step", self.layer_step_um)


@dataclass(frozen=True)
class TileConfig:
    """Network input tile."""

    size: int = 256

    def __post_init__(self) -> None:
        _require(isinstance(self.size, int) and 16 <= self.size <= 8192, "tile.size", "an integer in [16, 8192]", self.size)


@dataclass(frozen=True)
class ExperimentConfig:
    """An optical setup and a sample volume (docs/formats.md). Frozen and validated on construction."""

    optics: OpticsConfig = field(default_factory=OpticsConfig)
    volume: VolumeConfig = field(default_factory=VolumeConfig)
    particles: ParticlesConfig = field(default_factory=ParticlesConfig)
    tile: TileConfig = field(default_factory=TileConfig)

    def __post_init__(self) -> None:
        _require(
            self.particles.layer_step_um <= self.volume.z_max_um - self.volume.z_min_um,
            "particles.layer_step_um",
            f"a step no larger than the depth range {self.volume.z_max_um - self.volume.z_min_um}",
            self.particles.layer_step_um,
        )
        _require(
            _plane_count(self.volume.z_max_um - self.volume.z_min_um, self.particles.layer_step_um) <= MAX_PLANES,
            "particles.layer_step_um",
            f"at most {MAX_PLANES} layers over the depth range",
            self.particles.layer_step_um,
        )

    def layer_depths_um(self) -> tuple[float, ...]:
        """Depths of the simulated particle layers (µm): z_min_um ... z_max_um every layer_step_um."""
        return self.volume.planes_um(self.particles.layer_step_um)

    def to_dict(self) -> dict[str, dict[str, float | int]]:
        """Plain nested dict, the same shape as the TOML file."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ExperimentConfig":
        """Build from a nested dict; unknown sections or keys and wrong types raise `ConfigError`."""
        section_classes = {"optics": OpticsConfig, "volume": VolumeConfig, "particles": ParticlesConfig, "tile": TileConfig}
        unknown = set(data) - set(section_classes)
        if unknown:
            raise ConfigError(f"{sorted(unknown)[0]}: unknown section; expected one of {sorted(section_classes)}")
        built = {}
        for name, section_cls in section_classes.items():
            values = data.get(name, {})
            if not isinstance(values, dict):
                raise ConfigError(f"{name}: expected a table, got {values!r}")
            defaults = {f.name: f.default for f in dataclasses.fields(section_cls)} | _INPUT_ONLY.get(name, {})
            for key, value in values.items():
                if key not in defaults:
                    raise ConfigError(f"{name}.{key}: unknown key; expected one of {sorted(defaults)}")
                expected = type(defaults[key])
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise ConfigError(f"{name}.{key}: expected a number, got {value!r}")
                if isinstance(value, int) and abs(value) > 2**53:  # beyond every range below, and beyond float's exact integers
                    raise ConfigError(f"{name}.{key}: expected a number of sensible size, got an integer of {len(str(abs(value)))} digits")
                if expected is int and not float(value).is_integer():
                    raise ConfigError(f"{name}.{key}: expected an integer, got {value!r}")
                if isinstance(value, float) and not math.isfinite(value):
                    raise ConfigError(f"{name}.{key}: expected a finite number, got {value!r}")
            kwargs = {k: (int(v) if type(defaults[k]) is int else float(v)) for k, v in values.items()}
            if "camera_pixel_um" in kwargs:
                kwargs = _sample_pixel(kwargs)
            built[name] = section_cls(**kwargs)
        return cls(**built)


# Keys a file may give that the config stores in another form: a camera pitch becomes the pitch
# at the sample (camera pitch / magnification), which every computation uses.
_INPUT_ONLY = {"optics": {"camera_pixel_um": 0.0}}


def _sample_pixel(optics: dict[str, float]) -> dict[str, float]:
    """``optics`` with ``camera_pixel_um`` replaced by the pitch at the sample, ``pixel_um``; both given must agree."""
    optics = dict(optics)
    camera = optics.pop("camera_pixel_um")
    magnification = optics.get("magnification", 1.0)
    _require(0.0 < camera < 1e6, "optics.camera_pixel_um", "a camera pixel pitch in (0, 1e6) µm", camera)
    _require(magnification > 0.0, "optics.magnification", "a magnification in (0, 1000]", magnification)
    at_sample = camera / magnification
    if "pixel_um" in optics:
        _require(math.isclose(optics["pixel_um"], at_sample, rel_tol=1e-6), "optics.camera_pixel_um",
                 f"pixel_um x magnification = {optics['pixel_um'] * magnification:.6g} µm (or give only one of pixel_um, camera_pixel_um)", camera)
    optics["pixel_um"] = at_sample
    return optics


_COMMENTS = {
    "optics.wavelength_um": "vacuum wavelength (the seed experiment: 660 nm)",
    "optics.pixel_um": "pixel pitch at the sample (camera pitch / magnification)",
    "optics.medium_index": "refractive index used for propagation (z are optical distances)",
    "optics.magnification": "objective magnification (1: lensless)",
    "volume.z_min_um": "nearest reconstruction plane",
    "volume.z_max_um": "farthest reconstruction plane",
    "volume.z_step_um": "spacing of reconstruction planes (experimental z-stack)",
    "particles.layer_step_um": "spacing of the simulated particle layers",
    "tile.size": "tile edge in pixels (network input)",
}


def load_config(path: str | Path | None = None) -> ExperimentConfig:
    """Read and validate an experiment config from TOML; ``None`` gives the defaults.

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ConfigError
        Malformed TOML, an unknown key or an impossible value; the message names the key.
    InputError
        Not UTF-8 text; the message names the file.
    """
    if path is None:
        return ExperimentConfig()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: config file not found")
    try:
        data = tomllib.loads(read_text(path, what="config"))
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML ({error})") from None
    except RecursionError:  # arrays or tables nested thousands deep
        raise ConfigError(f"{path}: not a config (values nested too deeply)") from None
    return ExperimentConfig.from_dict(data)


def config_to_toml(config: ExperimentConfig) -> str:
    """The TOML text of ``config``, commented like docs/formats.md."""
    lines = []
    for section, values in config.to_dict().items():
        if lines:
            lines.append("")
        lines.append(f"[{section}]")
        for key, value in values.items():
            text = f"{key} = {value!r}"
            comment = _COMMENTS.get(f"{section}.{key}")
            if (section, key) == ("optics", "magnification") and value != 1.0:
                comment = f"objective magnification (camera pitch {config.optics.camera_pixel_um:.6g} µm)"
            lines.append(f"{text:<26}# {comment}" if comment else text)
    return "\n".join(lines) + "\n"


def write_config(path: str | Path, config: ExperimentConfig | None = None, *, force: bool = False) -> Path:
    """Write ``config`` (default: the defaults docs/config.md lists) as TOML, atomically.

    An existing ``path`` is replaced only with ``force`` (and only a regular file: `check_target`).
    """
    text = config_to_toml(ExperimentConfig() if config is None else config)
    return atomic_write_bytes(Path(path), text.encode("utf-8"), force=force)
