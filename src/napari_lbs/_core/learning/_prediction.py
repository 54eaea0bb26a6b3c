"""Prediction: a whole hologram → reconstruction planes → U-Net tile by tile → particles.

The whole hologram is back-propagated (so a tile keeps its true surroundings, which the seed's
per-tile back-propagation lost), cut into overlapping tiles of the size the model was trained
for, each tile-plane normalised as the training inputs were (``seed``: `experimental_planes`),
and the network's outputs stitched back with every pixel taken from the tile whose centre is
nearest. A particle on a tile edge is thus seen whole by a neighbouring tile. The stitched
output planes are decoded plane chunk by plane chunk — `PeakDecoder` then `suppress` for the
``focus`` formulation, whose input planes reach ``context`` planes beyond the requested depths;
`PlaneLinker` for the ``seed`` formulation — so memory stays bounded whatever the depth.

The ``focus`` formulation normalises each plane once, with the min and max of every
training-size tile interpolated bilinearly between the tile centres (`tile_normalisation`:
each pixel sees the statistics of the tiles around it, and no seam appears where tiles meet),
then runs its fully convolutional network on windows of at most ``window_px`` (default 640
pixels; `window_layout`) stitched nearest-centre like the tiles. Its stack is streamed: planes
are back-propagated a batch at a time and dropped once the last centre plane whose context
reaches them is through the network, so a 4096² hologram needs a few GB, not its whole stack.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from napari_lbs import __version__
from napari_lbs._core.calibration import experimental_planes
from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.learning._detection import PeakDecoder, PlaneLinker, suppress
from napari_lbs._core.learning._device_planes import backpropagated_planes
from napari_lbs._core.foundation import InputError, as_hologram
from napari_lbs._core.learning._network import LoadedModel, check_model_matches, inference_network, load_model, network_outputs, resolve_precision
from napari_lbs._core.physics import backpropagate, padded_shape
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback
from napari_lbs._core.foundation import check_memory, check_prediction_meta

__all__ = ["PredictionResult", "PredictionSettings", "check_threshold", "predict_particles", "prediction_settings", "tile_layout", "tile_normalisation", "window_layout"]

_PLANES_PER_CHUNK = 8
# Per pixel, one network call on one window of up to ~640² ran 1.2x cheaper than batches of
# 256² windows and 1.4x cheaper than a 1024² window on 2 CPU cores (the activations of a
# larger one leave the caches): ~544² windows cover a 1024² hologram with 1.13x its pixels
# where 256² windows with the same margins needed 1.56x.
_WINDOW_PX = 640


@dataclass(frozen=True)
class PredictionResult:
    """Particles (docs/formats.md table plus ``score`` and ``planes``) and how they were found.

    Attributes
    ----------
    particles : dict of arrays
        The particle table: ``x_um, y_um, z_um, diameter_um`` (µm), ``score`` and the model's
        own columns; a refined prediction's adds `refine_particles`' columns.
    provenance : dict
        Model, decoding, config, tiles and timings (the ``.json`` beside a written table).
    seconds : float
        Wall time of the call (s).
    """

    particles: dict[str, np.ndarray]
    provenance: dict
    seconds: float


@dataclass(frozen=True)
class PredictionSettings:
    """How `predict_particles` runs the network and decodes its output (also each frame of `predict_sequence`).

    Attributes
    ----------
    threshold : float, optional
        The smallest score a detection keeps; default the model's.
    device : {"auto", "cpu", "cuda"}
        Where the network runs.
    precision : {"auto", "float32", "bfloat16"}
        The network's arithmetic.
    force : bool
        Run a model made for other optics or depths anyway.
    margin_px : int
        Half the minimum overlap of neighbouring tiles (pixels).
    window_px : int, optional
        ``focus`` models: the largest edge of the windows the network runs on (pixels).

    Each is the `predict_particles` keyword of the same name, described there.
    """

    threshold: float | None = None
    device: str = "auto"
    precision: str = "auto"
    force: bool = False
    margin_px: int = 32
    window_px: int | None = None


def prediction_settings(settings: PredictionSettings | None, **keywords) -> PredictionSettings:
    """The `PredictionSettings` of a call: ``settings``, else one of the call's flat ``keywords`` (its field names).

    A call gives its options one way or the other: a keyword away from its default next to
    ``settings`` is refused.
    """
    if settings is None:
        return PredictionSettings(**keywords)
    if not isinstance(settings, PredictionSettings):
        raise InputError(f"settings: expected PredictionSettings, got {type(settings).__name__}")
    defaults = PredictionSettings()
    both = sorted(name for name, value in keywords.items() if value != getattr(defaults, name))
    if both:
        raise InputError(f"{', '.join(both)}: give the prediction's options either in settings or as keywords, not both")
    return settings


def tile_layout(length: int, *, size: int, margin: int) -> list[tuple[int, int, int]]:
    """Overlapping tiles along one axis: ``(start, keep_from, keep_to)`` in image pixels.

    Tiles of ``size`` overlap by at least ``2 * margin``; each keeps the pixels nearer its
    centre than any other tile's, so the kept parts partition ``[0, length)``.
    """
    if size > length:
        raise InputError(f"tile.size: a {size}-pixel tile is larger than the image ({length} pixels)")
    stride = max(size - 2 * margin, 1)
    starts = list(range(0, length - size, stride)) + [length - size]
    bounds = [0] + [(a + size + b) // 2 for a, b in zip(starts[:-1], starts[1:], strict=True)] + [length]
    return [(start, bounds[i], bounds[i + 1]) for i, start in enumerate(starts)]


def predict_particles(
    hologram: np.ndarray,
    model: LoadedModel | str | Path,
    config: ExperimentConfig | None = None,
    *,
    background: np.ndarray | None = None,
    planes_um: Sequence[float] | None = None,
    margin_px: int = 32,
    window_px: int | None = None,
    device: str = "auto",
    precision: str = "auto",
    force: bool = False,
    threshold: float | None = None,
    settings: PredictionSettings | None = None,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> PredictionResult:
    """Reconstruct the particle field of one hologram (the `napari-lbs predict` step).

    Parameters
    ----------
    hologram : (rows, cols) array
        Intensity hologram (at least one tile in each direction).
    model : LoadedModel or path
        A model file from `train_model`.
    config : ExperimentConfig, optional
        Optics and reconstruction depths; default the model's own. A config whose tile size
        differs from the model's is refused; so is one whose optics differ or whose depths
        leave the model's training range (`model_mismatches`), unless ``force``.
    background : (rows, cols) array, optional
        Hologram without particles (divided out before back-propagation).
    planes_um : sequence of float, optional
        Reconstruction depths (µm); default ``config.volume.planes_um()``.
    margin_px : int
        Half the minimum overlap of neighbouring tiles (pixels), at most a quarter tile.
    window_px : int, optional
        ``focus`` models: the largest edge of the windows the network runs on (pixels; at
        least the tile size; default 640). Each axis is covered by the fewest windows of at
        most about this edge overlapping by ``2 * margin_px`` (`window_layout`); a pixel is
        taken from the window whose centre is nearest. The network is fully convolutional and
        the planes are normalised over the whole image first, so windows only change the zero
        padding the network sees near their edges, which the margins keep away from the kept
        pixels. On 2 CPU cores, windows of 512-640 pixels cost the least per image (fewer
        overlaps than tile-size windows, activations that still fit the caches).
    device : {"auto", "cpu", "cuda"}
    precision : {"auto", "float32", "bfloat16"}
        The network's arithmetic (`resolve_precision`; recorded in the provenance).
    force : bool
        Run a model made for other optics or depths anyway (the config's optics are used).
    threshold : float, optional
        The smallest score a detection keeps (``focus``: the peak probability; ``seed``: the
        output value); default the model's, the one that scored best on its validation data.
        A lower one finds more particles and more false ones: a table that a fit then checks
        (`refine_particles`) can afford it.
    settings : PredictionSettings, optional
        ``margin_px``, ``window_px``, ``device``, ``precision``, ``force`` and ``threshold``
        in one object, instead of the keywords (a call gives one or the other).
    progress, should_stop
        One step per reconstruction plane (``focus``: also one per back-propagated plane,
        context included, first); a stop raises `Stopped`.
    """
    start_time = time.perf_counter()
    settings = prediction_settings(settings, margin_px=margin_px, window_px=window_px, device=device, precision=precision, force=force, threshold=threshold)
    margin_px, window_px, device, precision, force, threshold = (settings.margin_px, settings.window_px, settings.device, settings.precision, settings.force,
                                                                 settings.threshold)
    hologram = as_hologram(hologram)
    if background is not None:
        background = as_hologram(background, name="background")
        if background.shape != hologram.shape:
            raise InputError(f"background: expected the hologram's shape {hologram.shape}, got {background.shape}")
    loaded = model if isinstance(model, LoadedModel) else load_model(model, device=device)
    meta = loaded.meta
    check_prediction_meta(meta, name=str(loaded.path or "model"))
    threshold = check_threshold(meta["threshold"] if threshold is None else threshold, loaded)
    loaded = replace(loaded, network=inference_network(loaded.network))  # the caller's model stays as it is
    loaded.network.precision = resolve_precision(precision, next(loaded.network.parameters()).device)
    config = config if config is not None else loaded.config
    planes = [float(z) for z in (planes_um if planes_um is not None else config.volume.planes_um())]
    if not planes or not all(math.isfinite(z) and z > 0 for z in planes):
        raise InputError(f"planes_um: expected a non-empty list of positive depths (µm), got {list(planes_um) if planes_um is not None else planes!r}")
    check_model_matches(meta, config, planes_um=planes, force=force)
    optics = {"wavelength_um": config.optics.wavelength_um, "pixel_um": config.optics.pixel_um, "medium_index": config.optics.medium_index}
    check_memory(_prediction_bytes(hologram.shape, planes, loaded, optics), what=f"predicting a {hologram.shape[0]}x{hologram.shape[1]} hologram ({len(planes)} planes)",
                 remedy="crop the hologram or predict it in parts")
    size = int(meta["tile_size"])
    margin_px = min(int(margin_px), size // 4)
    layout = (tile_layout(hologram.shape[0], size=size, margin=margin_px), tile_layout(hologram.shape[1], size=size, margin=margin_px))
    steps = Steps(len(planes), progress=progress, should_stop=should_stop)
    if loaded.formulation == "focus":
        window_px = _WINDOW_PX if window_px is None else int(window_px)
        if window_px < size:
            raise InputError(f"window_px: expected at least the model's tile size {size}, got {window_px}")
        particles, details = _decode_focus(hologram, loaded, planes, layout, background=background, optics=optics, steps=steps, margin_px=margin_px, window_px=window_px,
                                           threshold=threshold)
    else:
        particles, details = _decode_seed(hologram, loaded, planes, layout, background=background, optics=optics, steps=steps, threshold=threshold)
    rows, cols = layout
    seconds = time.perf_counter() - start_time
    provenance = {
        "napari_lbs": __version__,
        "model": str(loaded.path) if loaded.path else None,
        "model_sha256": loaded.sha256,
        "weights_sha256": loaded.weights_sha256,
        "model_preset": meta["preset"],
        "model_epoch": meta.get("epoch"),
        "formulation": loaded.formulation,
        "precision": loaded.network.precision,
        "threshold": threshold,
        "model_threshold": meta["threshold"],
        **details,
        "processing": meta["processing"],
        "config": config.to_dict(),
        "planes_um": [planes[0], planes[-1], len(planes)],
        "tiles": [len(rows), len(cols), size, margin_px],
        "background": background is not None,
        "seconds": round(seconds, 3),
    }
    return PredictionResult(particles, provenance, seconds)


def check_threshold(value, loaded: LoadedModel) -> float:
    """``value`` as a detection threshold: a probability in (0, 1) for ``focus`` models, an output in (0, the largest output] for ``seed`` ones."""
    try:
        threshold = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"threshold: expected a number, got {value!r}") from None
    if loaded.formulation == "focus":
        if not 0.0 < threshold < 1.0:  # NaN fails too
            raise InputError(f"threshold: expected a positive score below 1 (a peak probability, in (0, 1)), got {threshold:g}")
    elif not 0.0 < threshold <= float(loaded.meta["output_scale"]):
        raise InputError(f"threshold: expected a positive score of at most {float(loaded.meta['output_scale']):g} (the model's largest output), got {threshold:g}")
    return threshold


def _prediction_bytes(shape: tuple[int, int], planes: list[float], loaded: LoadedModel, optics: dict) -> float:
    """Peak memory (bytes) `predict_particles` needs for a hologram of ``shape``, an estimate with a margin.

    Both formulations hold one batch of padded planes (`backpropagated_blocks`: 512 MiB, or
    one plane with the FFT's workspace when a plane is larger) beside full-size float32
    planes: ``focus`` the context's planes, the three maps and the decoder's window of them;
    ``seed`` a chunk of planes with its tiles, inputs, outputs and stitched planes.
    """
    rows, cols = shape
    padded = padded_shape(shape, z_max_um=max(planes), **optics)
    batch = max(512 * 2**20, 3 * 8 * padded[0] * padded[1])
    if loaded.formulation == "focus":
        reach = max(abs(int(o)) for o in loaded.meta.get("context", [0]))
        planes_held = (2 * reach + 2) + 3 + 9  # context planes, maps, decoder window
    else:
        planes_held = 5 * min(_PLANES_PER_CHUNK, len(planes)) + 2
    return batch + 4.0 * rows * cols * (planes_held + 4)  # + the hologram and its normalised copy


def _stitched(outputs: np.ndarray, layout, shape: tuple[int, int]) -> np.ndarray:
    """One image from per-tile outputs ``(tiles, ...)``: each pixel from the tile whose centre is nearest."""
    rows, cols = layout
    plane = np.empty(outputs.shape[1:-2] + shape, np.float32)
    index = 0
    for r, r_from, r_to in rows:
        for c, c_from, c_to in cols:
            plane[..., r_from:r_to, c_from:c_to] = outputs[index, ..., r_from - r : r_to - r, c_from - c : c_to - c]
            index += 1
    return plane


def _tiles(stack: np.ndarray, layout, size: int) -> list[np.ndarray]:
    rows, cols = layout
    return [stack[:, r : r + size, c : c + size] for r, _, _ in rows for c, _, _ in cols]


def _interpolation_matrix(length: int, layout: list[tuple[int, int, int]], size: int) -> np.ndarray:
    """``(length, tiles)`` weights interpolating values at the tiles' centres linearly, constant beyond the outer ones."""
    centres = np.array([start + (size - 1) / 2 for start, _, _ in layout])
    position = np.interp(np.arange(length), centres, np.arange(len(centres), dtype=np.float64))
    lower = np.minimum(position.astype(int), len(centres) - 1)
    upper = np.minimum(lower + 1, len(centres) - 1)
    weights = np.zeros((length, len(centres)), np.float32)
    np.add.at(weights, (np.arange(length), lower), 1.0 - (position - lower))
    np.add.at(weights, (np.arange(length), upper), position - lower)
    return weights


def tile_normalisation(stack: np.ndarray, layout, size: int, *, invert: bool, mode: str) -> None:
    """Normalise raw planes in place as `experimental_planes` normalises a tile, with per-tile statistics interpolated.

    Each plane's min and max over every ``size`` tile of ``layout`` (`tile_layout` along rows
    and columns) are interpolated bilinearly between the tile centres; the plane is stretched
    to [0, 1] with them (clipped), floored to 8-bit steps in ``seed`` mode and inverted with
    ``invert``. At a tile's centre this is that tile's own normalisation (exactly where the
    centre falls on a pixel, for odd tile sizes; between pixels otherwise).

    Parameters
    ----------
    stack : (planes, rows, cols) float32 array
        Raw reconstruction magnitudes; overwritten.
    layout : (rows layout, cols layout)
        `tile_layout` of each axis for tiles of ``size``.
    """
    normalise = _TileNormaliser(stack.shape[1:], layout, size, invert=invert, mode=mode)
    for plane in stack:
        normalise(plane)


class _TileNormaliser:
    """`tile_normalisation` of one plane at a time (the interpolation weights computed once)."""

    def __init__(self, shape: tuple[int, int], layout, size: int, *, invert: bool, mode: str) -> None:
        self.rows, self.cols = layout
        self.size, self.invert, self.mode = size, invert, mode
        self.along_rows, self.along_cols = _interpolation_matrix(shape[0], self.rows, size), _interpolation_matrix(shape[1], self.cols, size)

    def __call__(self, plane: np.ndarray) -> None:
        size = self.size
        # each tile's extremes read in place: stacking the tiles first copied every plane
        # 1.5 times (4096² planes: 115 MB each) for the same values
        low = np.empty((len(self.rows), len(self.cols)), plane.dtype)
        high = np.empty_like(low)
        for i, (r, _, _) in enumerate(self.rows):
            for j, (c, _, _) in enumerate(self.cols):
                tile = plane[r : r + size, c : c + size]
                low[i, j], high[i, j] = tile.min(), tile.max()
        low_map = self.along_rows @ low @ self.along_cols.T
        span_map = self.along_rows @ (high - low) @ self.along_cols.T
        plane -= low_map
        plane /= np.where(span_map > 0, span_map, 1.0)
        np.clip(plane, 0.0, 1.0, out=plane)
        if self.mode == "seed":
            np.floor(plane * 255.0, out=plane)
            plane /= 255.0
        if self.invert:
            np.subtract(1.0, plane, out=plane)


def _decode_seed(hologram, loaded: LoadedModel, planes, layout, *, background, optics, steps, threshold: float) -> tuple[dict, dict]:
    """The seed formulation: each plane's tiles through the network, `PlaneLinker` through depth."""
    meta = loaded.meta
    size = int(meta["tile_size"])
    invert, mode = bool(meta["processing"]["invert_experiment"]), meta["processing"]["mode"]
    linker = PlaneLinker(planes, pixel_um=optics["pixel_um"], threshold=threshold, full_value=float(meta["full_value"]), merge_lateral_um=float(meta.get("merge_lateral_um", 0.0)))
    for first in range(0, len(planes), _PLANES_PER_CHUNK):
        steps.check()
        chunk = planes[first : first + _PLANES_PER_CHUNK]
        magnitudes = backpropagate(hologram, chunk, background=background, **optics)
        tiles = np.stack(_tiles(magnitudes, layout, size), axis=0)
        inputs = experimental_planes(tiles.reshape(-1, size, size), invert=invert, mode=mode)
        outputs = network_outputs(loaded.network, inputs, output_scale=float(meta["output_scale"])).reshape(tiles.shape)
        stitched = _stitched(outputs, layout, hologram.shape)
        for offset in range(len(chunk)):
            linker.add(first + offset, stitched[offset])
        steps.advance(len(chunk))
    return linker.particles(), {}


def window_layout(length: int, *, most: int, margin: int) -> list[tuple[int, int, int, int]]:
    """The fewest windows of at most about ``most`` pixels covering one axis, overlapping by at least ``2 * margin``.

    Returns ``(start, stop, keep_from, keep_to)`` per window, in image pixels: each keeps the
    pixels nearer its centre than any other window's, so the kept parts partition
    ``[0, length)``. Every window starts at a multiple of 16 (the network's pooling factor)
    and all but the last have one edge, a multiple of 16, so the network pools each window
    on the same grid as the whole image and pads (by edge replication) only at the image's
    far edge, as it does the whole image; the last window ends there. A ``most`` of at least
    ``length`` is one window, the whole axis.
    """
    if length <= most:
        return [(0, length, 0, length)]
    overlap = 2 * margin
    count = -(-(length - overlap) // max(most - overlap, 1))
    share = -(-(length + overlap * (count - 1)) // count)  # ceil: the edge that many windows need
    edge = -(-share // 16) * 16
    stride = max(16, (edge - overlap) // 16 * 16)
    starts = [0]
    while starts[-1] + edge < length:
        starts.append(starts[-1] + stride)
    stops = [min(start + edge, length) for start in starts]
    bounds = [0] + [(b + stop) // 2 for stop, b in zip(stops[:-1], starts[1:], strict=True)] + [length]
    return [(start, stop, bounds[i], bounds[i + 1]) for i, (start, stop) in enumerate(zip(starts, stops, strict=True))]


def _decode_focus(hologram, loaded: LoadedModel, planes, layout, *, background, optics, steps, margin_px: int, window_px: int, threshold: float) -> tuple[dict, dict]:
    """The focus formulation: context planes in, 3-D peaks of the centre probability, one particle per peak.

    The stack is streamed: planes are back-propagated batch by batch (`backpropagated_planes`:
    on a CUDA device with ``torch.fft``, else numpy)
    and normalised as they come, each centre plane goes through the network window by window
    as soon as its context is there, and its maps go straight to the `PeakDecoder`; a plane is
    dropped once no later centre needs it. Memory is thus the context's planes plus one batch,
    not the whole stack: a 4096² hologram to 77 planes held 5 GB of stack before.
    """
    meta = loaded.meta
    size, step = int(meta["tile_size"]), float(meta["step_um"])
    context = [int(o) for o in meta["context"]]
    reach = max(abs(o) for o in context)
    if len(planes) > 1 and not np.allclose(np.diff(planes), step, rtol=1e-6, atol=1e-6):
        raise InputError(f"volume.z_step_um: the model was trained on planes {step:g} µm apart; reconstruct at that step")
    invert, mode = bool(meta["processing"]["invert_experiment"]), meta["processing"]["mode"]
    extended = [planes[0] + i * step for i in range(-reach, 0)] + list(planes) + [planes[-1] + i * step for i in range(1, reach + 1)]
    if extended[0] <= 0:
        raise InputError(f"volume.z_min_um: the model's context needs planes {reach * step:g} µm nearer the sensor than {planes[0]:g} µm")
    # the back-propagation reports and stops too: one step per back-propagated plane, context included
    steps.total += len(extended)
    normalise = _TileNormaliser(hologram.shape, layout, size, invert=invert, mode=mode)
    windows = (window_layout(hologram.shape[0], most=window_px, margin=margin_px), window_layout(hologram.shape[1], most=window_px, margin=margin_px))
    window_size = (windows[0][0][1], windows[1][0][1])  # the first window is the largest
    network = loaded.network.eval()
    device = next(network.parameters()).device
    diameter_scale_um = float(meta["diameter_scale_um"])
    decoder = PeakDecoder(planes, pixel_um=optics["pixel_um"], step_um=step)
    blocks = backpropagated_planes(hologram, extended, background=background, device=device, steps=steps, **optics)
    held: dict[int, np.ndarray] = {}  # normalised planes by index in ``extended``
    buffer = np.empty((1, *window_size, len(context)), np.float32)  # one window, channels last
    with torch.inference_mode():
        for centre in range(len(planes)):
            while centre + 2 * reach not in held:
                start, stop, block = next(blocks)
                for j in range(stop - start):
                    plane = block[j]
                    normalise(plane)
                    held[start + j] = plane
            for gone in [k for k in held if k < centre]:
                del held[gone]
            steps.check()
            channels = [held[centre + reach + o] for o in context]
            maps = np.empty((3, *hologram.shape), np.float32)  # probability, depth offset, diameter (µm)
            for r, r_stop, r_from, r_to in windows[0]:
                for c, c_stop, c_from, c_to in windows[1]:
                    shape = (r_stop - r, c_stop - c)
                    inputs = buffer if shape == window_size else np.empty((1, *shape, len(context)), np.float32)
                    for k, plane in enumerate(channels):
                        inputs[0, :, :, k] = plane[r:r_stop, c:c_stop]
                    # a channels-last NCHW view of the buffer: the layout the network runs fastest in
                    outputs = network(torch.from_numpy(inputs).to(device).permute(0, 3, 1, 2)).float()[0, :, r_from - r : r_to - r, c_from - c : c_to - c]
                    maps[0, r_from:r_to, c_from:c_to] = torch.sigmoid(outputs[0]).cpu().numpy()
                    maps[1, r_from:r_to, c_from:c_to] = outputs[1].cpu().numpy()
                    maps[2, r_from:r_to, c_from:c_to] = (torch.nn.functional.softplus(outputs[2]) * diameter_scale_um).cpu().numpy()
            decoder.add(centre, *maps)
            steps.advance(1)
    for _ in blocks:  # none is left: resuming lets the last batch report its progress
        pass
    axial_um = meta.get("axial_um")
    particles = suppress(decoder.candidates(), threshold=threshold, lateral_um=float(meta["lateral_um"]), axial_um=float(axial_um) if axial_um is not None else np.inf)
    return particles, {"axial_um": axial_um, "lateral_um": meta["lateral_um"], "context": context, "step_um": step, "windows": [len(windows[0]), len(windows[1]), *window_size]}
