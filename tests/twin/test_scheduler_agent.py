"""A scheduler agent on the bus: killed mid-campaign, or answering nonsense, the fallback rule takes over."""

import asyncio
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from tests.twin.test_device_process import free_port
from twin.campaign.decisions import Assignment
from twin.campaign.journal_read import read_events
from twin.runtime.lab import make_clock, prepare, run, run_async

ROOT = Path(__file__).resolve().parents[2]
SPEED = 200.0


@pytest.mark.process
def test_the_fallback_takes_over_when_the_agent_process_is_killed(tmp_path):
    port = free_port()
    raw = qd_lab(**{
        "campaign.budget": 10, "campaign.scheduler": "remote", "campaign.fallback_scheduler": "fifo",
        "clock": {"mode": "scaled", "speed": SPEED},
        "bus": {"kind": "zenoh", "listen": [f"tcp/127.0.0.1:{port}"]},
        "orchestrator.startup_s": 4000,
    })
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    s = prepare(path)
    clock = make_clock(s)
    db = tmp_path / "j.db"
    agent = subprocess.Popen(
        [sys.executable, "-m", "twin", "scheduler", "serve", str(path), "--scheduler", "spt",
         "--connect", f"tcp/127.0.0.1:{port}", "--clock", "scaled", "--speed", str(SPEED)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT,
    )
    seen = {}

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, db, on_start=lambda o: seen.setdefault("orch", o)))
        while "killed_at" not in seen and not campaign.done():
            orch = seen.get("orch")
            if orch is not None and orch.scheduler.answered >= 3:
                seen["answered"] = orch.scheduler.answered
                seen["killed_at"] = clock.now()
                os.kill(agent.pid, signal.SIGKILL)
            await clock.sleep(1)
        return await campaign

    try:
        summary = clock.run(main())
    finally:
        agent.kill()
        agent.wait()
    assert "killed_at" in seen, "the agent never made three decisions"
    assert summary.done == 10 and summary.abandoned == 0
    assert summary.scheduler_fallbacks > 0
    notes = [e for e in read_events(db) if e["kind"] == "scheduler.fallback"]
    assert notes and notes[0]["t_lab"] >= seen["killed_at"]
    assert "not on the bus" in notes[-1]["detail"] or "did not answer" in notes[-1]["detail"]


class Nonsense:
    """An agent that answers with a device that does not exist."""

    serve_on_bus = True

    def __init__(self, **_):
        pass

    def decide(self, view):
        return [Assignment(view.ready[0].task, "no-such-device")]


def test_an_agent_that_answers_nonsense_is_overruled_by_the_fallback(tmp_path):
    raw = qd_lab(**{"campaign.budget": 4, "campaign.scheduler": "tests.twin.test_scheduler_agent:Nonsense"})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    summary = run(path, journal=tmp_path / "j.db")
    assert summary.done == 4 and summary.scheduler_fallbacks == summary.decisions > 0
    notes = [e for e in read_events(tmp_path / "j.db") if e["kind"] == "scheduler.fallback"]
    assert len(notes) == 1 and "invalid decision" in notes[0]["detail"] and "no-such-device" in notes[0]["detail"]


class FailsEveryThird:
    """An agent whose decision raises now and then (a model that cannot read a view, say)."""

    serve_on_bus = True

    def __init__(self, **_):
        self.asked = 0

    def decide(self, view):
        self.asked += 1
        if self.asked % 3 == 0:
            raise RuntimeError("the model lost its weights")
        return FirstFit().decide(view)


@pytest.mark.parametrize("bus", ["memory", "zenoh"])
def test_an_agent_that_raises_is_covered_by_the_fallback_and_the_campaign_goes_on(tmp_path, bus):
    # it used to end the campaign: the memory bus passed the exception to the lab, Zenoh an error reply it did not take
    raw = qd_lab(**{"campaign.budget": 6, "campaign.scheduler": "tests.twin.test_scheduler_agent:FailsEveryThird",
                    "bus.kind": bus})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    summary = run(path, journal=tmp_path / "j.db")
    assert summary.done == 6 and summary.abandoned == 0
    assert 0 < summary.scheduler_fallbacks < summary.decisions
    notes = [e["detail"] for e in read_events(tmp_path / "j.db") if e["kind"] == "scheduler.fallback"]
    assert notes and all("the scheduler agent failed: RuntimeError: the model lost its weights" in n for n in notes)


def decided_by_replier(virtual_clock, replier):
    """What the lab's side of a remote scheduler decides for one ready step, the agent's side served by
    ``replier``, and the fallback's reasons."""
    from twin.campaign.decisions import FreeDevice, LabView, ReadyStep
    from twin.core.bus import open_bus
    from twin.runtime.remote_scheduler import Fallback, RemoteScheduler, alive_key, decide_key

    view = LabView(0.0, (ReadyStep("e0s0", 0, "measure", "spectrometer", 0.0, 0.0, 60.0, 60.0, frozenset(), ()),),
                   (FreeDevice("spectrometer-1", "spectrometer"),), (), 0, 1, 1)

    async def main():
        bus = open_bus("memory", virtual_clock)
        await bus.start()
        handles = [bus.serve(decide_key("t"), replier), bus.declare_token(alive_key("t"))]
        fallback = Fallback(FirstFit(), "first-fit")
        reasons = []
        fallback.on_fallback = reasons.append
        remote = RemoteScheduler(bus, "t", fallback, 5.0)
        try:
            await virtual_clock.sleep(1.0)
            return await remote.decide(view), reasons
        finally:
            remote.close()
            for h in handles:
                h.close()
            await bus.close()

    return virtual_clock.run(main())


def test_an_error_reply_on_the_bus_is_the_agents_failure_not_the_labs(virtual_clock):
    async def broken(key, payload):
        raise ValueError("cannot parse the view")

    decided, reasons = decided_by_replier(virtual_clock, broken)
    assert decided == [Assignment("e0s0", "spectrometer-1")]  # the fallback's
    assert reasons == ["the scheduler agent failed: the replier for 'labtwin/t/agent/scheduler/decide' failed: "
                       "cannot parse the view"]


@pytest.mark.parametrize("reply,says", [
    (b"[" * 100_000, "JSON nested too deep"),  # json.loads raises RecursionError: it failed the lab's decision
    (b'{"error": ' + b"[" * 100_000, "JSON nested too deep"), (b"\xff\xfe", "JSONDecodeError"),
    (b'{"assign": 5}', "not iterable"), (b'{"assign": [[1, 2]]}', "list indices"),
    (b'{"assign": [{"task": 1}]}', "KeyError('device')"),
])
def test_an_agent_whose_answer_cannot_be_read_is_overruled_by_the_fallback(virtual_clock, reply, says):
    async def hostile(key, payload):
        return reply

    decided, reasons = decided_by_replier(virtual_clock, hostile)
    assert decided == [Assignment("e0s0", "spectrometer-1")]  # the fallback's
    assert len(reasons) == 1 and reasons[0].startswith("the scheduler agent sent an unreadable decision")
    assert says in reasons[0]


class FirstFit:
    def decide(self, view):
        free, out = list(view.free), []
        for r in view.ready:
            fits = [f for f in free if f.device_type == r.device_type and f.name not in r.avoid]
            if fits:
                free.remove(fits[0])
                out.append(Assignment(r.task, fits[0].name))
        return out


def test_the_agent_reads_the_documented_view_and_names_the_field_of_a_malformed_one(virtual_clock):
    import json

    from twin.core.bus import open_bus
    from twin.core.bus.base import BusError
    from twin.campaign.decisions import DeviceState, FreeDevice, LabView, ReadyStep
    from twin.runtime.remote_scheduler import SchedulerService, decide_key, encode_view

    view = LabView(5230.0, (ReadyStep("e4s1", 4, "measure", "spectrometer", 5100.0, 5100.0, 60.0, 90.0,
                                      frozenset({"spectrometer-3", "spectrometer-1"}), (("reactor", 30.0),)),),
                   (FreeDevice("spectrometer-1", "spectrometer"), FreeDevice("spectrometer-2", "spectrometer")),
                   (DeviceState("spectrometer-1", "spectrometer", True, True, None, 7, 1, 480.0),), 3, 10, 2)
    wire = json.loads(encode_view(view))  # as docs/wire.md shows it: sets as sorted lists, pairs as lists
    assert wire["ready"][0]["avoid"] == ["spectrometer-1", "spectrometer-3"]
    assert wire["ready"][0]["then"] == [["reactor", 30.0]] and wire["devices"][0]["busy_until"] is None

    async def main():
        bus = open_bus("zenoh", virtual_clock)
        await bus.start()
        service = SchedulerService(bus, "t", FirstFit())
        service.start()
        try:
            await virtual_clock.sleep(1.0)
            reply = json.loads(await bus.request(decide_key("t"), encode_view(view), 5.0))
            wire["ready"][0]["expected_s"] = "a minute"
            with pytest.raises(BusError, match=r"\$\.ready\[0\]\.expected_s"):
                await bus.request(decide_key("t"), json.dumps(wire).encode(), 5.0)
            return reply
        finally:
            service.stop()
            await bus.close()

    assert virtual_clock.run(main()) == {"assign": [{"task": "e4s1", "device": "spectrometer-2"}]}
