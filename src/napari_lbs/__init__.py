"""napari-lbs: learning from better simulation for in-line particle holography.

The computation lives in `napari_lbs._core` (no Qt, no napari); the dock widgets and the
``napari-lbs`` console script are thin fronts over it.
"""

import os

__version__ = "0.1.0"

# MKL (torch's BLAS and LAPACK) otherwise picks kernels, and so rounding, by the buffers'
# memory alignment: the same fit run again, or in a worker process, could end a rounding
# error apart and, where a fit chooses between minima, elsewhere. Read when MKL starts, so
# set before anything loads torch; a value the user set is kept.
os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")
