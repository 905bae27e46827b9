from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from mavcal.testing.ci import pytest_runtest_makereport  # noqa: F401 - CI=true: a real-log/browser skip fails
from mavcal.testing.vehicle import TestVehicle

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


@pytest.fixture
def start_vehicle() -> Iterator[Callable[..., TestVehicle]]:
    """Factory: ``start_vehicle(transport="udpout", **options)`` starts a :class:`TestVehicle`
    on 127.0.0.1 with those options and returns it; every vehicle it started is stopped at
    teardown, whatever the test did (stopping twice is harmless, so ``with start_vehicle(...)
    as v:`` also works)."""
    started: list[TestVehicle] = []

    def start(transport: str = "udpout", **options) -> TestVehicle:
        vehicle = TestVehicle(transport, **options)
        started.append(vehicle)
        return vehicle.start()

    yield start
    for vehicle in started:
        vehicle.stop()


@pytest.fixture
def start_sitl():
    """Factory: ``start_sitl(errors=None, **options)`` starts a
    :class:`mavcal.testing.sitl.SitlVehicle` (skips without SITL; fails under CI=true) and
    returns it; every one it started is stopped at teardown, whatever the test did."""
    from mavcal.testing.sitl import SitlVehicle, require_sitl

    require_sitl()
    started: list[SitlVehicle] = []

    def start(errors=None, **options) -> SitlVehicle:
        vehicle = SitlVehicle(errors, **options)
        started.append(vehicle)
        return vehicle.start()

    yield start
    for vehicle in started:
        vehicle.stop()
