"""The refinement's inputs checked, and the hologram patches it fits.

**Patch**: a square of at most ``patch_px`` pixels, and no wider than the disc inside which
the fringes are sampled (their frequency below the pixel's Nyquist limit, `patch_edge`).
The patches of a batch are flattened and padded to one length (`Patches`); the fit runs
most iterations on every other pixel (`every_other_pixel`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from napari_lbs._core.foundation import PARTICLE_COLUMNS, InputError
from napari_lbs._core.refine._settings import BOUNDS, FIT_PARAMETERS, RefineSettings, check_bounded


@dataclass
class Patches:
    """Hologram patches of a batch of particles, flattened and padded to one length."""

    data: torch.Tensor  # (B, P) intensities
    mask: torch.Tensor  # (B, P) 1 where a real pixel
    x_um: torch.Tensor  # (B, P) pixel positions
    y_um: torch.Tensor
    u: torch.Tensor  # (B, P) patch coordinates in -1 … 1
    v: torch.Tensor
    shape: list[tuple[int, int]]  # each patch's (rows, cols)


def check_hologram(hologram) -> np.ndarray:
    image = np.asarray(hologram)
    if image.ndim != 2:
        raise InputError(f"hologram: expected a 2-D image, got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.number):
        raise InputError(f"hologram: expected numbers, got dtype {image.dtype}")
    image = image.astype(np.float64)
    if not np.all(np.isfinite(image)):
        raise InputError("hologram: contains NaN or infinite values")
    if not np.any(image > 0):
        raise InputError("hologram: no positive intensity (all zero?); expected a hologram normalised by its background")
    return image


def check_valid(valid, shape: tuple[int, int]) -> np.ndarray | None:
    """``valid`` as a (rows, cols) bool array of the hologram's ``shape``, or None (every pixel); refused in one line when it is not one, or leaves no pixel."""
    if valid is None:
        return None
    mask = np.asarray(valid)
    if mask.shape != tuple(shape) or mask.dtype != bool:
        raise InputError(f"valid: expected a bool array of the hologram's shape {tuple(shape)}, got {mask.dtype} of shape {mask.shape}")
    if not mask.any():
        raise InputError("valid: no pixel left to fit")
    return mask


# A camera's clipped focal spot shows as a plateau at the frame's maximum; a measured frame's
# maximum is otherwise reached by a pixel or two.
SATURATED_PIXELS = 5


def unsaturated_pixels(hologram) -> np.ndarray | None:
    """The pixels below the frame's maximum where `SATURATED_PIXELS` or more reach it (a saturated camera's plateau), else None (every pixel valid).

    For `refine_particles`' ``valid``, given the raw frame (a background division spreads
    the clipped values).
    """
    image = np.asarray(hologram)
    top = image.max()
    at_top = image >= top
    return ~at_top if int(np.count_nonzero(at_top)) >= SATURATED_PIXELS else None


def check_table(table):
    import pandas as pd

    frame = pd.DataFrame(table).reset_index(drop=True)
    missing = [c for c in PARTICLE_COLUMNS if c not in frame.columns]
    if missing:
        raise InputError(f"particle table: missing column {missing[0]}")
    for name in PARTICLE_COLUMNS:
        values = pd.to_numeric(frame[name], errors="coerce").to_numpy(dtype=np.float64)
        if not np.all(np.isfinite(values)):
            raise InputError(f"particle table: column {name} holds NaN, infinite or non-numeric values")
        frame[name] = values
    if np.any(frame["z_um"] <= 0):
        raise InputError("particle table: column z_um must be positive (distance to the sensor)")
    if np.any(frame["diameter_um"] <= 0):
        raise InputError("particle table: column diameter_um must be positive")
    return frame


def check_fixed(fixed: Mapping[str, float] | None) -> dict[str, float]:
    fixed = dict(fixed or {})
    for name, value in fixed.items():
        if name not in FIT_PARAMETERS:
            raise InputError(f"fixed: unknown parameter {name!r} (expected one of {', '.join(FIT_PARAMETERS)})")
        if not (isinstance(value, int | float) and math.isfinite(value)):
            raise InputError(f"fixed: {name} must be a finite number, got {value!r}")
        if name in BOUNDS:
            check_bounded(f"fixed: {name}", name, value)
    return fixed


def samples_every_angle(*, wavelength_um: float, medium_index: float, pixel_um: float) -> bool:
    """Whether a pitch of ``pixel_um`` samples every propagating fringe: at most half the medium wavelength ``λ/(2n)`` (µm).

    Then a sphere's fringes are cut by no Nyquist disc: they reach grazing angles, over the
    whole frame, fading only as the scattered wave spreads (a microscope's pitch at the
    sample, binned or not). A lensless sensor's pitch (2.2 µm at 660 nm) is coarser.
    """
    return pixel_um <= wavelength_um / (2.0 * medium_index)


def patch_edge(z_um: float, *, settings: RefineSettings, wavelength_um: float, pixel_um: float) -> int:
    """Patch edge (px): the disc of fringes below the Nyquist frequency, at most ``patch_px``.

    At a pitch of ``λ/(2n)`` or finer (a microscope's, binned or not) every propagating
    fringe is sampled, the disc reaches grazing angles, and the edge is ``patch_px``.
    """
    sin_nyquist = min(wavelength_um / settings.medium_index / (2.0 * pixel_um), 0.99)
    radius_px = z_um * sin_nyquist / math.sqrt(1.0 - sin_nyquist**2) / pixel_um
    return int(max(16, min(settings.patch_px, 2 * round(radius_px))))


def cut_patches(image: np.ndarray, x_um: np.ndarray, y_um: np.ndarray, edges: np.ndarray, *, pixel_um: float, device, valid: np.ndarray | None = None) -> Patches:
    """Each particle's square patch of ``image`` about its centre, cut at the frame's edges, as flat rows padded to the longest.

    ``valid``: (rows, cols) bool, the pixels the fits compare; the others (a saturated
    camera's clipped pixels) are in the patches with mask 0, as the padding is.
    """
    rows, cols = image.shape
    length = int(max(edges)) ** 2
    count = len(x_um)
    data = np.ones((count, length))
    mask = np.zeros((count, length))
    xs = np.zeros((count, length))
    ys = np.zeros((count, length))
    us = np.zeros((count, length))
    vs = np.zeros((count, length))
    shapes = []
    for i, (x, y, edge) in enumerate(zip(x_um, y_um, edges, strict=True)):
        half = edge // 2
        c0, r0 = round(x / pixel_um) - half, round(y / pixel_um) - half
        r_lo, r_hi = max(r0, 0), min(r0 + edge, rows)
        c_lo, c_hi = max(c0, 0), min(c0 + edge, cols)
        if r_lo >= r_hi or c_lo >= c_hi:
            shapes.append((0, 0))
            continue
        block = image[r_lo:r_hi, c_lo:c_hi]
        rr, cc = np.mgrid[r_lo:r_hi, c_lo:c_hi]
        n = block.size
        data[i, :n] = block.ravel()
        mask[i, :n] = 1.0 if valid is None else valid[r_lo:r_hi, c_lo:c_hi].ravel()
        # padding sits on the patch's first pixel: the models' radial range stays the patch's
        xs[i] = cc.ravel()[0] * pixel_um
        ys[i] = rr.ravel()[0] * pixel_um
        xs[i, :n] = cc.ravel() * pixel_um
        ys[i, :n] = rr.ravel() * pixel_um
        us[i, :n] = (cc.ravel() - (c0 + half)) / max(half, 1)
        vs[i, :n] = (rr.ravel() - (r0 + half)) / max(half, 1)
        shapes.append(block.shape)
    as_tensor = lambda a: torch.as_tensor(a, dtype=torch.float64, device=device)
    return Patches(as_tensor(data), as_tensor(mask), as_tensor(xs), as_tensor(ys), as_tensor(us), as_tensor(vs), shapes)


def every_other_pixel(patches: Patches) -> tuple[Patches, torch.Tensor]:
    """The patches' every other row and column (padded as `cut_patches` pads) and their indices (B, P') in ``patches``' pixels."""
    length = max((-(-rows // 2)) * (-(-cols // 2)) for rows, cols in patches.shape) if patches.shape else 0
    count = len(patches.shape)
    index = torch.zeros((count, max(length, 1)), dtype=torch.long, device=patches.data.device)
    real = torch.zeros(index.shape, dtype=torch.bool, device=patches.data.device)
    shapes = []
    for i, (rows, cols) in enumerate(patches.shape):
        picked = (torch.arange(0, rows, 2, device=index.device)[:, None] * cols + torch.arange(0, cols, 2, device=index.device)).reshape(-1)
        index[i, : picked.numel()] = picked
        real[i, : picked.numel()] = True
        shapes.append((-(-rows // 2), -(-cols // 2)))
    take = lambda t, padding: torch.where(real, torch.gather(t, 1, index), torch.full_like(index, padding, dtype=t.dtype))
    coarse = Patches(take(patches.data, 1.0), take(patches.mask, 0.0), torch.gather(patches.x_um, 1, index), torch.gather(patches.y_um, 1, index),
                      take(patches.u, 0.0), take(patches.v, 0.0), shapes)
    return coarse, index

