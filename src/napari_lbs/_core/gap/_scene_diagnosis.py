"""The gap diagnosed on the experiment's own particles: nested physical models, held-out likelihood, what is left.

1. **The scene** is every particle found (up to ``scene_particles``), fitted with its
   index contrast and absorption free, the residual searched again ``looks`` times for the
   particles the first search missed (`_scene`), and rendered to the Nyquist disc
   (``reach_cycles_per_px``: the aliased rings beyond it are the camera's to pass or not).
2. **The frame's effects** (`select_effects`): the catalog's camera around the scene's
   hologram, each effect a nested model fitted on one colour of a checkerboard of tiles and
   judged on the other by a Whittle likelihood, tile by tile; forward selection by a sign
   test over the held-out tiles' gains; then the shot-noise test on the final model.
   Coherence (a source's size) blurs each depth group of the scene by its own depth. Quantization and saturation are read from the levels the
   frame's counts use (`levels_test`).
3. **Particle optics** (``particle_phase``, `_optics`): the strongest ``particles`` of the
   scene rendered as opaque spheres and as transparent ones at each index contrast of
   ``index_grid``, to 1 cycle per pixel and through the camera's blur the effects found
   (`particle_models`), and read two ways: the power spectrum of their fine rings against
   each tile's, judged held out tile by tile (`optics_power_test`: a transparent sphere
   throws its refracted light into fine rings far from its centre, at frequencies that
   follow its index contrast; an opaque one does not), and the light on each sphere's axis
   back-propagated through its depth (`through_focus_test`: a ball lens's focus keeps it
   bright, an opaque sphere's shadow dark). Their sign tests' z are combined.
4. **What is left**, tile by tile: the structured power of the held-out residual (its power
   less its white floor, the median power above ``0.35`` cycles per pixel, where neither
   particles nor structure reach after the camera's blur) over the structured power of the
   frame itself, the *unexplained share* of the frame's structure. Its median over the tiles
   is the gap: a pair fitted as one particle or a particle cut by the frame's edge spoils a
   few tiles, an effect the model lacks spoils them all. The catalog explains the frame where
   that median is at most ``structure_level``, the residual's column and row means hold no
   fixed pattern (`line_pattern`: what a camera's column amplifiers and row read-out leave,
   the EMVA 1288 standard's check of non-uniformity) and it holds no blur that differs by
   direction (`directional_blur_test`: a sample moving during the exposure). Where it holds
   structure, what the model leaves is searched for dust on a window on either side of the
   volume, and the scene's particles fitted outside it are looked at too (`dust_layer`:
   grains fitted in one plane); a layer on enough tiles is named as the catalog's
   ``parasitic_fringes``, the frame is divided by the searched grains' hologram, its
   particles are found and fitted again and every effect is judged again on the light
   without them, and the scene's grains leave its table.
5. **The scene's numbers** (`scene_population`): the fitted particles' count, density, sizes,
   depths and index contrasts, and the small scatterers: the scene's fits below the config's
   sizes and what a search at smaller sizes finds in the residual (`_small_scatterers`).
"""

from __future__ import annotations

import json
import time
from contextlib import nullcontext
from dataclasses import dataclass, field, replace

import numpy as np

from threadpoolctl import threadpool_limits

from napari_lbs._core.foundation import ExperimentConfig, InputError, ProgressCallback, Steps, StopCallback, WorkerPool, as_hologram, begin_phase, json_safe
from napari_lbs._core.gap._blur_depth import BLUR_EFFECTS, attribute_blur, spectrum_width_test
from napari_lbs._core.gap._confidence import Decision, combined_z, verdict_probability
from napari_lbs._core.gap._detect import find_particles
from napari_lbs._core.gap._directional import directional_blur_test
from napari_lbs._core.gap._dust_layer import LAYER_TILES, dust_layer, dust_record, in_window, outside_volume
from napari_lbs._core.gap._heldout import TileSplit, tile_spectra
from napari_lbs._core.gap._levels import levels_test
from napari_lbs._core.gap._nested import DECIDED_Z, MEAN_EFFECTS, far_ring_power, select_effects, shot_noise_test, whiteness_draws
from napari_lbs._core.gap._scene_image import Scene
from napari_lbs._core.gap._unexplained import depth_groups, line_pattern, share_by_depth, unexplained_share
from napari_lbs._core.gap._optics_power import optics_power_test
from napari_lbs._core.gap._particle_models import optics_call, particle_models
from napari_lbs._core.gap._population import scene_population
from napari_lbs._core.gap._through_focus import through_focus_test
from napari_lbs._core.refine import RefineSettings, particle_hologram, refine_particles

__all__ = ["SceneDiagnosisSettings", "SceneDiagnosis", "diagnose_scene"]

_SMALL_FRACTION = 0.2  # small scatterers are looked for from this fraction of the sample's least diameter up to it
_WINDOW_FLOOR = 0.2  # the window's hologram divides the frame down to this much light (a grain's deepest shadow holds little but noise)
_NOT_TESTED = {
    "spherical_wave": "on one frame a point source's magnification is a change of each particle's depth and size",
    "multiple_scattering": "not modelled by this engine yet",
}


@dataclass(frozen=True)
class SceneDiagnosisSettings:
    """How `diagnose_scene` fits and decides.

    Attributes
    ----------
    particles : int
        The most of the scene's particles (the strongest found first) rendered under each
        particle model for the optics test.
    scene_particles : int
        The most particles found and fitted (index contrast and absorption free) for the frame's scene:
        every particle left out stays in the residual as structure.
    looks : int
        How many times the residual the fitted scene leaves is searched for particles the
        first search missed (each find fitted with the others taken out of the data).
    reach_cycles_per_px : float
        Fringe frequency up to which the scene's particles are rendered (`particle_hologram`).
        ``1`` renders the aliased rings a pixel records, which leaves far less structure in
        the residual, but how strongly a camera passes fringes above Nyquist depends on its
        pixels (fill factor, microlenses): on pixel-integrated Lorenz–Mie frames with nothing
        withheld, rendering them named blur and coherence where ``0.5`` (the Nyquist disc,
        what the fits model) named nothing.
    index_grid : tuple of float
        Index contrasts at which transparent spheres are rendered for the optics test.
    level_z : float
        The sign test's z an effect's held-out gain needs over the ``grid²`` tiles to be
        selected (tiles gaining less tiles losing, over the root of their number: 3 is 14 of
        16 tiles; at most ``grid``), and the particle optics' over the tested particles.
    structure_level : float
        Largest unexplained share of the frame's structure (median over the tiles) for which
        the catalog explains the frame.
    line_level : float
        Largest variance of the high-passed residual's column (or row) means, in units of what
        white noise gives them, for which the frame holds no fixed line pattern.
    grid : int
        Tiles per side of the held-out checkerboard.
    refine : RefineSettings
        How the particles are fitted; its ``workers`` processes, started once, fit every
        table of the diagnosis (the scene's, its looks', the small scatterers'). More than one
        spawns processes: a script then starts its work under ``if __name__ == "__main__":``.
    """

    particles: int = 64
    scene_particles: int = 256
    looks: int = 2
    reach_cycles_per_px: float = 0.5
    index_grid: tuple[float, ...] = (0.12, 0.26, 0.40)
    level_z: float = 3.0
    structure_level: float = 0.07
    line_level: float = 4.0
    grid: int = 4
    refine: RefineSettings = field(default_factory=lambda: RefineSettings(min_gain=0.0))

    def __post_init__(self) -> None:
        for name in ("particles", "scene_particles"):
            value = getattr(self, name)
            if not (isinstance(value, int) and 2 <= value <= 2000):
                raise InputError(f"scene diagnosis: {name} must be an integer 2-2000, got {value!r}")
        if not self.index_grid or not all(0.0 < float(v) <= 1.0 for v in self.index_grid):
            raise InputError(f"scene diagnosis: index_grid must hold index contrasts in (0, 1], got {self.index_grid!r}")
        if not (isinstance(self.reach_cycles_per_px, int | float) and 0.0 < self.reach_cycles_per_px <= 1.0):
            raise InputError(f"scene diagnosis: reach_cycles_per_px must be in (0, 1], got {self.reach_cycles_per_px!r}")
        if not (isinstance(self.looks, int) and 0 <= self.looks <= 10):
            raise InputError(f"scene diagnosis: looks must be an integer 0-10, got {self.looks!r}")
        if not (isinstance(self.grid, int) and 2 <= self.grid <= 16):
            raise InputError(f"scene diagnosis: grid must be an integer 2-16, got {self.grid!r}")
        for name in ("level_z", "structure_level", "line_level"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and np.isfinite(value) and value >= 0):
                raise InputError(f"scene diagnosis: {name} must be a finite number >= 0, got {value!r}")
        if self.level_z > self.grid:
            raise InputError(f"scene diagnosis: level_z must be at most grid={self.grid} (the sign test over grid² tiles reaches no more), got {self.level_z!r}")


@dataclass(frozen=True)
class SceneDiagnosis:
    """The report (docs/formats.md ``report.json``), the per-tile map of the structured share, and the fitted particles."""

    report: dict
    tile_map: np.ndarray = field(repr=False)
    particles: object = field(repr=False)
    seconds: float = 0.0

    def to_json(self) -> str:
        """The report as strict JSON text (NaN and infinities as null)."""
        return json.dumps(json_safe(self.report), indent=1, allow_nan=False)


def _optics(data: np.ndarray, table, selection, config: ExperimentConfig, split: TileSplit, settings: SceneDiagnosisSettings, progress, should_stop) -> dict:
    """The particles' optics on the scene's strongest particles, through the camera's blur the effects found: two views, one decision.

    The fine rings' power spectrum (`optics_power_test`, a sign test over the tiles) and the
    light on each sphere's axis through focus (`through_focus_test`, a sign test over the
    spheres), from the same renders (`particle_models`); their z summed and divided by √2
    (Stouffer's combination of independent tests) decides at ``level_z``. Where no sphere
    votes through focus, the spectrum decides alone. The index contrast is the spectrum's.
    """
    final = selection.fits["+".join(selection.chosen) or "baseline"].params
    blur_px = 0.0
    if "sensor_blur" in selection.chosen:
        blur_px = float(np.mean([fit["sensor_blur.sigma_px"] for fit in final]))
    if "coherence" in selection.chosen and len(table):
        # a source's blur at the particles' median depth, added in quadrature to the sensor's
        theta = float(np.mean([fit.get("coherence.theta_mrad", 0.0) for fit in final]))  # a spectrum's width leaves no Gaussian blur
        blur_px = float(np.hypot(blur_px, theta * 1e-3 * float(np.median(table["z_um"])) / config.optics.pixel_um))
    tested = table.iloc[: settings.particles]
    record = {"particles": int(len(tested)), "model": "undecided", "z": 0.0, "index_contrast": None, "camera_blur_px": blur_px}
    if len(tested):
        begin_phase(progress, f"particle optics: {len(tested)} particles rendered as opaque and as transparent spheres, read by their spectrum and through focus")
        steps = Steps(2 * len(tested), progress=progress, should_stop=should_stop, heartbeat_s=0.5)
        models = particle_models(data.shape, tested, config, index_grid=settings.index_grid, blur_px=blur_px, settings=settings.refine, steps=steps)
        spectrum = optics_power_test(data, models, split, blur_px=blur_px, level_z=settings.level_z)
        focus = through_focus_test(data, models, tested, config, split, level_z=settings.level_z, steps=steps)
        views = ((focus.pop("sphere_differences"), focus.pop("sphere_tiles")),) if focus["spheres"] else ()
        z = combined_z(spectrum["tile_differences"], views)  # the draws' test (`_decisions`) at even weights
        record.update({"model": optics_call(z, level_z=settings.level_z), "z": z,
                       "index_contrast": spectrum["index_contrast"], "power_spectrum": spectrum, "through_focus": focus,
                       "votes": (spectrum.pop("tile_differences"), views), "rendered": models[f"{spectrum['index_contrast']:g}"]})
    diameters = tested["diameter_um"].to_numpy(np.float64)
    record.update({"diameter_median_um": float(np.median(diameters)) if diameters.size else None,
                   "diameter_quartiles_um": np.percentile(diameters, [25, 75]).tolist() if diameters.size else None})
    return record


def _decisions(selection, shot: dict, optics_votes, phase_selected: bool, blur_profile: dict | None, *, level_z: float,
               spectrum: dict | None = None, dust: dict | None = None) -> list[Decision]:
    """The verdict's sign tests over the tiles (`verdict_probability`): each effect kept, each left out, each rival beaten, photon noise, the optics.

    Each selected effect of the mean against the model without it; each other one against
    the final model with it added, where that model was fitted; each selected effect against
    each rival that gained alone, put in its place, at the rivals' level (`DECIDED_Z`), where
    that model was fitted; photon noise, taken on a draw where its slope reads white on that
    draw's tiles and its sign test passes; the particles' optics (transparent where the verdict
    names them, else opaque, the simulator's: an undecided optics test is a doubt). A blur whose origin was read from the
    depth groups (`attribute_blur`) is counted as any named effect: the line through the
    depth groups' blurs chose it, and the tiles must still gain from it; the other blur is
    then not its rival on the tiles (the groups, not the tiles, told them apart). Where a
    blur was named, the spectrum's width against it (`spectrum_width_test`); where a dusty
    window was looked for, its grains' tiles (named from `LAYER_TILES`).
    """
    fits = selection.fits
    chosen = selection.chosen
    final = fits["+".join(chosen) or "baseline"]
    decisions = []
    for effect in MEAN_EFFECTS:
        if effect in chosen:
            without = "+".join(e for e in chosen if e != effect) or "baseline"
            if without in fits:
                decisions.append(Decision(f"{effect} kept", final.loglik - fits[without].loglik, 1))
        else:
            key = "+".join(sorted((*chosen, effect)))
            if key in fits:
                decisions.append(Decision(f"{effect} not added", fits[key].loglik - final.loglik, 0))
    alone = selection.steps[0]["gains"] if selection.steps else {}
    by_depth = bool(blur_profile and blur_profile.get("origin"))
    undecided = {(u["selected"], u["rival"]) for u in selection.undecided}
    for effect in chosen:
        for rival, gain in alone.items():
            if rival in chosen or rival not in MEAN_EFFECTS or gain.get("z") is None or gain["z"] < level_z or (effect, rival) in undecided:
                continue
            if by_depth and {effect, rival} <= set(BLUR_EFFECTS):
                continue
            key = "+".join(sorted((*(e for e in chosen if e != effect), rival)))
            if key in fits:
                decisions.append(Decision(f"{effect} rather than {rival}", final.loglik - fits[key].loglik, 1, needs_gain=False, level_z=DECIDED_Z))
    if shot["log10_photons"] is not None:
        # taken on a draw where its slope reads white there too (`whiteness_draws`): a slope on
        # the whiteness level is as uncertain a decision as a gain on the sign test's
        whiteness = shot.get("whiteness")
        gate = (lambda weights: whiteness_draws(whiteness, weights)) if whiteness is not None else None
        outcome = int(shot["white"] and shot["z"] >= level_z and shot["gain"] > 0)
        decisions.append(Decision("shot_noise", shot["tile_gains"], outcome, gate=gate))
    if optics_votes is not None:
        # a verdict that does not name the particles' optics claims the simulator's opaque
        # particles: where the optics test left them undecided, that claim holds only on the
        # draws where the tiles call them opaque
        tiles, views = optics_votes
        decisions.append(Decision("particle_phase", tiles, 1 if phase_selected else -1, needs_gain=False, three_way=True, views=views))
    if spectrum is not None:
        decisions.append(Decision(f"coherence as a spectrum's width rather than {' and '.join(spectrum['replaces'])}", spectrum["tile_gains"],
                                  int(spectrum["named"])))
    if dust is not None and dust["searched"]:
        # the window's grains counted by tile: named on a draw where they lie on LAYER_TILES tiles or more
        decisions.append(Decision("parasitic_fringes: dust on a window", dust["tiles"], int(dust["named"]), needs_gain=False,
                                  level_z=float(np.sqrt(LAYER_TILES)) - 1e-9))
    return decisions


def _found(image: np.ndarray, config: ExperimentConfig, most: int, progress, should_stop) -> dict:
    """`find_particles` with progress counted over its planes (twice the config's depth step)."""
    planes = len(config.volume.planes_um(2.0 * config.volume.z_step_um))
    return find_particles(image, config, max_particles=most, steps=Steps(planes, progress=progress, should_stop=should_stop))


def _scene(data: np.ndarray, found, config: ExperimentConfig, settings: SceneDiagnosisSettings, progress, should_stop, pool: WorkerPool) -> tuple:
    """The frame's particles fitted, with what the fits leave looked at again; their hologram as the camera records it.

    Every particle is fitted with its index and absorption free, the model closest to the
    data, so that what the frame's effects are judged on is as little of the particles'
    misfit as the fit can make it. A particle hidden by a neighbour (a pair closer than the
    finder's least distance, one behind another) is found in what the fits leave (``looks``
    times, `find_particles` on the residual hologram) and fitted there, the particles
    already fitted taken out of the data. The scene is rendered to ``reach_cycles_per_px``
    (`SceneDiagnosisSettings`). Depth groups of the particles are rendered alone too, for an
    effect that acts by depth (`Scene`).
    """
    import pandas as pd

    def render(table, reach: float) -> np.ndarray:
        return particle_hologram(data.shape, table, config, settings=settings.refine, reach_cycles_per_px=reach, should_stop=should_stop) if len(table) else np.ones(data.shape)

    def fit(image: np.ndarray, guesses):
        if not len(guesses):
            return guesses
        begin_phase(progress, f"the frame's scene: {len(guesses)} particles fitted")
        fitted = refine_particles(image, guesses, config, settings=settings.refine, progress=progress, should_stop=should_stop, pool=pool)
        return fitted[fitted["refined"]].reset_index(drop=True)

    columns = ["x_um", "y_um", "z_um", "diameter_um"]
    table = fit(data, found[columns])
    least_um = 0.25 * (config.particles.diameter_min_um + config.particles.diameter_max_um)
    for _ in range(settings.looks):
        if len(table) >= settings.scene_particles:
            break
        begin_phase(progress, "particles the fits missed, looked for in what they leave")
        # the Nyquist disc is enough to find what is missing
        residual = data - (render(table, 0.5) - 1.0)
        new = pd.DataFrame(_found(residual, config, settings.scene_particles - len(table), progress, should_stop))[columns]
        if len(table) and len(new):
            # a find on a kept particle is what its fit left of it, not another particle
            apart = np.hypot(new["x_um"].to_numpy()[:, None] - table["x_um"].to_numpy()[None], new["y_um"].to_numpy()[:, None] - table["y_um"].to_numpy()[None])
            new = new[apart.min(axis=1) > least_um]
        new = fit(residual, new)
        if new.empty:
            break
        table = pd.concat([table, new], ignore_index=True)
    # depth groups of about equal counts, each rendered alone: what a depth-dependent effect (coherence) blurs
    bins = depth_groups(table)
    begin_phase(progress, f"the scene of {len(table)} particles rendered, whole and in {len(bins)} depth groups")
    steps = Steps(1 + len(bins), progress=progress, should_stop=should_stop)
    scene = render(table, settings.reach_cycles_per_px)
    steps.advance()
    if len(table) < 2:
        return table, Scene(scene, pixel_um=config.optics.pixel_um)
    groups = []
    for rows in bins:
        groups.append(render(table.iloc[rows], settings.reach_cycles_per_px) - 1.0)
        steps.advance()
    groups = np.stack(groups).astype(np.float32)
    depths = tuple(float(table["z_um"].to_numpy()[rows].mean()) for rows in bins)
    return table, Scene(scene, depths, groups, config.optics.pixel_um)


def _small_scatterers(data: np.ndarray, table, scene: Scene, config: ExperimentConfig, settings: SceneDiagnosisSettings, progress, should_stop,
                      pool: WorkerPool):
    """What the fitted scene leaves, searched at the sizes below the config's: the frame's small scatterers, fitted.

    Debris, dust and bubbles are smaller than the sample and focus more weakly: the search
    for the sample's sizes (smoothing over their area, peaks a diameter apart) passes them by.
    The residual the scene's hologram (``scene.image``) leaves is searched again as if the particles were
    `_SMALL_FRACTION` of the config's least diameter up to it; each find away from the
    scene's particles is fitted (size free) and kept where its fit lowers the cost by the
    refinement's own significance (`RefineSettings.min_gain`'s default) and it is smaller than
    the sample. The scene itself is not changed: the effects are judged on the same particles.
    """
    import dataclasses

    import pandas as pd

    low = config.particles.diameter_min_um
    small = dataclasses.replace(config, particles=dataclasses.replace(config.particles, diameter_min_um=_SMALL_FRACTION * low, diameter_max_um=low))
    columns = ["x_um", "y_um", "z_um", "diameter_um"]
    residual = data - (scene.image - 1.0)
    begin_phase(progress, "small scatterers looked for in what the scene leaves")
    found = pd.DataFrame(_found(residual, small, settings.scene_particles, progress, should_stop))[columns]
    if len(table) and len(found):
        apart = np.hypot(found["x_um"].to_numpy()[:, None] - table["x_um"].to_numpy()[None], found["y_um"].to_numpy()[:, None] - table["y_um"].to_numpy()[None])
        found = found[apart.min(axis=1) > 0.5 * config.particles.diameter_max_um]
    if found.empty:
        return found
    begin_phase(progress, f"the small scatterers: {len(found)} fitted")
    significant = dataclasses.replace(settings.refine, min_gain=RefineSettings().min_gain)
    fitted = refine_particles(residual, found.reset_index(drop=True), config, settings=significant, progress=progress, should_stop=should_stop, pool=pool)
    return fitted[fitted["refined"] & (fitted["diameter_um"] < low)].reset_index(drop=True)


def _estimates(effect: str, selection) -> dict:
    """``{parameter: (value, standard error)}`` of a catalog effect of the mean (`FrameFit.estimate`); empty where it was not tried.

    A named effect's are those of the model the verdict names, fitted together with the other
    named effects (what the frame holds by the verdict); any other effect's, its own fit's.
    """
    source = selection.fits["+".join(selection.chosen)] if effect in selection.chosen else selection.fits.get(effect)
    if source is None:
        return {}
    return {name.split(".", 1)[1]: source.estimate(name) for name in source.params[0] if name.startswith(f"{effect}.")}


def diagnose_scene(hologram: np.ndarray, config: ExperimentConfig, *, settings: SceneDiagnosisSettings | None = None,
                   background: np.ndarray | None = None, progress: ProgressCallback | None = None,
                   should_stop: StopCallback | None = None, pool: WorkerPool | None = None) -> SceneDiagnosis:
    """Which catalog effects the experiment's frame holds, given its own particles (module docstring).

    Parameters
    ----------
    hologram : (rows, cols) array
        One frame, at least 128 pixels a side.
    config : ExperimentConfig
        Optics, depth range and the expected particle sizes.
    settings : SceneDiagnosisSettings, optional
    background : (rows, cols) array, optional
        A frame without particles: the hologram is divided by it (else by its mean).
    progress, should_stop : callable, optional
        ``progress(done, total)`` per phase (`begin_phase` names each: the particle models'
        fits, the scene's, the effects' selection), at least every second; ``should_stop``
        is heard within 2 s and raises `Stopped`.
    pool : WorkerPool, optional
        Processes for the fits, kept open by the caller across several frames so that they
        start once. Default: ``settings.refine.workers`` processes started for this frame and
        ended after it.

    Returns
    -------
    SceneDiagnosis
    """
    started = time.perf_counter()
    settings = settings or SceneDiagnosisSettings()
    data = as_hologram(hologram).astype(np.float64)
    if min(data.shape) < 128:
        raise InputError(f"hologram: expected at least 128 pixels a side, got {data.shape[0]}x{data.shape[1]}")
    if background is not None:
        scale = as_hologram(background, name="background").astype(np.float64)
        if scale.shape != data.shape:
            raise InputError(f"background: expected the hologram's shape {data.shape}, got {scale.shape}")
        data = data / np.maximum(scale, 1e-12)
    data = data / float(np.mean(data))
    # numpy's and scipy's BLAS work here on tall, narrow matrices (least squares over 131 000
    # pixels of a 1024² frame and a dozen parameters): a second OpenBLAS thread costs more in
    # hand-offs than it computes (the effects' selection 14.0 s on two threads, 7.8 s on one;
    # torch's fits keep their threads)
    with threadpool_limits(limits=1, user_api="blas"), (nullcontext(pool) if pool is not None else WorkerPool(settings.refine.workers)) as fits:
        return _diagnosed(data, np.asarray(hologram), config, settings, progress, should_stop, started, fits)


def _judged(data: np.ndarray, config: ExperimentConfig, split: TileSplit, settings: SceneDiagnosisSettings, progress, should_stop, pool: WorkerPool, *,
            again: bool = False) -> tuple:
    """The frame's particles found and fitted (`_scene`), the effects selected around them and the blur's origin: ``(table, scene, selection, blur_profile)``.

    ``again``: the frame is the light without a window's grains (the phases say so).
    """
    import pandas as pd

    cleared = "the frame without the window's grains: " if again else ""
    begin_phase(progress, f"{cleared}particles found in the back-propagated volume")
    found = pd.DataFrame(_found(data, config, max(settings.particles, settings.scene_particles), progress, should_stop)).drop(columns="focus")
    table, scene = _scene(data, found, config, settings, progress, should_stop, pool)
    begin_phase(progress, f"{cleared}the catalog's effects around {len(table)} fitted particles")
    selection = select_effects(data, scene, split, level_z=settings.level_z, progress=progress, should_stop=should_stop)
    begin_phase(progress, f"{cleared}the blur's origin read from each depth group's blur")
    steps = Steps(1, progress=progress, should_stop=should_stop, heartbeat_s=0.5)
    selection, blur_profile = attribute_blur(data, scene, split, selection, level_z=settings.level_z, check=steps.check)
    steps.advance()
    return table, scene, selection, blur_profile


def _diagnosed(data: np.ndarray, hologram: np.ndarray, config: ExperimentConfig, settings: SceneDiagnosisSettings, progress, should_stop,
               started: float, pool: WorkerPool) -> SceneDiagnosis:
    """`diagnose_scene` of the frame ``data`` (divided by its background and mean; ``hologram`` as recorded, for its levels)."""
    split = TileSplit.of(data.shape, grid=settings.grid)
    table, scene, selection, blur_profile = _judged(data, config, split, settings, progress, should_stop, pool)
    frame_spectra = tile_spectra(data - 1.0, split)
    dust = {"searched": False, "named": False}
    recorded_share = None  # the scene alone on the recorded frame, where a window is divided out of it
    final = selection.fits["+".join(selection.chosen) or "baseline"]
    structured = unexplained_share(final.residuals, split, frame_spectra)[0] > settings.structure_level
    if structured or np.count_nonzero(outside_volume(table, config)) >= LAYER_TILES:
        # what the model leaves holds structure, or the scene holds particles fitted outside the
        # volume: a dusty window's grains are looked for in it, and among them
        begin_phase(progress, "dust on a window outside the volume, looked for in what the model leaves and in the scene")
        dust = dust_layer(data / np.maximum(0.5 * (final.means[0] + final.means[1]), 1e-6), config, split, settings=settings.refine, scene=table,
                          search=structured, pool=pool, progress=progress, should_stop=should_stop)
        searched = dust["table"][~dust["table"]["in_scene"].astype(bool)] if dust["named"] else ()
        if len(searched):
            # the window's rings multiply the light: the frame divided by the searched grains'
            # hologram is the light without them, on which the particles are fitted again and
            # every effect judged again (fits made through the rings bend to them, and what
            # they leave grows with depth like a source's blur)
            recorded_share = unexplained_share(selection.fits["baseline"].residuals, split, frame_spectra)[0]
            window = particle_hologram(data.shape, searched, config, settings=settings.refine, reach_cycles_per_px=settings.reach_cycles_per_px,
                                       should_stop=should_stop)
            data = data / np.maximum(window, _WINDOW_FLOOR)
            data = data / float(np.mean(data))
            table, scene, selection, blur_profile = _judged(data, config, split, settings, progress, should_stop, pool, again=True)
            frame_spectra = tile_spectra(data - 1.0, split)
        if dust["named"]:
            # the window's grains the scene fitted as particles stay in its image (a grain's
            # hologram is a particle's) and leave its table: they are not the sample
            table = table[~in_window(table, dust, config)].reset_index(drop=True)
    begin_phase(progress, "the named blur against a spectrum's width in its place")
    steps = Steps(1, progress=progress, should_stop=should_stop, heartbeat_s=0.5)
    selection, spectrum = spectrum_width_test(data, scene, split, selection, level_z=settings.level_z, check=steps.check)
    steps.advance()
    optics = _optics(data, table, selection, config, split, settings, progress, should_stop)
    optics_votes = optics.pop("votes", None)  # each tile's and each sphere's vote, for the verdict's probability
    rendered = optics.pop("rendered", None)
    if optics["model"] == "transparent":
        # the named spheres' far rings, which the fitted scene does not render, stay in the
        # residual and their power grows with the light: photon noise is tested beside it
        final_fit = selection.fits["+".join(selection.chosen) or "baseline"]
        selection = replace(selection, shot_noise=shot_noise_test(final_fit, split, nuisance=far_ring_power(rendered)))
    small = _small_scatterers(data, table, scene, config, settings, progress, should_stop, pool)
    baseline_share = unexplained_share(selection.fits["baseline"].residuals, split, frame_spectra)[0]
    final = selection.fits["+".join(selection.chosen) or "baseline"]
    share, bands, tile_map, floor_variance = unexplained_share(final.residuals, split, frame_spectra)
    lines = line_pattern(final.residuals)
    directional = directional_blur_test(final.residuals, final.means, split, final.loglik)
    by_depth = share_by_depth(selection.fits["baseline"].residuals, final.residuals, data, table, split, floor_variance,
                         pixel_um=config.optics.pixel_um, reach_px=settings.refine.patch_px // 2)
    effects = []
    first_round = selection.steps[0]["gains"] if selection.steps else {}
    for effect in MEAN_EFFECTS:
        fit = selection.fits.get(effect)
        # an effect not tried (coherence without two particles to group by depth) leaves the gap as it is
        after = unexplained_share(fit.residuals, split, frame_spectra)[0] if fit is not None else baseline_share
        estimates = _estimates(effect, selection)
        gain = first_round.get(effect, {})
        effects.append({"id": effect, "gap_after": after, "shrink": 1.0 - after / baseline_share if baseline_share > 0 else 0.0,
                        "params": {name: value for name, (value, _) in estimates.items()},
                        "params_err": {name: (error if np.isfinite(error) else None) for name, (_, error) in estimates.items()},
                        "heldout_gain_nats": gain.get("gain_nats"), "z": gain.get("z"), "selected": effect in selection.chosen})
    if dust["named"]:
        # the catalog's dust is its static fringes' second source: named with the window's
        # numbers, and the straight fringe's only where it was selected too
        fringes = next(entry for entry in effects if entry["id"] == "parasitic_fringes")
        etalon = fringes["selected"]
        fringes.update({"selected": True, "dust_z": dust["z"],
                        "params": {**(fringes["params"] if etalon else {}), **dust["params"]},
                        "params_err": {**(fringes["params_err"] if etalon else {}),
                                       **{name: (error if np.isfinite(error) else None) for name, error in dust["params_err"].items()}}})
    phase_selected = bool(optics["model"] == "transparent")
    # the particles' optics and the camera's noise and levels leave the fitted mean, so the gap, as it is
    effects.append({"id": "particle_phase", "gap_after": baseline_share, "shrink": 0.0, "z": optics["z"], "selected": phase_selected,
                    "params": {"index_contrast": optics["index_contrast"], "transmission": 1.0} if phase_selected else {}})
    shot = selection.shot_noise
    shot_selected = bool(shot["z"] >= settings.level_z and shot["gain"] > 0 and shot["white"])
    effects.append({"id": "shot_noise", "gap_after": baseline_share, "shrink": 0.0, "z": shot["z"], "heldout_gain_nats": shot["gain"], "selected": shot_selected,
                    "band_ratios": shot["band_ratios"], "fine_ratios": shot["fine_ratios"], "noise_blur_px": shot["noise_blur_px"],
                    "params": {"log10_photons": shot["log10_photons"]} if shot["log10_photons"] is not None else {},
                    "params_err": {"log10_photons": shot["log10_photons_err"]} if shot["log10_photons"] is not None else {}})
    levels = levels_test(hologram, 0.5 * (final.means[0] + final.means[1]) - data, floor_variance=floor_variance)
    effects.append({"id": "quantization", "gap_after": baseline_share, "shrink": 0.0, "z": None, "selected": levels["selected"], "params": levels["params"],
                    "levels": {k: levels[k] for k in ("integer", "step_counts", "noise_share", "saturated_share", "saturation_noise_share")}})
    effects.sort(key=lambda entry: -(entry["z"] if entry["z"] is not None and np.isfinite(entry["z"]) else -np.inf))
    named = sorted([e["id"] for e in effects if e["selected"]])
    # what the tiles' gains chose: not the converter's levels, nor a window's dust (counted by its grains' tiles)
    gained = {e for e in named if e != "quantization" and not (e == "parasitic_fringes" and "parasitic_fringes" not in selection.chosen)}
    undecided = sorted({name for pair in selection.undecided for name in (pair["selected"], pair["rival"])})
    between = "; ".join(f"{pair['selected']} or {pair['rival']} (z {pair['z']:.1f} in its favour)" for pair in selection.undecided)
    patterned = [name for name, ratio in lines.items() if ratio > settings.line_level]
    streaked = bool(directional["z"] >= settings.level_z and directional["gain_nats"] > 0)
    catalog_explains = share <= settings.structure_level and not patterned and not streaked
    left = (f"unexplained share of the frame's structure {share:.3f} (median over the tiles; {'at most' if share <= settings.structure_level else 'above'} "
            f"{settings.structure_level:g})" + (f"; a fixed pattern in the {' and '.join(patterned)} (variance of their means {max(lines.values()):.1f}x white noise's)" if patterned else "")
            + (f"; a blur that differs by direction, outside the catalog (motion during the exposure, astigmatism: z {directional['z']:.1f}, "
               f"{directional['variance_difference_px2']:.2f} px² more along {np.degrees(directional['angle_rad']):.0f}°)" if streaked else ""))
    posterior = {("null" if name == "baseline" else name): p for name, p in selection.probabilities.items()}
    confidence = verdict_probability(_decisions(selection, shot, optics_votes, phase_selected, blur_profile, level_z=settings.level_z, spectrum=spectrum, dust=dust),
                                     level_z=settings.level_z)
    report = {
        "method": "scene",
        "gap": {"metric": "unexplained share of the frame's structure (median over the held-out tiles)", "baseline": baseline_share,
                "baseline_recorded_frame": recorded_share, "by_band": bands,
                "by_depth": by_depth, "line_pattern": lines, "directional_blur": directional, "particles": optics["particles"], "tiles": split.grid**2, "tile_px": split.size},
        "effects": effects,
        "verdict": {"id": None if undecided else "+".join(named) or None, "shrink": 1.0 - share / baseline_share if baseline_share > 0 else 0.0,
                    "residual": share, "undecided": undecided, "catalog_explains": bool(catalog_explains), "probability": confidence["probability"],
                    "reason": (f"selected by held-out gain (z >= {settings.level_z:g}): {', '.join(n for n in named if n in gained) or 'nothing'}"
                               + ("; quantization or saturation read from the frame's levels" if levels["selected"] else "")
                               + (f"; dust on a window {dust['depth_um'] / 1000:.1f} mm away: {dust['in_layer']} grains in one plane on "
                                  f"{int(np.count_nonzero(dust['tiles']))} tiles" if dust["named"] else "")
                               + (f"; undecided between {between}" if between else "")
                               + (f"; particle optics undecided (z {optics['z']:.1f}: neither the fine rings' spectrum nor the light on the spheres' "
                                  f"axes through focus tells transparent spheres from opaque ones)" if optics["model"] == "undecided" and optics["particles"] else "")
                               + f"; {left}")},
        "posterior": posterior,
        "confidence": confidence["decisions"],
        "particle_optics": optics,
        "scene": scene_population(table, config, data.shape, small=small),
        "blur_by_depth": blur_profile,
        "dust_layer": dust_record(dust),
        "spectrum_width": None if spectrum is None else {key: value for key, value in spectrum.items() if key != "tile_gains"},
        "selection": selection.steps,
        "undecided": list(selection.undecided),
        "not_tested": _NOT_TESTED,
    }
    return SceneDiagnosis(report, tile_map, table, round(time.perf_counter() - started, 2))
