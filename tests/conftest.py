import os

os.environ.setdefault("RERUN", "off")

import pytest  # noqa: E402

from twin.bus import open_bus  # noqa: E402
from twin.clock import LabClock  # noqa: E402


@pytest.fixture
def virtual_clock() -> LabClock:
    return LabClock("virtual")


@pytest.fixture(params=["memory", "zenoh"])
def bus_kind(request) -> str:
    return request.param


@pytest.fixture
def make_bus(bus_kind):
    """Build a started bus of the parametrised kind inside a running loop."""

    async def make(clock: LabClock):
        bus = open_bus(bus_kind, clock)
        await bus.start()
        return bus

    return make
