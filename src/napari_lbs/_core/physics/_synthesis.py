"""Random particle fields, their layer images, holograms and ground-truth label planes (HCS).

The seed paper's high-contrast simulation (Sec. 2.1): opaque particles on equally spaced
layers, each layer's image diffracted to the sensor by angular-spectrum propagation and the
fields superposed. Lengths in µm; positions follow docs/formats.md (``x_um = col * pixel_um``,
pixel centres at integer indices; ``z_um`` = distance to the sensor).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.fft

from napari_lbs._core.foundation import MAX_PARTICLES, InputError, check_number
from napari_lbs._core.physics._optics import padded_shape, propagation_grid, superpose, transfer_function
from napari_lbs._core.foundation import process_threads

__all__ = [
    "ParticleField",
    "Distractors",
    "SizeDistribution",
    "random_particle_field",
    "distractor_scene",
    "distractors_from_report",
    "sizes_from_report",
    "count_for_ppp",
    "disc_coverage",
    "layer_images",
    "simulate_hologram",
    "label_planes",
    "LABEL_SCALE",
]

LABEL_SCALE = 4.0  # label value = LABEL_SCALE * diameter (µm), as in the seed paper
_LABEL_HALF = 1  # 3x3 squares
_SUPERSAMPLE = 8  # 8x8 sub-samples per pixel: coverage quantised to 1/64


@dataclass(frozen=True)
class ParticleField:
    """Particles in a volume in front of a ``shape`` sensor of pitch ``pixel_um``.

    Attributes
    ----------
    x_um, y_um, z_um, diameter_um : (n,) float64 arrays
        Centres (µm; x along columns, y along rows, z = distance to the sensor) and diameters.
    shape : (int, int)
        Sensor window (rows, cols).
    pixel_um : float
        Sensor pitch (µm).
    """

    x_um: np.ndarray
    y_um: np.ndarray
    z_um: np.ndarray
    diameter_um: np.ndarray
    shape: tuple[int, int]
    pixel_um: float

    def __len__(self) -> int:
        return int(self.x_um.size)

    def table(self) -> dict[str, np.ndarray]:
        """The particle table (docs/formats.md columns)."""
        return {"x_um": self.x_um, "y_um": self.y_um, "z_um": self.z_um, "diameter_um": self.diameter_um}

    def layers_um(self) -> np.ndarray:
        """Distinct particle depths (µm), farthest first."""
        return np.unique(self.z_um)[::-1]


@dataclass(frozen=True)
class Distractors:
    """Scatterers a real sample holds besides the particles to report: in training data they are unlabelled.

    Attributes
    ----------
    impurities_per_tile : int
        Small scatterers (debris, dust or bubbles in the medium) per ``tile.size`` window, at
        uniform positions and depths over the volume, with diameters uniform in
        ``impurity_diameter_min_um`` … ``impurity_diameter_max_um`` (µm), below the particles'
        size range. A real sample's back-propagation shows such small foci (the seed's real
        hologram has dozens); a network that never saw them reports them as particles.
    impurity_diameter_min_um, impurity_diameter_max_um : float
        Their diameter range (µm).
    neighbours_margin_px : int
        The hologram is simulated over the window widened by this margin on every side, with
        particles and impurities at the same density there, and only the window is kept. A
        real hologram is a crop of a larger field: near its edges it holds fringes of
        particles whose centres lie outside it, which are not to be reported.
    """

    impurities_per_tile: int = 0
    impurity_diameter_min_um: float = 4.0
    impurity_diameter_max_um: float = 14.0
    neighbours_margin_px: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.impurities_per_tile, int) and self.impurities_per_tile >= 0):
            raise InputError(f"impurities_per_tile: expected a non-negative integer, got {self.impurities_per_tile!r}")
        if not 0.0 < self.impurity_diameter_min_um <= self.impurity_diameter_max_um:
            raise InputError(f"impurity_diameter_min_um: expected 0 < min <= impurity_diameter_max_um (um), got {self.impurity_diameter_min_um!r} and {self.impurity_diameter_max_um!r}")
        if not (isinstance(self.neighbours_margin_px, int) and 0 <= self.neighbours_margin_px <= 4096):
            raise InputError(f"neighbours_margin_px: expected 0..4096 pixels, got {self.neighbours_margin_px!r}")

    @property
    def active(self) -> bool:
        return self.impurities_per_tile > 0 or self.neighbours_margin_px > 0

    def to_dict(self) -> dict:
        """The settings that shape the data (no impurity diameters without impurities)."""
        sizes = {"impurity_diameter_min_um": float(self.impurity_diameter_min_um), "impurity_diameter_max_um": float(self.impurity_diameter_max_um)}
        return {"impurities_per_tile": int(self.impurities_per_tile), **(sizes if self.impurities_per_tile else {}), "neighbours_margin_px": int(self.neighbours_margin_px)}

    @classmethod
    def from_dict(cls, payload: dict | None) -> Distractors:
        return cls(**payload) if payload else cls()


# A scene's size quantiles are taken for training data from this many particles within the
# config's sizes: five quantiles of fewer are hardly a distribution.
_LEAST_SIZED = 10


@dataclass(frozen=True)
class SizeDistribution:
    """Particle diameters drawn from a measured distribution: its quantile function, piecewise linear.

    Attributes
    ----------
    levels : tuple of float
        Cumulative probabilities, increasing, within (0, 1) (a diagnosis report's percentiles
        over 100).
    diameters_um : tuple of float
        The diameter (µm) at each level, non-decreasing.

    A draw is the quantile function at a uniform number (inverse transform sampling), linear
    between the given quantiles and, below the first and above the last level, out to the
    least and largest diameter allowed (the config's range): the measured sizes set where
    most particles lie, the config's range still bounds them all.
    """

    levels: tuple[float, ...]
    diameters_um: tuple[float, ...]

    def __post_init__(self) -> None:
        try:
            levels, diameters = np.asarray(self.levels, np.float64), np.asarray(self.diameters_um, np.float64)
        except (TypeError, ValueError):
            raise InputError(f"levels, diameters_um: expected numbers, got {self.levels!r} and {self.diameters_um!r}") from None
        if levels.ndim != 1 or levels.size == 0 or levels.shape != diameters.shape:
            raise InputError(f"levels, diameters_um: expected two equally long lists of numbers, got {levels.size} and {diameters.size}")
        if not (np.all(np.isfinite(levels)) and np.all((levels > 0) & (levels < 1)) and np.all(np.diff(levels) > 0)):
            raise InputError(f"levels: expected increasing cumulative probabilities within (0, 1), got {self.levels!r}")
        if not (np.all(np.isfinite(diameters)) and np.all(diameters > 0) and np.all(np.diff(diameters) >= 0)):
            raise InputError(f"diameters_um: expected positive, non-decreasing diameters (um), got {self.diameters_um!r}")

    def draw(self, rng: np.random.Generator, count: int, *, diameter_min_um: float, diameter_max_um: float) -> np.ndarray:
        """``count`` diameters (µm, float64) within ``[diameter_min_um, diameter_max_um]``; one uniform draw each from ``rng``."""
        knots = np.clip(np.asarray(self.diameters_um, np.float64), diameter_min_um, diameter_max_um)
        return np.interp(rng.uniform(0.0, 1.0, count), [0.0, *self.levels, 1.0], [diameter_min_um, *knots, diameter_max_um])

    def to_dict(self) -> dict:
        return {"levels": [float(v) for v in self.levels], "diameters_um": [float(v) for v in self.diameters_um]}

    @classmethod
    def from_dict(cls, payload: dict | None) -> SizeDistribution | None:
        return cls(tuple(payload["levels"]), tuple(payload["diameters_um"])) if payload else None


def sizes_from_report(report: dict, *, diameter_range_um: tuple[float, float], name: str = "report") -> SizeDistribution | None:
    """The particle sizes a diagnosis report's scene measured, as training data's size distribution.

    The report's ``scene`` (`scene_population`): the fitted diameters' quantiles at its
    ``percentiles``, over the particles within the sizes its config allowed. None (the
    config's uniform sizes) where the report has no scene or no sizes in it, fewer than
    ten particles within its sizes, or quantiles outside ``diameter_range_um`` (µm; a report
    made with other sizes than the data's config).

    Raises
    ------
    InputError
        One line naming the report and the field that is malformed.
    """
    scene = report.get("scene") if isinstance(report, dict) else None
    if not isinstance(scene, dict) or scene.get("diameter_um") is None:
        return None
    try:
        counted, percentiles, diameters = scene["in_size_range"], scene["percentiles"], scene["diameter_um"]
    except KeyError as error:
        raise InputError(f"{name}: scene: missing {error}") from None
    if not isinstance(counted, int) or isinstance(counted, bool) or counted < 0:
        raise InputError(f"{name}: scene: in_size_range must be a count >= 0, got {counted!r}")
    if counted < _LEAST_SIZED:
        return None
    try:
        sizes = SizeDistribution(tuple(float(p) / 100.0 for p in percentiles), tuple(float(d) for d in diameters))
    except (InputError, TypeError, ValueError) as error:
        raise InputError(f"{name}: scene: percentiles, diameter_um: {error}") from None
    low, high = diameter_range_um
    if sizes.diameters_um[0] < low or sizes.diameters_um[-1] > high:
        return None
    return sizes


def distractors_from_report(report: dict, *, tile_px: int, diameter_min_um: float, wavelength_um: float | None = None, pixel_um: float | None = None,
                            medium_index: float = 1.0, name: str = "report") -> Distractors:
    """What a diagnosis report's scene measured besides the particles, as training data's unlabelled distractors.

    **Impurities**: the report's ``scene.small_scatterers`` (`scene_population`): their count
    per 256-pixel tile, scaled to ``tile_px``, rounded (none below half a scatterer per tile),
    and their diameters' least and largest, kept below the particles' ``diameter_min_um``.

    **Neighbours**: the frame's particles lie all over it, so a training tile, a crop of such
    a field, has particles outside it whose fringes reach in. Where the scene sized ten
    particles or more within the config's range and ``wavelength_um`` and ``pixel_um`` are given, each group is
    simulated with neighbours in a margin of two Airy radii of the scene's median particle at
    its median depth, ``2 × 1.22 (λ/n) z / d`` (the central diffraction lobe and the first
    ring, which hold most of the light it scatters), in pixels, rounded up, at most half a
    tile. On the built-in real hologram that is 105 pixels (25.3 µm at 3.61 mm, 660 nm, 2.2 µm
    pixels), near the demo's hand-set 96.

    A report without a scene (an older engine's) gives neither.

    Raises
    ------
    InputError
        One line naming the report and the field that is malformed.
    """
    scene = report.get("scene") if isinstance(report, dict) else None
    if scene is None:
        return Distractors()
    margin = _neighbours_margin_px(scene, tile_px=tile_px, wavelength_um=wavelength_um, pixel_um=pixel_um, medium_index=medium_index, name=name)
    try:
        small = scene["small_scatterers"]
        per_tile = float(small["per_256px_tile"]) * (tile_px / 256.0) ** 2
        sizes = small["diameter_um"]
    except (KeyError, TypeError) as error:
        raise InputError(f"{name}: scene: small_scatterers: missing {error}") from None
    if not np.isfinite(per_tile) or per_tile < 0:
        raise InputError(f"{name}: scene: small_scatterers: per_256px_tile must be a number >= 0, got {small['per_256px_tile']!r}")
    count = int(round(per_tile))
    if count == 0 or sizes is None:
        return Distractors(neighbours_margin_px=margin)
    try:
        low, high = (float(value) for value in sizes)
    except (TypeError, ValueError):
        raise InputError(f"{name}: scene: small_scatterers: diameter_um must be [least, largest] in um, got {sizes!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and 0.0 < low <= high):
        raise InputError(f"{name}: scene: small_scatterers: diameter_um must be 0 < least <= largest, got {sizes!r}")
    # what the fits sized at the particles' lower bound is kept just below it
    high = min(high, 0.98 * float(diameter_min_um))
    return Distractors(impurities_per_tile=count, impurity_diameter_min_um=min(low, high), impurity_diameter_max_um=high, neighbours_margin_px=margin)


def _neighbours_margin_px(scene: dict, *, tile_px: int, wavelength_um: float | None, pixel_um: float | None, medium_index: float, name: str) -> int:
    """Two Airy radii of the scene's median particle at its median depth (pixels, at most half a tile); 0 without `_LEAST_SIZED` sized particles or the optics."""
    if wavelength_um is None or pixel_um is None or not all(key in scene for key in ("in_size_range", "percentiles", "diameter_um", "z_um")):
        return 0  # no optics, or a scene that did not record its particles' sizes and depths
    try:
        sized = int(scene["in_size_range"])
        levels = [float(v) for v in scene["percentiles"]]
        diameters, depths = scene["diameter_um"], scene["z_um"]
    except (TypeError, ValueError) as error:
        raise InputError(f"{name}: scene: in_size_range and percentiles must be numbers ({error})") from None
    if sized < _LEAST_SIZED or 50.0 not in levels or diameters is None or depths is None:
        return 0
    try:
        diameter, depth = float(diameters[levels.index(50.0)]), float(depths[levels.index(50.0)])
    except (TypeError, ValueError, IndexError):
        raise InputError(f"{name}: scene: diameter_um and z_um must hold a number at each of percentiles, got {diameters!r} and {depths!r}") from None
    if not (np.isfinite(diameter) and np.isfinite(depth) and diameter > 0):
        raise InputError(f"{name}: scene: the median diameter_um and z_um must be finite, the diameter > 0, got {diameter!r} and {depth!r}")
    reach_um = 2.0 * 1.22 * (wavelength_um / medium_index) * abs(depth) / diameter
    return int(min(np.ceil(reach_um / pixel_um), tile_px // 2))


def distractor_scene(
    field: ParticleField,
    distractors: Distractors,
    *,
    tile_px: int,
    depth_range_um: tuple[float, float],
    diameter_range_um: tuple[float, float],
    layers_um: Sequence[float] | None = None,
    sizes: SizeDistribution | None = None,
    rng: np.random.Generator,
) -> ParticleField:
    """The scene the optics sees: ``field`` plus its distractors, on the window widened by the margin.

    Coordinates are shifted by the margin, so ``field``'s particles keep their place in the
    window ``[m:m + rows, m:m + cols]`` of the returned shape. Neighbours fill the margin at
    ``field``'s particle density (per area), with its diameter range (and ``sizes``, its
    distribution, where given) and depths (on
    ``layers_um`` when given, else uniform over ``depth_range_um``); impurities fill the whole
    widened window at ``impurities_per_tile`` per ``tile_px``² with depths uniform over
    ``depth_range_um``. Nothing is drawn from ``rng`` when ``distractors`` is inactive.
    """
    if not distractors.active:
        return field
    margin = int(distractors.neighbours_margin_px)
    rows, cols = field.shape
    shape = (rows + 2 * margin, cols + 2 * margin)
    extent_x, extent_y = (shape[1] - 1) * field.pixel_um, (shape[0] - 1) * field.pixel_um
    window = (margin * field.pixel_um, (margin + cols - 1) * field.pixel_um, margin * field.pixel_um, (margin + rows - 1) * field.pixel_um)
    area_ratio = shape[0] * shape[1] / (rows * cols)
    neighbours = int(round(len(field) * (area_ratio - 1.0)))
    x, y = [], []
    while len(x) < neighbours:  # uniform over the margin: rejection of the window (at least 1 - 1/area_ratio accepted)
        xi, yi = rng.uniform(0.0, extent_x), rng.uniform(0.0, extent_y)
        if not (window[0] <= xi <= window[1] and window[2] <= yi <= window[3]):
            x.append(xi)
            y.append(yi)
    neighbour_z = rng.choice(np.asarray(layers_um, np.float64), neighbours) if layers_um is not None else rng.uniform(*depth_range_um, neighbours)
    if sizes is None:
        neighbour_d = rng.uniform(*diameter_range_um, neighbours)
    else:
        neighbour_d = sizes.draw(rng, neighbours, diameter_min_um=diameter_range_um[0], diameter_max_um=diameter_range_um[1])
    impurities = int(round(distractors.impurities_per_tile * shape[0] * shape[1] / tile_px**2))
    impurity_x, impurity_y = rng.uniform(0.0, extent_x, impurities), rng.uniform(0.0, extent_y, impurities)
    impurity_z = rng.uniform(*depth_range_um, impurities)
    impurity_d = rng.uniform(distractors.impurity_diameter_min_um, distractors.impurity_diameter_max_um, impurities)
    shift = margin * field.pixel_um
    return ParticleField(
        np.concatenate([field.x_um + shift, x, impurity_x]),
        np.concatenate([field.y_um + shift, y, impurity_y]),
        np.concatenate([field.z_um, neighbour_z, impurity_z]),
        np.concatenate([field.diameter_um, neighbour_d, impurity_d]),
        shape,
        field.pixel_um,
    )


def count_for_ppp(ppp: float, shape: tuple[int, int], *, pixel_um: float, voxel_um: float) -> int:
    """Particle count for a concentration in particles per lateral voxel.

    The seed paper (Sec. 3.1) counts particles per voxel of ``voxel_um`` (26.82 µm there):
    540 particles over 63 x 63 voxels is 0.136 ppp.
    """
    if ppp < 0:
        raise InputError(f"ppp: expected a non-negative concentration, got {ppp}")
    voxels = (shape[0] * pixel_um / voxel_um) * (shape[1] * pixel_um / voxel_um)
    return int(round(ppp * voxels))


def random_particle_field(
    shape: tuple[int, int],
    *,
    count: int,
    diameter_min_um: float,
    diameter_max_um: float,
    layers_um: Sequence[float],
    pixel_um: float,
    seed: int | np.random.Generator | None = None,
    overlap: bool = True,
    continuous: bool = False,
    sizes: SizeDistribution | None = None,
) -> ParticleField:
    """Draw a random particle field.

    Diameters are uniform in ``[diameter_min_um, diameter_max_um]`` or, with ``sizes``, drawn
    from that distribution within it (`SizeDistribution.draw`), depths drawn uniformly
    from ``layers_um`` (the seed's HCS layers) or, with ``continuous=True``, uniformly over
    ``[min(layers_um), max(layers_um)]`` (every particle its own depth, as in a real volume),
    centres uniform over the window. With ``overlap=False`` no two particles overlap in
    projection along z (rejection sampling; raises when the window is too full).
    """
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 0 <= count <= MAX_PARTICLES:
        raise InputError(f"count: expected an integer in [0, {MAX_PARTICLES}], got {count!r}")
    low = check_number(diameter_min_um, key="diameter_min_um", low=0.0, above=True)
    if check_number(diameter_max_um, key="diameter_max_um", low=0.0, above=True) < low:
        raise InputError(f"diameter_max_um: expected a diameter of at least diameter_min_um={low:g}, got {diameter_max_um:g}")
    check_number(pixel_um, key="pixel_um", low=0.0, high=1e4, above=True)
    try:
        layers = np.asarray(layers_um, dtype=np.float64).ravel()
        rows, cols = (int(n) for n in shape)
    except (TypeError, ValueError):
        raise InputError(f"layers_um, shape: expected depths (µm) and (rows, cols), got {layers_um!r} and {shape!r}") from None
    if layers.size == 0 or not np.all(np.isfinite(layers)):
        raise InputError("layers_um: expected at least one depth, all finite")
    if not 1 <= rows <= 10**5 or not 1 <= cols <= 10**5:
        raise InputError(f"shape: expected 1 to 100000 pixels per side, got {shape!r}")
    rng = np.random.default_rng(seed)
    if sizes is None:
        diameters = rng.uniform(diameter_min_um, diameter_max_um, count)
    else:
        diameters = sizes.draw(rng, count, diameter_min_um=diameter_min_um, diameter_max_um=diameter_max_um)
    depths = rng.uniform(layers.min(), layers.max(), count) if continuous else rng.choice(layers, size=count)
    x = np.empty(count)
    y = np.empty(count)
    for i in range(count):
        for _attempt in range(10_000):
            xi, yi = rng.uniform(0.0, (cols - 1) * pixel_um), rng.uniform(0.0, (rows - 1) * pixel_um)
            if overlap or i == 0 or np.all(np.hypot(x[:i] - xi, y[:i] - yi) >= (diameters[:i] + diameters[i]) / 2):
                break
        else:
            raise InputError(f"count: {count} particles do not fit without overlap in a {rows}x{cols} window")
        x[i], y[i] = xi, yi
    return ParticleField(x, y, depths, diameters, (int(rows), int(cols)), float(pixel_um))


def disc_coverage(shape: tuple[int, int], x_um, y_um, diameter_um, *, pixel_um: float) -> np.ndarray:
    """Fraction of each pixel covered by discs (anti-aliased, 1/64 steps), float32 in [0, 1].

    Pixel ``(r, c)`` spans ``[c - 0.5, c + 0.5) x [r - 0.5, r + 0.5)`` pixels; coverage is the
    fraction of its 8x8 sub-samples that lie inside any disc.
    """
    coverage = np.zeros(shape, dtype=np.float32)
    offsets = (np.arange(_SUPERSAMPLE) + 0.5) / _SUPERSAMPLE - 0.5
    for xc, yc, d in zip(np.atleast_1d(x_um), np.atleast_1d(y_um), np.atleast_1d(diameter_um), strict=True):
        col, row, radius = xc / pixel_um, yc / pixel_um, d / (2.0 * pixel_um)
        r0, r1 = max(int(np.floor(row - radius - 1)), 0), min(int(np.ceil(row + radius + 1)), shape[0] - 1)
        c0, c1 = max(int(np.floor(col - radius - 1)), 0), min(int(np.ceil(col + radius + 1)), shape[1] - 1)
        if r0 > r1 or c0 > c1:
            continue
        sub_r = (np.arange(r0, r1 + 1)[:, None] + offsets[None, :]).ravel()
        sub_c = (np.arange(c0, c1 + 1)[:, None] + offsets[None, :]).ravel()
        inside = ((sub_r[:, None] - row) ** 2 + (sub_c[None, :] - col) ** 2) <= radius**2
        fraction = inside.reshape(r1 - r0 + 1, _SUPERSAMPLE, c1 - c0 + 1, _SUPERSAMPLE).mean(axis=(1, 3))
        box = coverage[r0 : r1 + 1, c0 : c1 + 1]
        # Discs of one layer that overlap still block light only once.
        np.maximum(box, np.minimum(box + fraction.astype(np.float32), 1.0), out=box)
    return coverage


def layer_images(field: ParticleField) -> tuple[np.ndarray, np.ndarray]:
    """Coverage image of each particle layer: ``(depths_um farthest first, (n_layers, rows, cols) float32)``."""
    depths = field.layers_um()
    images = np.stack([
        disc_coverage(field.shape, field.x_um[field.z_um == z], field.y_um[field.z_um == z], field.diameter_um[field.z_um == z], pixel_um=field.pixel_um)
        for z in depths
    ]) if depths.size else np.zeros((0,) + field.shape, np.float32)
    return depths, images


def simulate_hologram(field: ParticleField, *, wavelength_um: float, medium_index: float = 1.0, shadowing: bool = False) -> np.ndarray:
    """Intensity hologram of opaque particles under a unit plane wave, float32, unobstructed light = 1.

    Parameters
    ----------
    field : ParticleField
        Particles; their depths are distances to the sensor.
    wavelength_um, medium_index
        Vacuum wavelength (µm) and medium index.
    shadowing : bool
        False (the seed's model): each layer's scattered field ``-coverage`` is propagated to
        the sensor alone and the fields are superposed. True: the wave is propagated layer by
        layer from the farthest, each layer multiplying it by its transmission ``1 - coverage``,
        so nearer particles shadow the light scattered by farther ones.
    """
    if not isinstance(field, ParticleField):
        raise InputError(f"field: expected a ParticleField (random_particle_field, or one built from a particle table), got {type(field).__name__}")
    optics = {"wavelength_um": wavelength_um, "pixel_um": field.pixel_um, "medium_index": medium_index}
    padded_shape(field.shape, z_max_um=0.0, **optics)  # refuses optics no propagation can use, before the layers are drawn
    depths, images = layer_images(field)
    if depths.size == 0:
        return np.ones(field.shape, dtype=np.float32)
    if not shadowing:
        scattered = superpose([-image for image in images], depths, **optics)
        return np.abs(1.0 + scattered).astype(np.float32) ** 2
    grid, spread_limit_um = propagation_grid(field.shape, z_max_um=float(depths[0]), **optics)
    rows, cols = field.shape
    wave = np.ones(grid, dtype=np.complex64)
    transmission = np.ones(grid, dtype=np.float32)
    for depth, next_depth, image in zip(depths, np.append(depths[1:], 0.0), images, strict=True):
        transmission[:rows, :cols] = 1.0 - image
        wave *= transmission
        kernel = transfer_function(grid, float(depth - next_depth), spread_limit_um=spread_limit_um, **optics)
        wave = scipy.fft.ifft2(scipy.fft.fft2(wave, workers=process_threads()) * kernel, workers=process_threads())
    return (np.abs(wave[:rows, :cols]) ** 2).astype(np.float32)


def label_planes(field: ParticleField, planes_um: Sequence[float]) -> np.ndarray:
    """Ground-truth label planes: a 3x3 square of value 4 x diameter (µm) per particle.

    Each particle is drawn on the plane of ``planes_um`` nearest its depth, centred on the
    pixel nearest its centre; squares are clipped at the window edge. Where squares overlap
    the larger diameter wins.

    Returns
    -------
    (len(planes_um), rows, cols) float32
    """
    planes = np.asarray(planes_um, dtype=np.float64)
    labels = np.zeros((planes.size,) + field.shape, dtype=np.float32)
    rows, cols = field.shape
    for x, y, z, d in zip(field.x_um, field.y_um, field.z_um, field.diameter_um, strict=True):
        plane = int(np.argmin(np.abs(planes - z)))
        row, col = int(round(y / field.pixel_um)), int(round(x / field.pixel_um))
        r0, r1 = max(row - _LABEL_HALF, 0), min(row + _LABEL_HALF + 1, rows)
        c0, c1 = max(col - _LABEL_HALF, 0), min(col + _LABEL_HALF + 1, cols)
        if r0 < r1 and c0 < c1:
            box = labels[plane, r0:r1, c0:c1]
            np.maximum(box, np.float32(LABEL_SCALE * d), out=box)
    return labels
