"""A clean cancel: after a timeout the lab gives a device nothing until it has answered the cancel (or a grace
period has passed, or it left the bus), and a "busy" answer from a device still stopping uses up no attempt —
in one process on the memory bus, and with the device in another process behind a router."""

import json
import re

import pytest
import yaml

from tests.conftest import qd_lab
from tests.twin.test_device_process import free_port
from tests.twin.test_distributed_lab import start
from twin import DriverSetup, StepContext, StepResult
from twin.campaign.journal_read import read_events
from twin.runtime.lab import make_clock, prepare, run_async
from twin.scenario import parse

STOPPING_S = 100.0  # lab seconds the slow device takes to reach its safe state: longer than the grace (60)


class SlowToStop:
    """A measuring device that never finishes in time and takes STOPPING_S to stop when cancelled."""

    labtwin_api = 1
    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm"})

    def __init__(self, setup: DriverSetup) -> None:
        self.clock = None

    async def run(self, step: str, params: dict, sample: dict | None, ctx: StepContext) -> StepResult:
        self.clock = ctx.clock
        await ctx.clock.sleep(10_000)
        return StepResult({"peak_nm": 600.0}, sample)

    async def safe_state(self) -> None:
        if self.clock is not None:
            await self.clock.sleep(STOPPING_S)


def _lab(**changes) -> dict:
    return qd_lab(**{
        "devices.synthesiser.duration": {"mean_s": 60, "cv": 0},
        "devices.spectrometer": {"driver": "tests.twin.test_clean_cancel:SlowToStop", "instances": 1,
                                 "steps": ["measure"], "duration": {"mean_s": 60, "cv": 0}},
        "campaign.budget": 3, "campaign.max_in_flight": 3,
        "orchestrator.timeout_factor": 1, "orchestrator.timeout_slack_s": 60, "orchestrator.cancel_grace_s": 60,
        "orchestrator.retry": {"max_attempts": 2, "backoff_s": 0, "jitter": 0},
        "orchestrator.quarantine_after": 100, **changes})


def _check(db, summary) -> None:
    events = read_events(db)
    kinds = [e["kind"] for e in events]
    busy = [e for e in events if e["kind"] == "msg.rejected" and "busy" in e["detail"]]
    timed_out = sorted((e["task"], e["attempt"]) for e in events if e["kind"] == "attempt.failed"
                       and json.loads(e["detail"])["code"] == "timed_out")
    # each experiment had its two attempts, both timed out: no "busy" answer used one up (a busy answer's attempt
    # number is not used again, so the timed-out ones are not numbered 1 and 2)
    per_step: dict = {}
    for task, n in timed_out:
        per_step.setdefault(task, set()).add(n)
    assert {t: len(ns) for t, ns in per_step.items()} == {f"e{i}s1": 2 for i in range(3)}
    assert summary.abandoned == 3 and summary.timed_out == 6
    assert busy, "the device was never asked while stopping: the grace is longer than the test means"
    # says what it is still running, in words (it read "busy with ('e0s1', 1)"), and that it is making it safe
    reasons = [json.loads(e["detail"])["body"]["reason"] for e in busy]
    assert all(re.fullmatch(r"busy with e\d+s1 \(attempt \d+\): its safe_state\(\) has not returned", r)
               for r in reasons), reasons
    # a "busy" after the grace quarantined the device until it answered (device.stuck said once), so no step
    # was offered to it again before: one "busy" per cancel left unanswered at most
    assert len(busy) == summary.stuck <= kinds.count("attempt.cancel_unanswered")
    assert kinds.count("device.stuck") == 1
    released = [e for e in events if e["kind"] == "device.probe" and "answered the cancel" in (e["detail"] or "")]
    assert len(released) >= len(busy) - 1  # the campaign may end before the last
    assert kinds.count("attempt.cancel_acknowledged") >= 5  # the campaign may end before the last


def test_on_the_memory_bus(tmp_path):
    s = parse(_lab())
    clock = make_clock(s)
    summary = clock.run(run_async(s, clock, tmp_path / "j.db"))
    _check(tmp_path / "j.db", summary)


@pytest.mark.process
def test_with_the_device_in_another_process(tmp_path):
    speed = 200.0
    router = f"tcp/127.0.0.1:{free_port()}"
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(_lab(**{
        "clock": {"mode": "scaled", "speed": speed}, "orchestrator.startup_s": 4000,
        "bus": {"kind": "zenoh", "listen": [], "connect": [router], "lease_ms": 1000}})))
    s = prepare(path)
    procs = [start(["router", "--listen", router], "router"),
             start(["device", "serve", str(path), "--id", "spectrometer", "--connect", router], "ready spectrometer")]
    clock = make_clock(s)
    try:
        summary = clock.run(run_async(s, clock, tmp_path / "j.db", {"spectrometer"}))
    finally:
        for p in procs:
            p.kill()
            p.wait()
    _check(tmp_path / "j.db", summary)
