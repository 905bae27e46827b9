from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
REAL = SHARED / "data" / "real"
SITL = REPO / "sitl_logs"


@pytest.fixture(scope="session")
def real_dir() -> Path:
    if not REAL.is_dir():
        pytest.skip(f"real logs not found at {REAL} (shared/ must sit beside the repo)")
    return REAL


@pytest.fixture(scope="session")
def sitl_dir() -> Path:
    return SITL
