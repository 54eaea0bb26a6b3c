"""Which refined particles are of the sample's material: a gate on the fitted index contrast.

A lab that knows what it put in the water (polystyrene beads: ``n_p - n_m`` = 0.26) wants
those particles counted, and the debris, bubbles and dust of the same hologram set apart.
The Lorenz–Mie fit measures each particle's index contrast (`refine_particles`); a
particle whose value is far from the sample's, beyond both what one material's fits spread
over and its own uncertainty, is of another material. Holographic characterisation tools
gate their size-and-index scatter the same way (Yevick et al. 2014; Altman & Grier 2020).

References
----------
Yevick, A., Hannel, M. & Grier, D. G. (2014). Machine-learning approach to holographic
particle characterization. Optics Express 22, 26884.
Altman, L. E. & Grier, D. G. (2020). CATCH: characterizing and tracking colloids
holographically using deep neural networks. J. Phys. Chem. B 124, 1602.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core.foundation import InputError

__all__ = ["MATERIAL_SIGMAS", "MATERIAL_TOLERANCE", "same_material"]

# The spread of one material's fitted index contrasts: on the development holograms of
# docs/refinement.md, polystyrene spheres of 16-36 um fitted 0.185-0.30 (the largest, beyond
# the fit's valleys, lowest), and the debris (index 1.45, 3-12 um) 0.30-0.55 as 10-18 um spheres.
MATERIAL_TOLERANCE = 0.08
# and a particle's own uncertainty: differences within this many index_err are one material
MATERIAL_SIGMAS = 2.0


def same_material(table, *, index_contrast: float, tolerance: float = MATERIAL_TOLERANCE, sigmas: float = MATERIAL_SIGMAS) -> np.ndarray:
    """True for each particle whose fitted index contrast is consistent with the sample's.

    A particle is of another material when its ``index_contrast`` differs from
    ``index_contrast`` by more than ``tolerance`` and by more than ``sigmas`` times its own
    uncertainty ``index_err``. A row the fit did not measure (no index contrast), or
    measured without an uncertainty, is kept: nothing says it is of another material.

    The fit measures a large sphere's index contrast within the phase-delay period it
    starts in (`RefineSettings.index_contrast`, the valley prior of `refine_particles`):
    a sphere of another material whose phase delay differs by whole periods fits in the
    sample's valley. What the gate sets apart is what does not fit the sample's material:
    debris and small scatterers (on the development holograms, 9 of 12 debris, none of 694
    polystyrene spheres but one misfit at the window's edge).

    Parameters
    ----------
    table : mapping of column name to 1-D array, or pandas.DataFrame
        A refined particle table (`refine_particles`): ``index_contrast`` and ``index_err``.
    index_contrast : float
        The sample's ``n_p - n_m`` (polystyrene in water: 1.59 - 1.33 = 0.26).
    tolerance : float
        Differences up to this are one material whatever the uncertainty.
    sigmas : float
        Differences up to this many ``index_err`` are one material whatever the tolerance.

    Returns
    -------
    numpy.ndarray of bool, one per row.
    """
    if not isinstance(index_contrast, (int, float, np.number)) or not np.isfinite(index_contrast):
        raise InputError(f"index_contrast must be a number, got {index_contrast!r}")
    if not (tolerance >= 0 and sigmas >= 0):
        raise InputError(f"tolerance and sigmas must be >= 0, got {tolerance!r} and {sigmas!r}")
    for column in ("index_contrast", "index_err"):
        if column not in table:
            raise InputError(f"the table has no {column} column: refine it first (refine_particles)")
    fitted = np.asarray(table["index_contrast"], dtype=np.float64)
    error = np.nan_to_num(np.asarray(table["index_err"], dtype=np.float64), nan=np.inf)
    allowed = np.maximum(tolerance, sigmas * error) if sigmas > 0 else np.full(fitted.shape, float(tolerance))
    return ~np.isfinite(fitted) | (np.abs(fitted - float(index_contrast)) <= allowed)
