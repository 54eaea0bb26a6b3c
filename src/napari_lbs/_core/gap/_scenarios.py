"""The simulations a diagnosis learns from: scenarios drawn from a broad prior, and the tiles they make.

A *scenario* is one simulated experiment: which catalog effects are present (none, one or
two) and at what strength, and every nuisance the answer must not depend on — the particle
model (opaque discs, absorbing or weakly transmitting spheres of any phase delay), how many
particles and how large, the camera's fringe contrast, read noise and response. Its
hologram is simulated as the diagnosis sees a real one: a grid of tiles at their places on
the sensor (`TileGrid`), each tile cut from one periodic field so that, as on a large
sensor, every tile has particles all around it.

``particle_phase`` means something a user can act on: the particles transmit at least
`TRANSPARENT` of the light (transparent beads, cells, droplets), where the nuisance spheres of
every other scenario transmit at most `OPAQUE`; the particle model is otherwise drawn the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.physics import EFFECTS, OPTICAL_EFFECTS, check_effects, optical_hologram, sensor_image
from napari_lbs._core.physics import random_particle_field

__all__ = ["TileGrid", "Scenario", "ScenarioPrior", "draw_scenario", "simulate_tiles", "catalog_candidates", "EFFECT_BRANCHES", "TRANSPARENT", "OPAQUE", "SATURATION"]

TRANSPARENT = 0.55  # particle_phase: the particles transmit at least this fraction of the field's amplitude
OPAQUE = 0.35  # every other scenario's spheres transmit at most this
SATURATION = (1.2, 3.0)  # full scale over the mean level of a camera whose bit depth is known (the real hologram: 255 / 161 = 1.58)


@dataclass(frozen=True)
class TileGrid:
    """Where a diagnosis reads a hologram: ``per_side``² tiles of ``tile_px``, one at the centre of each cell of the sensor.

    Attributes
    ----------
    frame_shape : (int, int)
        The sensor's (rows, cols), pixels.
    tile_px : int
        Tile edge (pixels).
    per_side : int
        Tiles along each axis (cells of the frame).
    """

    frame_shape: tuple[int, int]
    tile_px: int
    per_side: int = 4

    def origins(self, shift: tuple[int, int] = (0, 0)) -> list[tuple[int, int]]:
        """Top-left pixel of every tile on the sensor, row by row; ``shift`` moves every tile within its cell (pixels)."""
        cell = (self.frame_shape[0] // self.per_side, self.frame_shape[1] // self.per_side)
        out = []
        for i in range(self.per_side):
            for j in range(self.per_side):
                r = i * cell[0] + (cell[0] - self.tile_px) // 2 + shift[0]
                c = j * cell[1] + (cell[1] - self.tile_px) // 2 + shift[1]
                out.append((int(np.clip(r, i * cell[0], (i + 1) * cell[0] - self.tile_px)), int(np.clip(c, j * cell[1], (j + 1) * cell[1] - self.tile_px))))
        return out

    def shifts(self) -> list[tuple[int, int]]:
        """Shifts (`origins`) that together cover each cell with non-overlapping tiles, as far as it holds whole tiles (at least the centre)."""
        cell = (self.frame_shape[0] // self.per_side, self.frame_shape[1] // self.per_side)
        steps = [max(c // self.tile_px, 1) for c in cell]
        offsets = [[k * self.tile_px - (n - 1) * self.tile_px // 2 for k in range(n)] for n in steps]  # whole pixels: tiles never overlap
        return [(a, b) for a in offsets[0] for b in offsets[1]]

    def centres(self, shift: tuple[int, int] = (0, 0)) -> np.ndarray:
        """(tiles, 2) tile centres (`origins` at ``shift``) as (y, x) fractions of the frame, −0.5 … 0.5."""
        half = self.tile_px / 2
        return np.array([((r + half) / self.frame_shape[0] - 0.5, (c + half) / self.frame_shape[1] - 0.5) for r, c in self.origins(shift)])


@dataclass(frozen=True)
class ScenarioPrior:
    """What a diagnosis's simulations are drawn from.

    Attributes
    ----------
    candidates : tuple of str
        The catalog effects that may be present.
    none, one : float
        Probability of no effect and of exactly one (the rest: two).
    known : dict
        ``{effect_id: params}`` in every scenario (what the user knows).
    bits : float or None
        The file's bit depth: every scenario is quantised so, its saturation level (relative
        to the mean) drawn from `SATURATION` (it varies with the scene, not the setup).
    density : (float, float)
        Particle density relative to the config's, log-uniform between these.
    strength : (float, float)
        Where in each effect's range, from its weakest (0) to its strongest (1) setting, a
        present effect's strength is drawn (uniformly; on a log scale for scale parameters).
    """

    candidates: tuple
    none: float = 0.3
    one: float = 0.45
    known: dict = field(default_factory=dict)
    bits: float | None = None
    density: tuple = (0.3, 3.0)
    strength: tuple = (0.0, 1.0)


@dataclass(frozen=True)
class Scenario:
    """One simulated experiment: ``effects`` (known and present, with parameters), ``present`` (the labels), nuisances."""

    present: tuple
    effects: dict
    baseline: dict
    particle_model: dict
    density: float


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


# effects of two kinds, each scenario one of them: the strength parameter of each kind
EFFECT_BRANCHES = {"coherence": ("theta_mrad", "bandwidth_nm"), "parasitic_fringes": ("amplitude", "dust_per_mpx")}

# each effect's strength parameters: (weakest, strongest, log scale); the others are drawn over their whole range
_STRENGTHS = {
    "illumination": {"depth": (0.1, 0.7, False)},
    "shot_noise": {"log10_photons": (2.8, 1.0, False)},
    "quantization": {"bits": (6.49, 2.51, False), "saturation": (3.0, 1.3, False)},
    "sensor_blur": {"sigma_px": (0.5, 1.6, False)},
    "coherence": {"theta_mrad": (0.6, 3.0, False), "bandwidth_nm": (8.0, 60.0, True)},
    "particle_phase": {"index_contrast": (0.003, 0.3, True), "transmission": (TRANSPARENT, 1.0, False)},
    "parasitic_fringes": {"amplitude": (0.02, 0.12, False), "dust_per_mpx": (20.0, 300.0, True)},
    "spherical_wave": {"source_mm": (80.0, 10.0, True)},
}


def _effect_params(effect_id: str, rng: np.random.Generator, strength: tuple) -> dict:
    """A present effect's parameters, drawn from a broad prior (strong enough to matter, not beyond physics)."""

    def draw(name: str) -> float:
        weak, strong, log = _STRENGTHS[effect_id][name]
        t = rng.uniform(*strength)
        return float(math.exp(math.log(weak) + t * (math.log(strong) - math.log(weak)))) if log else float(weak + t * (strong - weak))

    if effect_id == "illumination":
        return {"depth": draw("depth"), "x0": rng.uniform(-0.45, 0.45), "y0": rng.uniform(-0.45, 0.45)}
    if effect_id == "shot_noise":
        return {"log10_photons": draw("log10_photons")}
    if effect_id == "quantization":
        return {"bits": float(round(draw("bits"))), "saturation": draw("saturation")}
    if effect_id == "sensor_blur":
        return {"sigma_px": draw("sigma_px")}
    if effect_id == "coherence":  # spatial or temporal, as likely
        return {"theta_mrad": draw("theta_mrad"), "bandwidth_nm": 0.0} if rng.random() < 0.5 else {"theta_mrad": 0.0, "bandwidth_nm": draw("bandwidth_nm")}
    if effect_id == "particle_phase":
        return {"index_contrast": draw("index_contrast"), "transmission": draw("transmission")}
    if effect_id == "multiple_scattering":
        return {"on": 1.0}
    if effect_id == "parasitic_fringes":  # an etalon's fringe or dust on a window, as likely
        if rng.random() < 0.5:
            return {"amplitude": draw("amplitude"), "period_px": rng.uniform(4.0, 24.0), "angle_rad": rng.uniform(0, math.pi), "dust_per_mpx": 0.0}
        return {"amplitude": 0.0, "dust_per_mpx": draw("dust_per_mpx"), "dust_zone_px": rng.uniform(8.0, 60.0), "dust_grain_px": _log_uniform(rng, 1.5, 20.0)}
    if effect_id == "spherical_wave":
        return {"source_mm": draw("source_mm")}
    raise KeyError(effect_id)


def draw_scenario(prior: ScenarioPrior, rng: np.random.Generator) -> Scenario:
    """One scenario from ``prior``: the effects present (none, one or two) and every nuisance."""
    u = rng.random()
    count = 0 if u < prior.none else 1 if u < prior.none + prior.one else 2
    present = tuple(sorted(rng.choice(prior.candidates, size=min(count, len(prior.candidates)), replace=False).tolist())) if prior.candidates else ()
    effects = {k: dict(v) for k, v in prior.known.items()}
    if prior.bits:
        effects["quantization"] = {"bits": float(prior.bits), "saturation": rng.uniform(*SATURATION)}
    for effect_id in present:
        effects[effect_id] = _effect_params(effect_id, rng, prior.strength)
    # the particles: discs, or spheres that absorb most of the light with any phase delay;
    # transparent spheres are the particle_phase effect itself
    if "particle_phase" not in effects:
        model = {"index_contrast": _log_uniform(rng, 0.003, 0.3), "transmission": rng.uniform(0.0, OPAQUE)} if rng.random() < 0.5 else {}
        if model:
            effects["particle_phase"] = model
    else:
        model = dict(effects["particle_phase"])
    density = _log_uniform(rng, *prior.density)
    if "multiple_scattering" in present:
        density = min(max(density, 1.0) * rng.uniform(3.0, 8.0), 10.0)  # shadowing needs particles overlapping in projection
    baseline = {"contrast": rng.uniform(0.5, 1.2), "sigma": _log_uniform(rng, 0.004, 0.08), "gamma": rng.uniform(0.7, 1.4)}
    return Scenario(present, check_effects(effects), baseline, model, density)


def simulate_tiles(scenario: Scenario, config: ExperimentConfig, grid: TileGrid, rng: np.random.Generator) -> list[np.ndarray]:
    """The tiles (float32, unobstructed ≈ 1) of ``scenario`` at ``grid``'s places, as a camera records them.

    One periodic field of ``per_side × tile_px`` pixels a side holds the particles; its light
    reaches the sensor (the optical effects), then the camera (baseline contrast, read noise,
    gamma and the sensor effects), each of its pixels at the place on the sensor of the tile it
    belongs to (`sensor_image`'s ``frame_px``).
    """
    side = grid.per_side * grid.tile_px
    area_ratio = side * side / float(config.tile.size) ** 2
    count = rng.poisson(config.particles.per_tile * area_ratio * scenario.density)
    layers = np.arange(config.volume.z_min_um, config.volume.z_max_um + 1e-6, max(config.particles.layer_step_um, config.volume.z_step_um))
    particles = random_particle_field(
        (side, side), count=int(count), diameter_min_um=config.particles.diameter_min_um * 0.8, diameter_max_um=config.particles.diameter_max_um * 1.2,
        layers_um=layers, pixel_um=config.optics.pixel_um, seed=rng,
    )
    optical = {k: v for k, v in scenario.effects.items() if k in OPTICAL_EFFECTS}
    intensity = optical_hologram(particles, optical, wavelength_um=config.optics.wavelength_um, medium_index=config.optics.medium_index, periodic=True)
    # each pixel of the simulated field at its tile's place on the sensor
    origins = grid.origins()
    rows_at = np.concatenate([origins[i * grid.per_side][0] + np.arange(grid.tile_px) for i in range(grid.per_side)])
    cols_at = np.concatenate([origins[j][1] + np.arange(grid.tile_px) for j in range(grid.per_side)])
    sensor = {k: v for k, v in scenario.effects.items() if k not in OPTICAL_EFFECTS}
    noise = rng.standard_normal(intensity.shape).astype(np.float32)
    image = sensor_image(intensity, scenario.baseline, sensor, noise=noise, frame_px=(rows_at, cols_at, grid.frame_shape))
    t = grid.tile_px
    return [image[i * t : (i + 1) * t, j * t : (j + 1) * t] for i in range(grid.per_side) for j in range(grid.per_side)]


def catalog_candidates(known: dict) -> tuple:
    """The catalog effects a diagnosis can name: all but the known ones."""
    return tuple(e for e in EFFECTS if e not in known)
