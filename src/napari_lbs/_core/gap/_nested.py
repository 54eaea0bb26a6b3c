"""Catalog effects as nested models of the experiment's frame, around its own fitted particles.

The frame's model is the catalog's camera (`sensor_image`, the code that makes training data)
applied to the hologram of the experiment's particles as they were fitted (`particle_hologram`):

    mean = gain · sensor_image(scene; contrast, gamma; effects)

The baseline fits ``gain``, the fringe ``contrast`` and the response ``gamma`` (the seed's
noise offset acts as a fringe contrast once a frame is normalised; its gamma map as a
response). Each effect adds its catalog parameters and is nothing at their neutral values, so
the baseline is nested in every model and a model with an effect in every model with one more.

Effects of the mean: ``illumination`` (the beam's envelope: depth, waist and centre),
``sensor_blur`` (σ in pixels, blurring the light before the noise is added),
``parasitic_fringes`` (an etalon's straight fringe: amplitude, period, angle and phase, started at the
residual's strongest spectral peak, refined by its Fourier sum) and ``coherence`` (a source of angular size θ: each
particle's pattern blurred by σ = θ·z, so that deep particles lose their fine fringes and
shallow ones keep them, where a sensor's blur takes the same from every depth; the scene's
particles are rendered in depth groups for it, `Scene`). ``shot_noise`` changes the noise, not the mean: it is
judged on the high-passed residual, whose variance grows with the light by ``1 / photons``.

Parameters are fitted by least squares on the tiles of one colour (`TileSplit`), every other
pixel of them, and judged on the other colour's tiles by the held-out likelihood
(`whittle_loglik`). Forward selection adds the effect of the largest significant held-out
gain (``z``: a sign test over the held-out tiles, `_gain`, ties broken by the summed gain,
which must be positive too), fits the model again from its optimum (so that the next round's
models, which start there, gain by their effect and not by further steps on the parameters
they share), and stops when no effect reaches ``level_z``; backward elimination then drops,
one at a time, a selected effect that no longer reaches ``level_z`` given the others. A
selected effect that does not beat, at a z of 2, a rival put in its place (one that gained alone) is undecided between the two:
spatial coherence and a sensor's blur both soften fine fringes, and only their growth with
depth tells them apart.
"""

from __future__ import annotations

import concurrent.futures
import threading
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage, optimize
from scipy.signal import fftconvolve

from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback, Stopped, process_threads, thread_pool
from napari_lbs._core.gap._confidence import sign_z
from napari_lbs._core.gap._heldout import TileSplit, model_probabilities, tile_spectra, whittle_loglik
from napari_lbs._core.gap._scene_image import Scene
from napari_lbs._core.gap._tile_errors import clustered_errors, mean_of_halves
from napari_lbs._core.physics import EFFECTS, gaussian_blur, sensor_image

__all__ = ["DECIDED_Z", "EVERY_OTHER", "MEAN_EFFECTS", "FrameFit", "gain_and_z", "Selection", "both_colours", "fit_frame", "last_two", "far_ring_power", "select_effects", "shot_noise_test", "whiteness_draws"]

# the parameters each effect of the mean fits (the others of its catalog entry stay neutral)
MEAN_EFFECTS = {
    "illumination": ("depth", "waist", "x0", "y0"),
    "sensor_blur": ("sigma_px",),
    "parasitic_fringes": ("amplitude", "period_px", "angle_rad", "phase_rad"),
    "coherence": ("theta_mrad",),
}
_BY_DEPTH = ("coherence",)  # effects that need the scene's depth groups


_BASELINE = (("gain", 1.0, (0.2, 5.0)), ("contrast", 1.0, (0.0, 3.0)), ("gamma", 1.0, (0.3, 3.0)))
_STEPS = 12  # least-squares steps per fit: the starts are the simpler model's optimum
_HIGH_PASS_PX = 1.5  # the shot-noise test's high pass: the residual less its Gaussian blur of this σ
_BAND_PX = (1.0, 3.0)  # its band pass, for blurred noise's whiteness check: the residual's blur of the first σ less that of the second
_FINE_TAPS = np.array([1.0, -2.0, 1.0])  # its finest filter, for white noise's: the second difference along rows, then along columns
_SMOOTH_LIGHT_PX = 8.0  # the light's smooth part, about which the fringes vary: the Gaussian blur of the mean of this σ
WHITE_RATIO = 2.0  # photon noise's slope in its hypothesis's filter (the finest for white noise, the band for blurred) over that in the high pass lies within this factor of the hypothesis's on each colour
DECIDED_Z = 2.0  # the sign test's z by which a selected effect must beat a rival in its place
# the pixels a fit compares: every other row and column of the fitted tiles (neighbours add little but cost)
EVERY_OTHER = (slice(0, None, 2), slice(0, None, 2))


def last_two(compute):
    """``compute(value)`` remembered for the two latest values: a least-squares step's Jacobian moves one parameter at a time, so a costly part that depends on one parameter is redone for that parameter's own moves only."""
    recent: dict = {}

    def remembered(value):
        if value not in recent:
            if len(recent) >= 2:
                recent.pop(next(iter(recent)))
            recent[value] = compute(value)
        return recent[value]

    return remembered


@dataclass(frozen=True)
class FrameFit:
    """One model fitted twice, on each colour's tiles: its parameters, residuals and held-out log-likelihood per tile."""

    effects: tuple[str, ...]
    params: tuple[dict, dict]
    loglik: np.ndarray = field(repr=False)
    residuals: tuple[np.ndarray, np.ndarray] = field(repr=False)
    means: tuple[np.ndarray, np.ndarray] = field(repr=False)
    errors: tuple[dict, dict] = field(default=({}, {}), repr=False)  # each colour's standard errors (`clustered_errors`; NaN on a bound)

    def estimate(self, name: str) -> tuple[float, float]:
        """Parameter ``name``: the mean of the two colours' fits and its standard error (`mean_of_halves`; NaN where either colour has none).

        The two colours' tiles are disjoint halves of the frame, so their fits are two
        independent measurements.
        """
        return mean_of_halves([params[name] for params in self.params], [errors.get(name, np.nan) for errors in self.errors],
                              period=2 * np.pi if name.endswith("phase_rad") else None)


@dataclass(frozen=True)
class Selection:
    """What forward selection found: the models it fitted, the gains it judged, the effects it kept.

    ``undecided`` holds a record per selected effect and rival (one that gained alone) that
    predicts the held-out tiles about as well in its place: ``selected``, ``rival``,
    ``gain_nats`` and ``z`` of the selected model over the swapped one.
    """

    chosen: tuple[str, ...]
    fits: dict
    steps: list
    probabilities: dict
    shot_noise: dict
    undecided: tuple = ()


def _fringe_start(residual: np.ndarray) -> dict:
    """Amplitude, period (px), angle and phase (rad) of the residual's most prominent straight fringe within the catalog's periods.

    Prominent over its ring: the spectrum divided by its median at the same radius. A
    particle's misfit spreads its power round a ring of frequencies (its fringes point every
    way); a straight fringe puts all of its power at one frequency, however weak it is beside
    the rings. The peak's bin is then refined by the residual's Fourier sum on a grid a tenth
    of a bin fine within a bin of it: a fringe's phase drifts by 2π over the frame for every
    bin its frequency is off, and a fit started a half bin away turns its period to follow
    the phase instead of finding it. The sum's argument at the refined frequency is the
    fringe's phase at the first pixel, twice its modulus over the pixels summed its amplitude.
    """
    centred = residual - residual.mean()
    spectrum = np.abs(np.fft.rfft2(centred)) ** 2
    fy = np.fft.fftfreq(residual.shape[0])[:, None]
    fx = np.fft.rfftfreq(residual.shape[1])[None, :]
    radius = np.hypot(fx, fy)
    ring = np.minimum((radius * min(residual.shape)).astype(int), min(residual.shape))  # rings one frequency step wide
    medians = np.zeros(ring.max() + 1)
    order = np.argsort(ring, axis=None)
    bounds = np.searchsorted(ring.ravel()[order], np.arange(ring.max() + 2))
    values = spectrum.ravel()[order]
    for k in range(ring.max() + 1):
        if bounds[k + 1] > bounds[k]:
            medians[k] = np.median(values[bounds[k] : bounds[k + 1]])
    prominence = spectrum / np.maximum(medians[ring], 1e-30)
    prominence[(radius < 1.0 / 24.0) | (radius > 0.25)] = 0.0  # within the catalog's periods, 4-24 px
    row, col = np.unravel_index(int(np.argmax(prominence)), prominence.shape)
    f_x, f_y = float(fx[0, col]), float(fy[row, 0])
    if f_y < 0:  # the model's angle lies in [0, π): the same fringe, its wave vector turned round
        f_x, f_y = -f_x, -f_y
    rows, cols = residual.shape
    offsets = np.linspace(-1.0, 1.0, 21)
    grid_x, grid_y = f_x + offsets / cols, f_y + offsets / rows
    sums = np.exp(-2j * np.pi * np.outer(grid_y, np.arange(rows))) @ centred @ np.exp(-2j * np.pi * np.outer(np.arange(cols), grid_x))
    k_y, k_x = np.unravel_index(int(np.argmax(np.abs(sums))), sums.shape)
    f_x, f_y = float(grid_x[k_x]), float(grid_y[k_y])
    counted = max(int(np.count_nonzero(residual)), 1)  # the pixels of the fitted tiles (the others are zeros)
    return {"amplitude": float(np.clip(2.0 * np.abs(sums[k_y, k_x]) / counted, 0.005, 0.1)), "period_px": 1.0 / max(np.hypot(f_x, f_y), 1e-6),
            "angle_rad": float(np.arctan2(f_y, f_x) % np.pi), "phase_rad": float(np.angle(sums[k_y, k_x]))}


def _starts(effect: str, residual: np.ndarray) -> dict:
    if effect == "parasitic_fringes":
        return _fringe_start(residual)
    return {"illumination": {"depth": 0.1, "waist": EFFECTS["illumination"].neutral["waist"], "x0": 0.0, "y0": 0.0}, "sensor_blur": {"sigma_px": 0.6},
            "coherence": {"theta_mrad": 0.5, "bandwidth_nm": 5.0}}[effect]


def _mean(scene: Scene, values: dict, effects: tuple[str, ...], zeros: np.ndarray, *, keep: tuple[slice, slice] | None = None,
          blurred=None) -> np.ndarray:
    """The model's frame (``keep``: its kept rows and columns, `sensor_image`); ``blurred(value)`` stands for the coherence's law.

    Coherence is a source's size (``coherence.theta_mrad``, `Scene.coherent_blur`) or, where
    the model holds ``coherence.bandwidth_nm`` instead, a spectrum's width (`Scene.spectral_blur`).
    """
    image = scene.image
    if "coherence" in effects:
        spectral = "coherence.bandwidth_nm" in values
        law = blurred or (scene.spectral_blur if spectral else scene.coherent_blur)
        image = law(values["coherence.bandwidth_nm" if spectral else "coherence.theta_mrad"])
    camera = [e for e in effects if e not in _BY_DEPTH]
    chosen = {e: {**EFFECTS[e].neutral, **{p: values[f"{e}.{p}"] for p in MEAN_EFFECTS[e]}} for e in camera}
    baseline = {"contrast": values["contrast"], "sigma": 0.0, "gamma": values["gamma"]}
    return values["gain"] * sensor_image(image, baseline, chosen, noise=zeros, keep=keep).astype(np.float64)


def _fit(data: np.ndarray, scene: Scene, mask: np.ndarray, effects: tuple[str, ...], start: dict, zeros: np.ndarray, check,
         tiles: np.ndarray, parameters: dict) -> tuple[dict, dict]:
    """The least-squares fit on ``mask``'s pixels (every other one) and its parameters' errors, ``tiles`` (`TileSplit.labels`) their clusters."""
    names = [name for name, _, _ in _BASELINE] + [f"{e}.{p}" for e in effects for p in parameters[e]]
    bounds = {name: limits for name, _, limits in _BASELINE}
    bounds.update({f"{e}.{p}": EFFECTS[e].bounds[p] for e in effects for p in parameters[e]})
    x0 = np.array([float(np.clip(start[name], *bounds[name])) for name in names])
    sample = mask[EVERY_OTHER]
    target = data[EVERY_OTHER][sample]
    # the coherence's blur is redone for its own parameter's moves only
    blurred = last_two(scene.spectral_blur if "coherence.bandwidth_nm" in names else scene.coherent_blur)

    def residual(x: np.ndarray) -> np.ndarray:
        if check is not None:
            check()  # a stop is heard, and progress reported, within an evaluation
        return _mean(scene, dict(zip(names, x, strict=True)), effects, zeros, keep=EVERY_OTHER, blurred=blurred)[sample] - target

    low, high = np.array([bounds[n][0] for n in names]), np.array([bounds[n][1] for n in names])
    # ``max_nfev`` counts steps here: each also costs one evaluation per parameter for the Jacobian
    result = optimize.least_squares(residual, x0, bounds=(low, high), x_scale="jac", max_nfev=_STEPS, diff_step=1e-3, ftol=1e-5, xtol=1e-5)
    errors = clustered_errors(result.jac, result.fun, tiles[EVERY_OTHER][sample], fixed=result.active_mask != 0)
    return dict(zip(names, (float(v) for v in result.x), strict=True)), dict(zip(names, (float(e) for e in errors), strict=True))


def fit_frame(data: np.ndarray, scene, split: TileSplit, effects: tuple[str, ...], *, starts: tuple[dict, dict] | None = None, check=None,
              parameters: dict | None = None) -> FrameFit:
    """Fit ``effects`` (and the baseline) on each colour's tiles; the held-out log-likelihood of every tile.

    ``scene``: a `Scene`, or the particles' hologram as an array (no depth-dependent effect then).
    ``check``: called before each evaluation of the model (`Steps.check`: raises `Stopped`).
    ``parameters``: an effect's fitted parameters where they are not `MEAN_EFFECTS`' (a
    spectrum's width for coherence: ``{"coherence": ("bandwidth_nm",)}``).
    """
    parameters = {**MEAN_EFFECTS, **(parameters or {})}
    zeros = np.zeros(data.shape, np.float32)
    scene = Scene.of(scene)
    scene32 = replace(scene, image=scene.image.astype(np.float32))

    def on_colour(colour: int, heard) -> tuple:
        start = {name: value for name, value, _ in _BASELINE}
        if starts is not None:
            start.update(starts[colour])
        for effect in effects:
            if not all(f"{effect}.{p}" in start for p in parameters[effect]):
                guess = _starts(effect, np.where(split.mask(colour), data - start["gain"] * scene.image, 0.0))
                start.update({f"{effect}.{p}": v for p, v in guess.items() if p in parameters[effect]})
        fitted, errors = _fit(data, scene32, split.mask(colour), effects, start, zeros, heard, tiles, parameters)
        mean = _mean(scene32, fitted, effects, zeros)
        return fitted, errors, mean, data - mean, tile_spectra(data - mean, split)

    tiles = split.labels()
    (params0, errors0, mean0, residual0, spectra0), (params1, errors1, mean1, residual1, spectra1) = both_colours(on_colour, check)
    return FrameFit(tuple(effects), (params0, params1), whittle_loglik((spectra0, spectra1), split), (residual0, residual1), (mean0, mean1),
                    (errors0, errors1))


def both_colours(on_colour, check) -> tuple:
    """``(on_colour(0, check), on_colour(1, ...))``, the two side by side where the process has two threads.

    The fits of the two colours are independent and spend their time in numpy,
    which release the GIL. Colour 1 runs on a pool thread, which hears a stop through an event
    set when this thread's ``check`` raises (progress is reported from this thread alone).
    """
    if process_threads() < 2:
        return on_colour(0, check), on_colour(1, check)
    stopping = threading.Event()

    def heard() -> None:
        if stopping.is_set():
            raise Stopped("stopped with the other colour's fit")

    other = thread_pool("frame-fit").submit(on_colour, 1, heard)
    try:
        first = on_colour(0, check)
        while not other.done():
            if check is not None:
                check()
            concurrent.futures.wait([other], timeout=0.25)
    except BaseException:
        stopping.set()
        concurrent.futures.wait([other])
        raise
    return first, other.result()


def gain_and_z(better: np.ndarray, worse: np.ndarray) -> tuple[float, float]:
    """Summed held-out gain (nats) and its sign test's z over the tiles.

    ``z = (tiles gaining - tiles losing) / sqrt(tiles either way)``: an effect the frame holds
    acts on every tile and helps nearly all of them, where a particle the scene misfits
    swings one tile by thousands of nats either way; counting tiles keeps such a tile to one
    vote (on a development etalon, 14 of 16 tiles gained 80-480 nats and two lost 570 and
    1 270: its summed gain over its tile-to-tile error was 1.2, its sign test 3.0). The sum
    still has to be positive (`select_effects`).
    """
    difference = better - worse
    return float(difference.sum()), sign_z(difference)


def _high_passed(image: np.ndarray) -> np.ndarray:
    """The shot-noise test's high pass: ``image`` less its Gaussian blur of ``_HIGH_PASS_PX``."""
    return image - gaussian_blur(image, _HIGH_PASS_PX)


def far_ring_power(rendered: np.ndarray) -> tuple[np.ndarray, ...]:
    """The local power of a scene's rings in each of the shot-noise test's filters (``blur(filtered², 3 px)``: the high pass, the band pass, the finest).

    ``rendered``: the scene rendered to 1 cycle per pixel under the particle model the optics
    test named (transparent spheres' far rings, aliased as the pixels record them); the
    fitted scene reaches the Nyquist disc only, so those rings stay in the residual, and
    their power, which grows with the light about them, is a nuisance of `shot_noise_test`.
    """
    return tuple(gaussian_blur(passed(rendered) ** 2, 3.0) for passed in _FILTERS)


def _band_passed(image: np.ndarray) -> np.ndarray:
    """Its band pass, for blurred noise's whiteness check: ``image``'s blurs of the two σ of ``_BAND_PX``, the wider subtracted."""
    return gaussian_blur(image, _BAND_PX[0]) - gaussian_blur(image, _BAND_PX[1])


def _fine_passed(image: np.ndarray) -> np.ndarray:
    """Its finest filter, for white noise's whiteness check: ``image``'s second difference along each axis in turn (the spectrum's corners)."""
    return ndimage.correlate1d(ndimage.correlate1d(image, _FINE_TAPS, axis=0, mode="reflect"), _FINE_TAPS, axis=1, mode="reflect")


_FILTERS = (_high_passed, _band_passed, _fine_passed)  # the test's filters, in the order of its slopes: the high pass first, the slope's own
_BAND, _FINE = 1, 2  # their places in `_FILTERS`


def shot_noise_test(fit: FrameFit, split: TileSplit, *, nuisance: tuple[np.ndarray, ...] = ()) -> dict:
    """Does the residual's variance grow with the light? A held-out test of a signed slope in the mean.

    The residual is high-passed (less its Gaussian blur of σ = 1.5 px) to keep the noise and
    little of the structure. Its squares are regressed, over one colour's tiles, on what an
    imperfect particle model leaves — the local fringe amplitude ``|mean - blur(mean, 8 px)|``
    and the model's own local fine-fringe power ``blur((mean - blur(mean, 1.5 px))², 3 px)``,
    where the rings beyond the scene's rendered reach lie, which a pixel records and the
    model does not — with and without the mean itself (photon noise is larger on the bright
    fringes than on the dark ones), and the Gaussian log-likelihoods of the two are compared
    on the other colour's tiles, every other pixel of every other row. ``log10_photons`` is
    the catalog's parameter: photons per unit of normalised light, from the slope corrected
    for the high pass's share of white noise; ``log10_photons_err`` its standard error, the
    tiles the slope was fitted on its clusters (`clustered_errors`).

    Photon noise is white: per unit of the white noise each filter keeps, its slope is the
    same in every filter. What the fitted particles leave is red — misfit rings, a window's
    rings from grains outside the field, a blur's or an envelope's misfit: its power falls
    with the spatial frequency — so white noise's slope is compared between the two finest
    filters, the high pass and the second difference along each axis (``_FINE_TAPS``, the
    spectrum's corners), where the leftovers hold least. On the development frames photon
    noise reads a fine ratio of 0.85–1.06 alone and 0.70–0.94 beside a window's dust or
    transparent spheres of n 1.46 (whose band ratios, 1.9–4.4 and 0.4–3.4, read it as
    not white), and the leftovers alone at most 0.45. A camera that blurs its charge (crosstalk,
    a colour sensor's interpolation) blurs its noise too: where the model holds a sensor
    blur, noise blurred by it is the other hypothesis, read on the band pass (``_BAND_PX``: the
    blur of σ 1 px less that of σ 3 px) against the high pass (blurred noise's band ratio is
    12 for σ 1 px of white's 1), since the second difference keeps under 2 % of it, and that
    share hangs on the kernel's shape near the Nyquist frequency, which a Gaussian does not
    model. ``band_ratios`` and ``fine_ratios`` are each colour's slope in the band and in the
    finest filter over its slope in the high pass, per unit of white noise's (each on the
    light weighted by its filter's kernel squared about each pixel, which is what a filtered
    pixel's variance follows: on the pixel's own light, fringes a few pixels apart dilute the
    band's slope, to 0.67–0.75 of photon noise's on a test frame; and each within
    neighbourhoods, the light's smooth part ``blur(mean, 8 px)`` a nuisance regressor: under
    an envelope the misfit it scales follows the smooth light, and read on it one colour's
    ratio fell to −0.3–0.5 where photon noise alone gives 1);
    ``noise_blur_px`` the hypothesis whose ratios (the fine ones for white noise, the band's
    for blurred noise) lie nearer it (0: white), whose filters' shares give
    ``log10_photons``, per unit of the noise's variance in a pixel as recorded (blurred noise
    of that variance came from 1 / Σg² fewer photons, g the blur's kernel: 12.6 for σ 1 px);
    ``white`` whether both lie within a factor ``WHITE_RATIO`` of it; ``tile_gains`` the
    held-out gain of each tile (nats), whose signs the sign test counts (`_confidence`);
    ``whiteness`` each tile's normal equations of the filtered slopes' regressions, from
    which `whiteness_draws` reads ``white`` again on reweighted tiles.

    ``nuisance``: more maps of what the residual holds besides noise, regressors of every
    filter's variance beside the misfit's (the local power of transparent spheres' far rings,
    which the fitted scene does not render: `far_ring_power`).
    """
    # white noise, and noise blurred by the camera's fitted blur (a colour sensor's
    # interpolation, charge shared between pixels): each filter's share of its variance
    blur_px = float(np.mean([params["sensor_blur.sigma_px"] for params in fit.params])) if "sensor_blur" in fit.effects else 0.0
    kept, light_weights = {}, {}  # per hypothesis, each filter's (`_FILTERS`) share and its kernel squared
    for sigma in {0.0, blur_px}:
        impulse = np.zeros((41, 41))
        impulse[20, 20] = 1.0
        noise = gaussian_blur(impulse, sigma) if sigma > 0 else impulse
        # per unit of the noise's variance in a pixel, as recorded (the catalog's photon noise is added per pixel)
        passed = [filtered(noise) for filtered in _FILTERS]
        kept[sigma] = np.array([np.sum(p**2) / np.sum(noise**2) for p in passed])
        # a filtered pixel's variance is the light about it weighted by the filter's kernel squared
        light_weights[sigma] = [p**2 / np.sum(p**2) for p in passed]
    colours = split.colours()
    gains = np.zeros(len(colours))
    slopes, slope_errors = [], []
    normal = {(colour, sigma): [] for colour in (0, 1) for sigma in kept}  # per colour and hypothesis: each filter's, in `_FILTERS`' order
    moments = {(colour, sigma): [] for colour in (0, 1) for sigma in kept}
    for fitted_on in (0, 1):
        residual, mean = fit.residuals[fitted_on], fit.means[fitted_on]
        filtered = [passed(residual) for passed in _FILTERS]
        high = filtered[0]
        smooth_light = gaussian_blur(mean, _SMOOTH_LIGHT_PX)
        misfit = (np.abs(mean - smooth_light), gaussian_blur(_high_passed(mean) ** 2, 3.0), *nuisance)
        # per tile: the high-passed residual, the null's regressors (1 and the misfit's), the mean
        samples = [(high[w][::2, ::2].ravel(), np.stack([np.ones(high[w][::2, ::2].size)] + [m[w][::2, ::2].ravel() for m in misfit], axis=1), mean[w][::2, ::2].ravel(), c)
                   for w, c in zip(split.windows(), colours, strict=True)]
        fitted = [s for s in samples if s[3] == fitted_on]
        h2 = np.concatenate([s[0] for s in fitted]) ** 2
        x_null = np.concatenate([s[1] for s in fitted])
        x_photon = np.concatenate([x_null, np.concatenate([s[2] for s in fitted])[:, None]], axis=1)
        null, *_ = np.linalg.lstsq(x_null, h2, rcond=None)
        alternative, *_ = np.linalg.lstsq(x_photon, h2, rcond=None)
        slopes.append(float(alternative[-1]))
        own = [w for w, c in zip(split.windows(), colours, strict=True) if c == fitted_on]
        squares = [h2] + [np.concatenate([image[w][::2, ::2].ravel() for w in own]) ** 2 for image in filtered[1:]]
        # the slope within neighbourhoods: what follows the frame's smooth light (the misfit an
        # envelope scales) is a nuisance; photon noise follows the light fringe by fringe
        smooth = np.concatenate([smooth_light[w][::2, ::2].ravel() for w in own])[:, None]
        tile_of = np.concatenate([np.full(s[0].size, k) for k, s in enumerate(fitted)])
        for sigma, weights in light_weights.items():
            for filtered_squares, weight in zip(squares, weights, strict=True):
                light = fftconvolve(mean, weight, mode="same")
                x_light = np.concatenate([x_null, smooth, np.concatenate([light[w][::2, ::2].ravel() for w in own])[:, None]], axis=1)
                # each tile's normal equations: their sum gives the slope, a reweighting of the tiles refits it (`whiteness_draws`)
                normal[(fitted_on, sigma)].append(np.stack([x_light[tile_of == k].T @ x_light[tile_of == k] for k in range(len(own))]))
                moments[(fitted_on, sigma)].append(np.stack([x_light[tile_of == k].T @ filtered_squares[tile_of == k] for k in range(len(own))]))
        slope_errors.append(float(clustered_errors(x_photon, h2 - x_photon @ alternative, tile_of)[-1]))
        least = 0.1 * float(np.mean(h2))  # a linear variance may fall below zero off the fitted range: a tenth of the mean bounds it
        for k, (h, x_t, m_t, colour) in enumerate(samples):
            if colour == fitted_on:
                continue
            v0 = np.maximum(x_t @ null, least)
            v1 = np.maximum(x_t @ alternative[:-1] + alternative[-1] * m_t, least)
            gains[k] = -0.5 * float(np.sum(h**2 / v1 + np.log(v1)) - np.sum(h**2 / v0 + np.log(v0)))
    total, z = gain_and_z(gains, np.zeros_like(gains))
    # each hypothesis read on its filter: white noise on the finest, blurred noise on the band
    read_on = {sigma: (_FINE if sigma == 0 else _BAND) for sigma in kept}
    whiteness = {"tiles": [np.flatnonzero(colours == colour) for colour in (0, 1)], "read_on": read_on,
                 "expected": {sigma: kept[sigma][read_on[sigma]] / kept[sigma][0] for sigma in kept},
                 "normal": {key: np.stack(value) for key, value in normal.items()}, "moments": {key: np.stack(value) for key, value in moments.items()}}
    ratios = {sigma: per_filter[0] for sigma, per_filter in _slope_ratios(whiteness, np.ones((1, len(colours)))).items()}  # (filters, colours)
    noise_blur = min(kept, key=lambda sigma: _off(ratios[sigma][read_on[sigma]], whiteness["expected"][sigma]))
    white = bool(_off(ratios[noise_blur][read_on[noise_blur]], whiteness["expected"][noise_blur]) <= np.log(WHITE_RATIO))
    mean_slope, slope_error = mean_of_halves(slopes, slope_errors)
    slope = mean_slope / kept[noise_blur][0]
    if slope <= 0:
        total, z = min(total, 0.0), min(z, 0.0)  # a variance that falls with the light is no photon noise
    relative = slope_error / mean_slope if slope > 0 else np.nan  # log10(1/slope) moves by its relative error over ln 10
    per_white = kept[0.0][0] / kept[0.0]  # a ratio per unit of white noise's
    return {"gain": total, "z": z, "log10_photons": float(np.log10(1.0 / slope)) if slope > 0 else None,
            "log10_photons_err": float(relative / np.log(10.0)) if np.isfinite(relative) else None,
            "band_ratios": [float(r * per_white[_BAND]) for r in ratios[noise_blur][_BAND]],
            "fine_ratios": [float(r * per_white[_FINE]) for r in ratios[noise_blur][_FINE]], "noise_blur_px": noise_blur, "white": white,
            "tile_gains": gains, "whiteness": whiteness}


def _slope_ratios(whiteness: dict, weights: np.ndarray) -> dict[float, np.ndarray]:
    """Per noise hypothesis, each filter's slope over the high pass's, on each colour (draws, filters, colours), the tiles weighted by each row of ``weights``; NaN where the high pass's slope is not positive."""
    ratios = {}
    for sigma in whiteness["expected"]:
        per_colour = []
        for colour, tiles in enumerate(whiteness["tiles"]):
            w = weights[:, tiles]
            # (draws, filters): each filter's slope from the weighted tiles' normal equations
            system = np.einsum("dt,ftij->dfij", w, whiteness["normal"][(colour, sigma)])
            rhs = np.einsum("dt,fti->dfi", w, whiteness["moments"][(colour, sigma)])
            slope = np.linalg.solve(system, rhs[..., None])[..., -1, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                per_colour.append(np.where(slope[:, :1] > 0, slope / slope[:, :1], np.nan))
        ratios[sigma] = np.stack(per_colour, axis=-1)
    return ratios


def _off(ratios: np.ndarray, expected: float) -> np.ndarray:
    """How far the colours' ratios (last axis) lie from a hypothesis's ``expected`` ratio: the larger logged factor, infinite for a ratio that is not positive."""
    with np.errstate(divide="ignore", invalid="ignore"):
        distance = np.where(np.isfinite(ratios) & (ratios > 0), np.abs(np.log(ratios / expected)), np.inf)
    return np.max(distance, axis=-1)


def whiteness_draws(whiteness: dict, weights: np.ndarray) -> np.ndarray:
    """Whether photon noise's slope reads white (`shot_noise_test`'s ``white``) on each draw of the tiles' weights.

    ``whiteness``: the test's ``whiteness`` record (each tile's normal equations of the
    filters' slope regressions, per colour and noise hypothesis). ``weights``: (draws, tiles),
    each row the tiles' weights of one draw (`verdict_probability`). Each draw refits every
    slope on its weighted tiles, takes the hypothesis whose colours' ratios (on its own
    filter) lie nearer it, and reads white where both lie within ``WHITE_RATIO`` of it, as
    the test does on the tiles weighted alike.
    """
    ratios = _slope_ratios(whiteness, np.asarray(weights, dtype=np.float64))
    nearest = np.min(np.stack([_off(ratios[sigma][:, whiteness["read_on"][sigma]], expected) for sigma, expected in whiteness["expected"].items()]), axis=0)
    return nearest <= np.log(WHITE_RATIO)


def select_effects(data: np.ndarray, scene, split: TileSplit, *, candidates=tuple(MEAN_EFFECTS), level_z: float = 3.0,
                   max_effects: int = 3, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> Selection:
    """Forward selection over ``candidates`` by held-out gain (module docstring); the shot-noise test on the final model.

    ``scene``: a `Scene` (an array: no depth-dependent candidate). ``progress`` hears one step
    per model fitted, out of the most forward selection may fit, and again at least every
    half second within a fit; ``should_stop`` is heard within a fit (`Stopped`).
    """
    scene = Scene.of(scene)
    if scene.groups is None:
        candidates = tuple(c for c in candidates if c not in _BY_DEPTH)
    rounds = min(max_effects, len(candidates))
    steps = Steps(2 + sum(len(candidates) - k + 1 for k in range(rounds)), progress=progress, should_stop=should_stop, heartbeat_s=0.5)
    chosen: tuple[str, ...] = ()

    def polished(model: tuple[str, ...], fit: FrameFit) -> FrameFit:
        # a model the next round builds on is fitted again from its optimum: every model of that
        # round starts there and takes as many steps, so a gain is the effect's, not further
        # steps on the parameters they share (an unconverged envelope let any effect "gain")
        again = fit_frame(data, scene, split, model, starts=fit.params, check=steps.check)
        steps.advance()
        return again

    fits = {"baseline": polished((), fit_frame(data, scene, split, (), check=steps.check))}
    steps.advance()
    record = []
    while len(chosen) < max_effects:
        base = fits["+".join(chosen) or "baseline"]
        round_gains = {}
        for effect in candidates:
            if effect in chosen:
                continue
            model = tuple(sorted((*chosen, effect)))
            fit = fit_frame(data, scene, split, model, starts=base.params, check=steps.check)
            steps.advance()
            fits["+".join(model)] = fit
            round_gains[effect] = gain_and_z(fit.loglik, base.loglik)
        if not round_gains:
            break
        # the sign test saturates once every tile gains: among equal votes the larger gain leads
        best = max(round_gains, key=lambda e: (round_gains[e][1], round_gains[e][0]))
        record.append({"given": list(chosen), "gains": {e: {"gain_nats": g, "z": z} for e, (g, z) in round_gains.items()}, "added": None})
        if round_gains[best][1] < level_z or round_gains[best][0] <= 0:
            break
        chosen = tuple(sorted((*chosen, best)))
        fits["+".join(chosen)] = polished(chosen, fits["+".join(chosen)])
        record[-1]["added"] = best
    while len(chosen) >= 2:
        # backward: an effect added early may be one that a later one explains better (a source's
        # size blurs like a sensor, more at depth): each is judged again given all the others
        full = fits["+".join(chosen)]
        kept_gains = {}
        for effect in chosen:
            reduced = tuple(e for e in chosen if e != effect)
            key = "+".join(reduced)
            if key not in fits:
                fits[key] = fit_frame(data, scene, split, reduced, starts=full.params, check=steps.check)
            kept_gains[effect] = gain_and_z(full.loglik, fits[key].loglik)
        weakest = min(kept_gains, key=lambda e: kept_gains[e][1])
        record.append({"given": [e for e in chosen if e != weakest], "gains": {e: {"gain_nats": g, "z": z} for e, (g, z) in kept_gains.items()},
                       "removed": None})
        if kept_gains[weakest][1] >= level_z and kept_gains[weakest][0] > 0:
            break
        chosen = tuple(e for e in chosen if e != weakest)
        record[-1]["removed"] = weakest
    final = fits["+".join(chosen) or "baseline"]
    # each selected effect against every candidate that gained alone, in its place: one that
    # predicts the held-out tiles about as well is an alternative the frame cannot rule out
    alone = record[0]["gains"] if record else {}
    undecided = []
    for effect in chosen:
        for rival in candidates:
            if rival in chosen or alone.get(rival, {}).get("z", -np.inf) < level_z:
                continue
            swapped = tuple(sorted((*(e for e in chosen if e != effect), rival)))
            key = "+".join(swapped)
            if key not in fits:
                fits[key] = fit_frame(data, scene, split, swapped, starts=final.params, check=steps.check)
            gain, z = gain_and_z(final.loglik, fits[key].loglik)
            if z < DECIDED_Z:
                undecided.append({"selected": effect, "rival": rival, "gain_nats": gain, "z": z})
    probabilities = model_probabilities({name: fit.loglik for name, fit in fits.items()})
    steps.advance(steps.total - steps.done)
    return Selection(chosen, fits, record, probabilities, shot_noise_test(final, split), tuple(undecided))
