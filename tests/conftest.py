import pytest

from twin.bus import open_bus
from twin.clock import LabClock
from twin.scenario import set_dotted


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


def qd_lab(**changes) -> dict:
    """A small quantum-dot lab as a scenario dict; ``changes`` are dotted paths."""
    raw = {
        "name": "test_lab",
        "lab": "t",
        "devices": {
            "synthesiser": {"driver": "synthesiser", "instances": 1, "steps": ["synthesise"],
                            "duration": {"mean_s": 60, "cv": 0.1}},
            "spectrometer": {"driver": "spectrometer", "instances": 2, "steps": ["measure"],
                             "duration": {"mean_s": 60, "cv": 0.1}},
        },
        "chemistry": {
            "model": "quantum_dots",
            "parameters": {
                "concentration_mm": {"low": 1, "high": 50},
                "temperature_c": {"low": 220, "high": 320},
                "time_s": {"low": 10, "high": 600},
            },
            "targets": [{"name": "R", "outputs": {"peak_nm": {"value": 630, "tol": 5}}}],
        },
        "workflow": [{"step": "synthesise", "device": "synthesiser"}, {"step": "measure", "device": "spectrometer"}],
        "campaign": {"budget": 8, "max_in_flight": 2, "stop_on_target": False},
        "orchestrator": {"timeout_factor": 2, "timeout_slack_s": 60,
                         "retry": {"max_attempts": 3, "backoff_s": 10, "jitter": 0.2}},
        "bus": {"kind": "memory"},
    }
    for dotted, value in changes.items():
        set_dotted(raw, dotted, value)
    return raw


@pytest.fixture
def scenario_of():
    from twin.scenario import parse

    return lambda **changes: parse(qd_lab(**changes))
