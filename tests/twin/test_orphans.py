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
