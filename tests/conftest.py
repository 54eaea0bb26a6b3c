from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
REAL_HOLOGRAM_BMP = SHARED / "reference" / "lbs-experiment" / "cropped_hologram.bmp"


@pytest.fixture(scope="session")
def real_hologram_bmp() -> Path:
    # CI runs with ../shared beside the clone; without it this is a failure, not a skip.
    assert REAL_HOLOGRAM_BMP.is_file(), f"expected the seed's real hologram at {REAL_HOLOGRAM_BMP}"
    return REAL_HOLOGRAM_BMP
