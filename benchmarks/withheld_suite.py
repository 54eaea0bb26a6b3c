"""The frozen withheld-effect suite: pseudo-experiments the diagnosis is judged on, never tuned on.

Every hologram is made by an independent forward model — Lorenz–Mie theory (pylorenzmie,
through `pseudoreal.mie_intensity`) for the particles, and the effects written here with
their own parameterisation, none of it from `napari_lbs._core.physics._effects` — as a camera would
record it (8-bit counts, Gaussian read noise; photon noise only where it is the withheld effect). Absorbing spheres (n = 1.59 + 0.5i, opaque through 20 µm) are the
particles of every case except the transparent-sphere cases (n = 1.59 and 1.38 in water).

The design (`FROZEN`) and its seed were written and committed before the suite's first run.
`DEVELOPMENT` has the same kinds of case at other strengths and seeds: it is what any level
of the diagnosis is chosen on. Multiple scattering is absent from both: no independent
forward model of shadowing between Lorenz–Mie spheres is at hand (pylorenzmie superposes
single-scattered fields).

Run ``python benchmarks/withheld_suite.py make frozen DIR`` to write the holograms and
``design.json`` (a few minutes on 2 cores); ``bench_diagnosis.py suite DIR`` scores them.
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pseudoreal  # noqa: E402

ABSORBING = 1.59 + 0.5j
WATER = pseudoreal.N_MEDIUM


@dataclass(frozen=True)
class Case:
    """One pseudo-experiment: ``effects`` maps a catalog id (the expected answer) to this suite's own parameters."""

    name: str
    size: int
    effects: dict = field(default_factory=dict)
    spheres_per_512: int = 30
    level: float = 150.0  # counts of unobstructed light
    read_noise: float = 1.5  # counts (rms)

    @property
    def expected(self) -> list[str]:
        return sorted(self.effects)


FROZEN_SEED = 7331
FROZEN = (
    # controls: absorbing spheres, nothing withheld (densities, levels and read noise vary)
    Case("control-a", 512), Case("control-b", 512, spheres_per_512=20, level=170, read_noise=2.5), Case("control-c", 512, spheres_per_512=40, level=130, read_noise=1.0),
    Case("control-d", 512, level=180, read_noise=3.0), Case("control-e", 512, spheres_per_512=25, level=140, read_noise=2.0),
    Case("control-f", 1024), Case("control-g", 1024, spheres_per_512=20, level=165, read_noise=2.0), Case("control-h", 1024, spheres_per_512=35, level=135, read_noise=1.2),
    Case("control-i", 1024, level=175, read_noise=2.5), Case("control-j", 1024, spheres_per_512=28, level=150, read_noise=1.8),
    # one effect each, weak and strong
    Case("vignetting-weak", 512, {"illumination": {"falloff": 0.25, "centre": (0.35, 0.6)}}),
    Case("vignetting-strong", 1024, {"illumination": {"falloff": 0.5, "centre": (0.7, 0.3)}}),
    Case("photons-weak", 512, {"shot_noise": {"photons": 150.0}}),
    Case("photons-strong", 1024, {"shot_noise": {"photons": 40.0}}),
    Case("bits-weak", 512, {"quantization": {"step_counts": 4}}),
    Case("bits-strong", 1024, {"quantization": {"step_counts": 12}}),
    Case("crosstalk-weak", 512, {"sensor_blur": {"kernel": "binomial3"}}),
    Case("crosstalk-strong", 1024, {"sensor_blur": {"kernel": "binomial5"}}),
    Case("source-disc", 512, {"coherence": {"source_mrad": 2.0}}),
    Case("led-bandwidth", 1024, {"coherence": {"bandwidth_nm": 30.0}}),
    Case("transparent-polystyrene", 512, {"particle_phase": {"index": 1.59}}),
    Case("transparent-low-index", 1024, {"particle_phase": {"index": 1.38}}),
    Case("etalon", 512, {"parasitic_fringes": {"etalon": 0.05, "period_px": 9.0, "angle_rad": 1.1}}),
    Case("dust-16mm", 1024, {"parasitic_fringes": {"dust_mm": 16.0, "grains_per_mpx": 40.0, "grain_um": (20.0, 80.0)}}),
    Case("point-source-60mm", 512, {"spherical_wave": {"source_mm": 60.0}}),
    Case("point-source-20mm", 1024, {"spherical_wave": {"source_mm": 20.0}}),
    # two effects
    Case("vignetting+photons", 512, {"illumination": {"falloff": 0.4, "centre": (0.3, 0.35)}, "shot_noise": {"photons": 60.0}}),
    Case("crosstalk+transparent", 512, {"sensor_blur": {"kernel": "binomial5"}, "particle_phase": {"index": 1.59}}),
    Case("etalon+bits", 1024, {"parasitic_fringes": {"etalon": 0.06, "period_px": 13.0, "angle_rad": 0.4}, "quantization": {"step_counts": 8}}),
    Case("led+vignetting", 512, {"coherence": {"bandwidth_nm": 40.0}, "illumination": {"falloff": 0.45, "centre": (0.6, 0.65)}}),
)

DEVELOPMENT_SEED = 1234
DEVELOPMENT = (
    Case("control-1", 512), Case("control-2", 512, spheres_per_512=35, level=160, read_noise=2.0), Case("control-3", 512, spheres_per_512=22, level=140, read_noise=1.2),
    Case("control-4", 1024, level=155, read_noise=2.2),
    Case("vignetting", 512, {"illumination": {"falloff": 0.35, "centre": (0.55, 0.4)}}),
    Case("photons", 512, {"shot_noise": {"photons": 80.0}}),
    Case("bits", 512, {"quantization": {"step_counts": 8}}),
    Case("crosstalk", 512, {"sensor_blur": {"kernel": "binomial3"}}),
    Case("source-disc", 512, {"coherence": {"source_mrad": 2.5}}),
    Case("led-bandwidth", 512, {"coherence": {"bandwidth_nm": 20.0}}),
    Case("transparent", 512, {"particle_phase": {"index": 1.45}}),
    Case("etalon", 512, {"parasitic_fringes": {"etalon": 0.04, "period_px": 16.0, "angle_rad": 2.0}}),
    Case("dust-10mm", 512, {"parasitic_fringes": {"dust_mm": 10.0, "grains_per_mpx": 60.0, "grain_um": (10.0, 60.0)}}),
    Case("point-source-30mm", 512, {"spherical_wave": {"source_mm": 30.0}}),
    Case("photons+crosstalk", 512, {"shot_noise": {"photons": 60.0}, "sensor_blur": {"kernel": "binomial5"}}),
)
SUITES = {"frozen": (FROZEN, FROZEN_SEED), "development": (DEVELOPMENT, DEVELOPMENT_SEED)}


def _fresnel_discs(shape: tuple[int, int], rng: np.random.Generator, *, distance_mm: float, grains_per_mpx: float, grain_um: tuple[float, float]) -> np.ndarray:
    """Intensity behind opaque dust discs ``distance_mm`` before the sensor: Fresnel propagation (paraxial transfer function) written here."""
    rows, cols = shape
    pad = (2 * rows, 2 * cols)  # an evenly dusty window sends rings in from outside the field too
    count = rng.poisson(grains_per_mpx * pad[0] * pad[1] / 1e6)
    yy, xx = np.mgrid[0 : pad[0], 0 : pad[1]]
    opaque = np.zeros(pad, bool)
    for _ in range(count):
        r = rng.uniform(*grain_um) / 2 / pseudoreal.PIXEL_UM
        cy, cx = rng.uniform(0, pad[0]), rng.uniform(0, pad[1])
        box = (slice(max(int(cy - r - 1), 0), int(cy + r + 2)), slice(max(int(cx - r - 1), 0), int(cx + r + 2)))
        opaque[box] |= (yy[box] - cy) ** 2 + (xx[box] - cx) ** 2 <= r**2
    fy, fx = np.fft.fftfreq(pad[0], pseudoreal.PIXEL_UM), np.fft.fftfreq(pad[1], pseudoreal.PIXEL_UM)
    wavelength = pseudoreal.WAVELENGTH_UM  # the window is in air
    kernel = np.exp(-1j * np.pi * wavelength * distance_mm * 1e3 * (fy[:, None] ** 2 + fx[None, :] ** 2))
    field = 1.0 - np.fft.ifft2(np.fft.fft2(opaque.astype(float)) * kernel)
    return (np.abs(field) ** 2)[rows // 2 : rows // 2 + rows, cols // 2 : cols // 2 + cols]


def _scene(case: Case, rng: np.random.Generator) -> np.ndarray:
    """Pixel-integrated Lorenz–Mie intensity of the case's spheres with its optical effects (unobstructed light = 1)."""
    size = case.size
    count = int(round(case.spheres_per_512 * (size / 512) ** 2))
    extent = (size - 1) * pseudoreal.PIXEL_UM
    x, y = rng.uniform(0, extent, count), rng.uniform(0, extent, count)
    z, d = rng.uniform(1900.0, 4700.0, count), rng.uniform(20.0, 30.0, count)
    index = complex(case.effects["particle_phase"]["index"]) if "particle_phase" in case.effects else ABSORBING
    shape = (size, size)
    spherical = case.effects.get("spherical_wave")
    if spherical:
        source_um, centre = spherical["source_mm"] * 1e3, extent / 2
        magnification = source_um / (source_um - z * WATER)  # z is air-equivalent; the source distance a physical one in water
        x, y, z, d = centre + magnification * (x - centre), centre + magnification * (y - centre), magnification * z, magnification * d
    coherence = case.effects.get("coherence", {})
    if "source_mrad" in coherence:
        # a uniform disc source of that angular diameter, sampled at its centre and on two rings (6 and 12 points)
        radius = coherence["source_mrad"] / 2 * 1e-3
        angles = [(0.0, 0.0)] + [(f * radius * np.cos(a), f * radius * np.sin(a)) for f, n in ((0.45, 6), (0.85, 12)) for a in np.arange(n) * 2 * np.pi / n]
        return np.mean([pseudoreal.mie_intensity(shape, x + z * tx, y + z * ty, z, d, index) for tx, ty in angles], axis=0)
    if "bandwidth_nm" in coherence:
        # a flat spectrum of that full width: incoherent sum over 7 wavelengths
        original = pseudoreal.WAVELENGTH_UM
        try:
            images = []
            for offset in np.linspace(-0.5, 0.5, 7) * coherence["bandwidth_nm"] * 1e-3:
                pseudoreal.WAVELENGTH_UM = original + offset
                images.append(pseudoreal.mie_intensity(shape, x, y, z, d, index))
        finally:
            pseudoreal.WAVELENGTH_UM = original
        return np.mean(images, axis=0)
    return pseudoreal.mie_intensity(shape, x, y, z, d, index)


def _camera(intensity: np.ndarray, case: Case, rng: np.random.Generator) -> np.ndarray:
    """The suite's camera: the case's sensor-side effects, photon and read noise, 8-bit counts."""
    rows, cols = intensity.shape
    image = intensity.astype(np.float64)
    yy, xx = np.mgrid[0:rows, 0:cols] / max(rows, cols)
    illumination = case.effects.get("illumination")
    if illumination:  # cos⁴ vignetting about an off-centre axis: ``falloff`` lost at the field's farthest corner
        cx, cy = illumination["centre"]
        distance = np.hypot(xx - cx, yy - cy)
        focal = distance.max() / np.sqrt((1 - illumination["falloff"]) ** -0.5 - 1)
        image = image / (1 + (distance / focal) ** 2) ** 2
    fringes = case.effects.get("parasitic_fringes", {})
    if "etalon" in fringes:
        phase = 2 * np.pi * (xx * np.cos(fringes["angle_rad"]) + yy * np.sin(fringes["angle_rad"])) * max(rows, cols) / fringes["period_px"]
        image = image * (1 + fringes["etalon"] * np.cos(phase))
    if "dust_mm" in fringes:
        image = image * _fresnel_discs((rows, cols), rng, distance_mm=fringes["dust_mm"], grains_per_mpx=fringes["grains_per_mpx"], grain_um=fringes["grain_um"])
    blur = case.effects.get("sensor_blur")
    if blur:  # charge sharing: a separable binomial kernel
        taps = {"binomial3": [1, 2, 1], "binomial5": [1, 4, 6, 4, 1]}[blur["kernel"]]
        kernel = np.asarray(taps, float) / sum(taps)
        image = ndimage.convolve1d(ndimage.convolve1d(image, kernel, axis=0, mode="reflect"), kernel, axis=1, mode="reflect")
    if "shot_noise" in case.effects:  # photo-electrons of unobstructed light
        photons = case.effects["shot_noise"]["photons"]
        image = rng.poisson(np.clip(image, 0, None) * photons) / photons
    counts = image * case.level + rng.normal(0.0, case.read_noise, image.shape)
    step = case.effects.get("quantization", {}).get("step_counts", 1)
    return (np.clip(np.round(counts / step), 0, 255 // step) * step).astype(np.uint8)


def make(suite: str, folder: str, only: list[str] | None = None) -> None:
    """Write the suite's holograms (``NAME.tif``, 8-bit) and ``design.json`` into ``folder``."""
    import tifffile

    cases, seed = SUITES[suite]
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    design = []
    for index, case in enumerate(cases):
        design.append({**asdict(case), "expected": case.expected, "file": f"{case.name}.tif"})
        if only and case.name not in only:
            continue
        rng = np.random.default_rng([index, seed])
        tifffile.imwrite(out / f"{case.name}.tif", _camera(_scene(case, rng), case, rng))
        print(f"{case.name}: {case.size}² {case.expected or 'control'}", flush=True)
    (out / "design.json").write_text(json.dumps({"suite": suite, "seed": seed, "cases": design}, indent=1))


if __name__ == "__main__":
    if len(sys.argv) < 4 or sys.argv[1] != "make" or sys.argv[2] not in SUITES:
        raise SystemExit("usage: withheld_suite.py make frozen|development DIR [CASE ...]")
    make(sys.argv[2], sys.argv[3], sys.argv[4:] or None)
