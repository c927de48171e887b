"""A device whose orchestrator left the bus stops its step in a safe state after a grace period."""

import json

import pytest

from tests.conftest import qd_lab
from twin import DeviceActor, StepResult
from twin.core import keys
from twin.core.bus import open_bus
from twin.core.messages import Kind, pack
from twin.scenario import parse


class Slow:
    capabilities = frozenset({"measure"})

    def __init__(self, setup=None):
        self.safe = 0

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(1000)
        return StepResult({"peak_nm": 600.0}, sample)

    async def safe_state(self):
        self.safe += 1


@pytest.mark.parametrize("back_after", [None, 50.0])
def test_an_orphaned_step_is_stopped_after_the_grace_period_unless_the_orchestrator_returns(
        virtual_clock, back_after):
    heard, driver = [], Slow()
    virtual_clock.run(_campaign_dies(virtual_clock, back_after, heard, driver))
    kinds = [(m["kind"], m["body"].get("code")) for _, m in heard]
    if back_after is None:
        assert ("fault", "cancelled") in kinds and ("result", None) not in kinds
        t, fault = next((t, m) for t, m in heard if m["kind"] == "fault")
        assert t == pytest.approx(110) and "orchestrator was gone for 100 lab-s" in fault["body"]["reason"]
        assert driver.safe >= 1
    else:
        assert ("result", None) in kinds and ("fault", "cancelled") not in kinds


async def _campaign_dies(virtual_clock, back_after, heard, driver):
    s = parse(qd_lab())
    bus = open_bus("memory", virtual_clock)
    await bus.start()
    actor = DeviceActor("spectrometer-1", s.devices["spectrometer"], driver, bus, virtual_clock, s.lab, 0,
                        orphan_grace_s=100)
    bus.subscribe(keys.evt(s.lab), lambda key, payload: heard.append((virtual_clock.now(), json.loads(payload))))
    boss = bus.declare_token(keys.orchestrator(s.lab))
    await actor.start()
    bus.publish(keys.cmd(s.lab, "spectrometer-1"),
                pack(Kind.COMMAND, {"step": "measure", "params": {}, "sample": None, "expected_s": 1000},
                     id="o:1", sender="orchestrator", t_lab=0.0, task="e0s0", attempt=1))
    await virtual_clock.sleep(10)
    boss.close()  # the orchestrator dies
    if back_after is not None:
        await virtual_clock.sleep(back_after)
        boss = bus.declare_token(keys.orchestrator(s.lab))
    await virtual_clock.sleep(2000)
    await actor.stop()
    await bus.close()


class Simulator(Slow):
    chemistry_models = frozenset({"quantum_dots"})


@pytest.mark.parametrize("driver_class", [Simulator, Slow])
def test_a_simulator_of_a_shared_lab_refuses_a_campaign_it_has_no_chemistry_for(virtual_clock, driver_class):
    """`twin device serve` of a shared lab simulates the campaigns its lab file lists; a campaign submitted later
    is told why its step cannot run there (and retries later), never given another campaign's chemistry. A real
    instrument (no simulated chemistry) runs any campaign's step."""
    heard: list = []

    async def main():
        s = parse(qd_lab())
        bus = open_bus("memory", virtual_clock)
        await bus.start()
        listed = driver_class()
        actor = DeviceActor("spectrometer-1", s.devices["spectrometer"], driver_class(), bus, virtual_clock, s.lab,
                            0, shared={"dots": listed})
        bus.subscribe(keys.evt(s.lab), lambda key, payload: heard.append(json.loads(payload)))
        await actor.start()
        for n, campaign in enumerate(("dots", "late")):
            bus.publish(keys.cmd(s.lab, "spectrometer-1"),
                        pack(Kind.COMMAND, {"step": "measure", "params": {}, "sample": None, "expected_s": 1000},
                             id=f"o:{n}", sender="orchestrator", t_lab=0.0, task="e0s0", attempt=1,
                             campaign=campaign))
            await virtual_clock.sleep(2000)
        await actor.stop()
        await bus.close()

    virtual_clock.run(main())
    by_campaign = {}
    for m in heard:
        by_campaign.setdefault(m["campaign"], []).append(m)
    assert [m["kind"] for m in by_campaign["dots"]] == ["accepted", "result"]
    late = [m for m in by_campaign["late"] if m["kind"] != "progress"]
    if driver_class is Simulator:
        assert [m["kind"] for m in late] == ["rejected"]
        assert late[0]["body"]["infeasible"] is False and "not campaign 'late'" in late[0]["body"]["reason"]
        assert "twin device serve" in late[0]["body"]["reason"]
    else:
        assert [m["kind"] for m in late] == ["accepted", "result"]
