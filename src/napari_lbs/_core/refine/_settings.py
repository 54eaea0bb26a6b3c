"""What the refinement fits, within which bounds, and how (`RefineSettings`).

Each particle's fitted parameters are its position, depth, diameter, index contrast
``n_p - n_m`` and absorption ``κ`` (`FIT_PARAMETERS`, the first `PHYSICAL` columns of the
fit's parameters, the depth in the medium), then the `NUISANCE` coefficients of the
illumination ``c0 + c1 u + c2 v`` over its patch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from napari_lbs._core.foundation import InputError

FIT_PARAMETERS = ("x_um", "y_um", "z_um", "diameter_um", "index_contrast", "absorption")
PHYSICAL = len(FIT_PARAMETERS)
NUISANCE = 3  # illumination c0 + c1 u + c2 v
BOUNDS = {  # (low, high) of each physical parameter in fit units; positions are bounded by the patch
    "diameter_um": (0.05, 500.0),
    "index_contrast": (-0.9, 2.5),
    "absorption": (0.0, 5.0),
}


@dataclass(frozen=True)
class RefineSettings:
    """How `refine_particles` fits.

    Attributes
    ----------
    medium_index : float
        Refractive index of the medium the particles are in (water: 1.33). The Lorenz–Mie
        scattering happens there; the table's depths stay in the config's convention.
    index_contrast, absorption : float
        Starting ``n_p - n_m`` (polystyrene in water: 0.26) and ``κ`` when the table has no
        such column.
    depth_window_um : float
        Depths scanned on each side of the guess (µm, the table's convention).
    depth_candidates : int
        Best local minima of the scan that start a fit.
    depth_prior_um : float
        The guesses' median depth error (µm, the table's convention; a network's validated
        median ``|Δz|``), or 0 for none. Where the hologram tells two depths apart by less
        than a few noise variances (a sphere's fringes among its neighbours' in a dense
        field), the searches pick the one nearer the guess: a depth ``Δz`` from it pays
        ``ln 2 · |Δz| / depth_prior_um`` half noise variances, a Laplace prior of that median.
    patch_px : int
        Largest patch edge (pixels).
    iterations : int
        Levenberg–Marquardt steps per round.
    rounds : int
        Fitting rounds. In the first, each particle's model holds the holograms of the
        other detections in reach at their guesses; each later one refits the particles with
        neighbours, holding them at the previous round's fits (more precise in crowded
        fields: two rounds halved the median depth error at four times the seed's density,
        at about 1.8 times the time).
    huber : float
        Residuals beyond this many noise scales get a Huber weight below 1.
    min_gain : float
        Lowering of the robust cost (in noise variances) that the fit must achieve over
        the model without the particle (its neighbours and the illumination) to keep a
        detection.
    pixel_integration : bool
        Model each pixel integrating its area (True) or point-sampled (pylorenzmie's).
    batch : int
        Most particles fitted together (memory); a round's particles are split into the
        fewest batches of at most this many, of equal sizes.
    device : str
        ``cpu``, ``cuda`` or ``auto``.
    workers : int
        Processes fitting batches side by side on the CPU, one thread each (the batches
        are independent: the table is the one a single process on one thread gives, bit
        for bit). More than 1 spawns processes, so a script must start
        its work under ``if __name__ == "__main__":``; ``napari-lbs predict --refine`` uses
        one per available core.
    """

    medium_index: float = 1.33
    index_contrast: float = 0.26
    absorption: float = 0.0
    depth_window_um: float = 400.0
    depth_candidates: int = 3
    depth_prior_um: float = 0.0
    patch_px: int = 128
    iterations: int = 8
    rounds: int = 1
    huber: float = 2.5
    min_gain: float = 50.0
    pixel_integration: bool = True
    batch: int = 8
    device: str = "cpu"
    workers: int = 1

    def __post_init__(self) -> None:
        for name in ("medium_index", "depth_window_um", "depth_prior_um", "huber", "min_gain"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise InputError(f"refine settings: {name} must be a finite number >= 0, got {value!r}")
        for name in ("depth_candidates", "patch_px", "iterations", "rounds", "batch", "workers"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise InputError(f"refine settings: {name} must be a positive integer, got {value!r}")
        if self.patch_px < 16:
            raise InputError(f"refine settings: patch_px must be at least 16, got {self.patch_px}")
        for name in ("index_contrast", "absorption"):
            check_bounded(f"refine settings: {name}", name, getattr(self, name))


def check_bounded(label: str, name: str, value) -> None:
    """A start or fixed value of a bounded parameter (`BOUNDS`) inside the fit's range."""
    low, high = BOUNDS[name]
    if not (isinstance(value, int | float) and math.isfinite(value) and low <= value <= high):
        raise InputError(f"{label} must be a number from {low:g} to {high:g} (the fit's range), got {value!r}")

