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
then runs its fully convolutional network on windows of ``window_px`` (default the tile size)
stitched nearest-centre like the tiles.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from napari_lbs import __version__
from napari_lbs._core._calibration import experimental_planes
from napari_lbs._core._config import ExperimentConfig
from napari_lbs._core._detection import PeakDecoder, PlaneLinker, suppress
from napari_lbs._core._io import InputError, as_hologram
from napari_lbs._core._network import LoadedModel, check_model_matches, focus_maps, inference_network, load_model, network_outputs
from napari_lbs._core._optics import backpropagate
from napari_lbs._core._progress import ProgressCallback, Steps, StopCallback
from napari_lbs._core._validation import check_prediction_meta

__all__ = ["PredictionResult", "predict_particles", "tile_layout", "tile_normalisation"]

_PLANES_PER_CHUNK = 8
_WINDOW_PIXELS_PER_BATCH = 8 * 256 * 256  # input planes per network call, in pixels: bounds activation memory


@dataclass
class PredictionResult:
    """Particles (CONTRACT.md table plus ``score`` and ``planes``) and how they were found."""

    particles: dict[str, np.ndarray]
    provenance: dict
    seconds: float


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
    force: bool = False,
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
        ``focus`` models: edge of the windows the network runs on (pixels; at least the tile
        size; default the tile size). Larger windows cost fewer pixels (one 1024² window is
        1/1.56 of 256² tiles with 32-pixel margins) but on 2 CPU cores ran slower (33.4 s vs
        30.4 s for the real 1024² hologram: a small window's activations stay in cache); they
        may pay off on a GPU (not measured).
    device : {"auto", "cpu", "cuda"}
    force : bool
        Run a model made for other optics or depths anyway (the config's optics are used).
    progress, should_stop
        One step per reconstruction plane (``focus``: also one per back-propagated plane,
        context included, first); a stop raises `Stopped`.
    """
    start_time = time.perf_counter()
    hologram = as_hologram(hologram)
    if background is not None:
        background = as_hologram(background, name="background")
        if background.shape != hologram.shape:
            raise InputError(f"background: expected the hologram's shape {hologram.shape}, got {background.shape}")
    loaded = model if isinstance(model, LoadedModel) else load_model(model, device=device)
    meta = loaded.meta
    check_prediction_meta(meta, name=str(loaded.path or "model"))
    loaded = replace(loaded, network=inference_network(loaded.network))  # the caller's model stays as it is
    config = config if config is not None else loaded.config
    planes = [float(z) for z in (planes_um if planes_um is not None else config.volume.planes_um())]
    check_model_matches(meta, config, planes_um=planes, force=force)
    size = int(meta["tile_size"])
    margin_px = min(int(margin_px), size // 4)
    layout = (tile_layout(hologram.shape[0], size=size, margin=margin_px), tile_layout(hologram.shape[1], size=size, margin=margin_px))
    optics = {"wavelength_um": config.optics.wavelength_um, "pixel_um": config.optics.pixel_um, "medium_index": config.optics.medium_index}
    steps = Steps(len(planes), progress=progress, should_stop=should_stop)
    if loaded.formulation == "focus":
        window_px = size if window_px is None else int(window_px)
        if window_px < size:
            raise InputError(f"window_px: expected at least the model's tile size {size}, got {window_px}")
        particles, details = _decode_focus(hologram, loaded, planes, layout, background=background, optics=optics, steps=steps, margin_px=margin_px, window_px=window_px)
    else:
        particles, details = _decode_seed(hologram, loaded, planes, layout, background=background, optics=optics, steps=steps)
    rows, cols = layout
    seconds = time.perf_counter() - start_time
    provenance = {
        "napari_lbs": __version__,
        "model": str(loaded.path) if loaded.path else None,
        "model_sha256": loaded.sha256,
        "model_preset": meta["preset"],
        "model_epoch": meta.get("epoch"),
        "formulation": loaded.formulation,
        "threshold": meta["threshold"],
        **details,
        "processing": meta["processing"],
        "config": config.to_dict(),
        "planes_um": [planes[0], planes[-1], len(planes)],
        "tiles": [len(rows), len(cols), size, margin_px],
        "background": background is not None,
        "seconds": round(seconds, 3),
    }
    return PredictionResult(particles, provenance, seconds)


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
    rows, cols = layout
    along_rows, along_cols = _interpolation_matrix(stack.shape[1], rows, size), _interpolation_matrix(stack.shape[2], cols, size)
    for plane in stack:
        tiles = np.stack([plane[r : r + size, c : c + size] for r, _, _ in rows for c, _, _ in cols])
        low = tiles.min(axis=(1, 2)).reshape(len(rows), len(cols))
        high = tiles.max(axis=(1, 2)).reshape(len(rows), len(cols))
        low_map = along_rows @ low @ along_cols.T
        span_map = along_rows @ (high - low) @ along_cols.T
        plane -= low_map
        plane /= np.where(span_map > 0, span_map, 1.0)
        np.clip(plane, 0.0, 1.0, out=plane)
        if mode == "seed":
            np.floor(plane * 255.0, out=plane)
            plane /= 255.0
        if invert:
            np.subtract(1.0, plane, out=plane)


def _decode_seed(hologram, loaded: LoadedModel, planes, layout, *, background, optics, steps) -> tuple[dict, dict]:
    """The seed formulation: each plane's tiles through the network, `PlaneLinker` through depth."""
    meta = loaded.meta
    size = int(meta["tile_size"])
    invert, mode = bool(meta["processing"]["invert_experiment"]), meta["processing"]["mode"]
    linker = PlaneLinker(planes, pixel_um=optics["pixel_um"], threshold=float(meta["threshold"]), full_value=float(meta["full_value"]), merge_lateral_um=float(meta.get("merge_lateral_um", 0.0)))
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


def _decode_focus(hologram, loaded: LoadedModel, planes, layout, *, background, optics, steps, margin_px: int, window_px: int) -> tuple[dict, dict]:
    """The focus formulation: context planes in, 3-D peaks of the centre probability, one particle per peak."""
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
    # the back-propagation reports and stops too: on a 1024² hologram it is the first few seconds
    steps.total += len(extended)
    reported = 0

    def backpropagated(done: int, total: int) -> None:
        nonlocal reported
        steps.advance(done - reported)
        reported = done

    stack = backpropagate(hologram, extended, background=background, progress=backpropagated, should_stop=steps.stop_requested, **optics).astype(np.float32, copy=False)
    tile_normalisation(stack, layout, size, invert=invert, mode=mode)
    window_size = (min(window_px, hologram.shape[0]), min(window_px, hologram.shape[1]))
    window_rows = tile_layout(hologram.shape[0], size=window_size[0], margin=margin_px)
    window_cols = tile_layout(hologram.shape[1], size=window_size[1], margin=margin_px)
    windows = (window_rows, window_cols)
    batch_size = max(1, _WINDOW_PIXELS_PER_BATCH // (window_size[0] * window_size[1]))
    decoder = PeakDecoder(planes, pixel_um=optics["pixel_um"], step_um=step)
    for first in range(0, len(planes), _PLANES_PER_CHUNK):
        steps.check()
        centres = list(range(first, min(first + _PLANES_PER_CHUNK, len(planes))))
        low, high = centres[0], centres[-1] + 2 * reach + 1  # extended-stack planes this chunk needs
        outputs = []
        for r, _, _ in window_rows:
            for c, _, _ in window_cols:
                steps.check()
                window = stack[low:high, r : r + window_size[0], c : c + window_size[1]]
                maps = focus_maps(loaded.network, window, [k - first + reach for k in centres], context=context, diameter_scale_um=float(meta["diameter_scale_um"]), batch_size=batch_size)
                outputs.append(np.stack([np.stack(m[1:]) for m in maps]))  # (centres, 3, window rows, window cols)
        stitched = outputs[0] if len(outputs) == 1 else _stitched(np.stack(outputs), windows, hologram.shape)
        for k, centre in enumerate(centres):
            decoder.add(centre, *stitched[k])
        steps.advance(len(centres))
    axial_um = meta.get("axial_um")
    particles = suppress(decoder.candidates(), threshold=float(meta["threshold"]), lateral_um=float(meta["lateral_um"]), axial_um=float(axial_um) if axial_um is not None else np.inf)
    return particles, {"axial_um": axial_um, "lateral_um": meta["lateral_um"], "context": context, "step_um": step, "windows": [len(window_rows), len(window_cols), *window_size]}
