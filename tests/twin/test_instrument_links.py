"""A driver's side of the instrument: its health report and its connection (connect, disconnect), answered or
named, never a traceback."""

import json

import pytest

from tests.conftest import qd_lab
from tests.twin.test_bad_drivers import Raises
from twin.device.driver import StepResult
from twin.runtime.lab import run
from twin.scenario import parse


class Healthy(Raises):
    async def health(self):
        return {"ok": True, "lamp_hours": 1234}


class NumpyHealth(Raises):
    """An SDK's readings as numpy numbers, then an object: the query failed; `twin devices` said it never answered."""

    async def health(self):
        import numpy as np

        return {"ok": True, "lamp_temp_c": np.float32(41.5), "errors": [self] if getattr(self, "odd", 0) else []}


async def test_a_device_answers_health_requests_with_its_drivers_report(virtual_clock):
    from twin.core import keys
    from twin.device.actor import DeviceActor
    from twin.core.bus import open_bus

    s = parse(qd_lab())
    bus = open_bus("memory", virtual_clock)
    await bus.start()
    actors = [DeviceActor(name, s.devices["spectrometer"], drv, bus, virtual_clock, s.lab, 0)
              for name, drv in (("spectrometer-1", Healthy(None)), ("spectrometer-2", Raises(None)))]
    for a in actors:
        await a.start()
    one = json.loads(await bus.request(keys.health(s.lab, "spectrometer-1"), b"", timeout=5))
    two = json.loads(await bus.request(keys.health(s.lab, "spectrometer-2"), b"", timeout=5))
    assert one == {"device": "spectrometer-1", "on_bus": True, "dropped": 0, "running": None, "recent": [],
                   "t_lab": virtual_clock.now(), "clock": {"mode": "virtual", "speed": 1.0, "in_lab_time": True},
                   "driver": {"ok": True, "lamp_hours": 1234}}
    assert "driver" not in two and two["on_bus"]
    for a in actors:
        await a.stop()
    await bus.close()


async def test_a_health_report_of_numpy_numbers_or_what_is_not_json_is_an_answer(virtual_clock):
    from twin.core import keys
    from twin.core.bus import open_bus
    from twin.device.actor import DeviceActor

    s = parse(qd_lab())
    bus = open_bus("memory", virtual_clock)
    await bus.start()
    driver = NumpyHealth(None)
    actor = DeviceActor("spectrometer-1", s.devices["spectrometer"], driver, bus, virtual_clock, s.lab, 0)
    await actor.start()
    ask = keys.health(s.lab, "spectrometer-1")
    assert json.loads(await bus.request(ask, b"", timeout=5))["driver"] == {"ok": True, "lamp_temp_c": 41.5,
                                                                              "errors": []}
    driver.odd = 1
    said = json.loads(await bus.request(ask, b"", timeout=5))["driver"]
    assert said["ok"] is False and said["error"].startswith("health() returned what is not JSON: ")
    await actor.stop()
    await bus.close()


class HangingHealth(Raises):
    async def health(self):
        import asyncio

        await asyncio.Event().wait()  # an SDK's status call that never returns


def test_a_health_report_the_driver_never_finishes_is_the_devices_answer_with_that_said(monkeypatch):
    """It was no answer at all: `twin device health` said "answered: no" of a device on the bus, running a step."""
    import time

    from twin.core import keys
    from twin.core.bus import open_bus
    from twin.core.clock import LabClock, wall_on_loop
    from twin.device import actor as actors

    monkeypatch.setattr(actors, "HEALTH_WALL_S", 0.3)
    clock = LabClock("scaled", speed=50.0)
    s = parse(qd_lab())

    async def ask():
        bus = open_bus("memory", clock)
        await bus.start()
        actor = actors.DeviceActor("spectrometer-1", s.devices["spectrometer"], HangingHealth(None), bus, clock,
                                   s.lab, 0)
        await actor.start()
        started = time.perf_counter()
        try:
            said = json.loads(await bus.request(keys.health(s.lab, "spectrometer-1"), b"", timeout=wall_on_loop(3)))
            return said, time.perf_counter() - started
        finally:
            await actor.stop()
            await bus.close()

    said, took = clock.run(ask())
    assert said["on_bus"] and said["driver"] == {"ok": False, "error": "health() did not return within 0.3 s"}
    assert 0.3 <= took < 3  # wall seconds, on a lab clock 50 times as fast


class BadConnect(Raises):
    async def connect(self, presence):
        raise ConnectionRefusedError(111, "Connection refused")

    async def disconnect(self):
        pass

    async def run(self, step, params, sample, ctx):
        return StepResult({"peak_nm": 600.0}, sample)


class BadDisconnect(BadConnect):
    async def connect(self, presence):
        presence(True)

    async def disconnect(self):
        raise RuntimeError("socket already closed")


def test_an_instrument_that_cannot_connect_or_disconnect_is_named_not_a_traceback(tmp_path, caplog):
    """connect() raising was a traceback out of the lab's start; disconnect() raising, one out of its end, the
    finished campaign's summary never printed."""
    from twin.core.errors import DriverError

    def lab(cls):
        return parse(qd_lab(**{
            "devices.inst": {"driver": f"tests.twin.test_instrument_links:{cls}", "instances": 1, "steps": ["measure"],
                             "duration": {"mean_s": 60}},
            "workflow": [{"step": "synthesise", "device": "synthesiser"}, {"step": "measure", "device": "inst"}],
            "campaign.budget": 2, "clock": {"mode": "scaled", "speed": 2000}}))

    with pytest.raises(DriverError, match=r"inst: its driver's connect\(\) failed: ConnectionRefusedError: "
                                          r"\[Errno 111\] Connection refused; it did not start"):
        run(lab("BadConnect"), journal=tmp_path / "c.db", bus="memory")
    from twin.campaign.journal_read import read_run
    from twin.runtime.resume import ResumeError, resume

    stopped = read_run(tmp_path / "c.db")["summary"]["stopped"]  # `twin report` said nothing of why
    assert stopped.startswith("the lab did not start: inst: its driver's connect() failed: ConnectionRefusedError")
    with pytest.raises(ResumeError, match=r"the campaign ended \(the lab did not start: inst: its driver's "
                                          r"connect\(\) failed.*run it "
                                          r"again \(twin run\)"):  # it said "the campaign finished"
        resume(tmp_path / "c.db")
    summary = run(lab("BadDisconnect"), journal=tmp_path / "d.db", bus="memory")
    assert summary.done == 2
    assert "inst: disconnect() failed at shutdown: RuntimeError('socket already closed')" in caplog.text


def test_a_shared_lab_whose_instrument_cannot_connect_says_so_in_each_campaigns_journal(tmp_path):
    """Its journals read as killed: `twin report` said "interrupted ... Continue it with: twin resume"."""
    from tests.conftest import twin_cli
    from tests.twin.shared_labs import LAB, SMALL
    from twin.core.errors import DriverError
    from twin.runtime.lab import prepare
    from twin.runtime.shared_run import run_shared

    s = prepare(LAB, clock="scaled", speed=3000, bus="memory",
                overrides={**SMALL, "devices.spectrometer.driver": "tests.twin.test_instrument_links:BadConnect"})
    with pytest.raises(DriverError, match="its driver's connect\\(\\) failed"):
        run_shared(s, tmp_path / "lab", handle_signals=False)
    said = " ".join(twin_cli("report", tmp_path / "lab").output.split())
    for name in (c.name for c in s.campaigns):
        assert f"{tmp_path / 'lab' / name}.db: never started — spectrometer: its driver's connect() failed" in said
    assert "interrupted" not in said, said


class Flickering(Raises):
    """An instrument whose link drops during its second step and is back 300 lab-s later, its own task says."""

    events: list = []

    def __init__(self, setup):
        self.name, self.steps, self.presence = setup.name, 0, None

    async def connect(self, presence):
        self.presence = presence
        presence(True)

    async def disconnect(self):
        pass

    async def run(self, step, params, sample, ctx):
        import asyncio

        self.steps += 1
        if self.steps == 2:
            asyncio.get_running_loop().create_task(self._back_in(300))
            self.presence(False)
            try:
                await ctx.clock.sleep(1e6)  # what a driver that waits on its instrument's answer does
            except asyncio.CancelledError:
                Flickering.events.append((self.name, "cancelled"))
                raise
        await ctx.clock.sleep(60)
        Flickering.events.append((self.name, "done"))
        return StepResult({"peak_nm": 600.0}, sample)

    async def _back_in(self, lab_s):
        import asyncio

        await asyncio.sleep(lab_s)  # the lab's event loop keeps lab time
        self.presence(True)


def test_a_step_running_when_the_instrument_goes_is_cancelled_and_the_device_is_back_when_its_driver_says(tmp_path):
    """docs/drivers.md: presence(False) takes the device off the bus and cancels the step it runs, which moves
    elsewhere; presence(True), from a task of the driver's own, brings it back to take work again."""
    Flickering.events = []
    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_instrument_links:Flickering",
                          "campaign.budget": 8}))
    summary = run(lab, journal=tmp_path / "j.db", bus="memory", runtime="asyncio")
    assert summary.done == 8 and summary.abandoned == 0
    assert summary.devices_lost == 2 and summary.steps_lost >= 1
    ev = Flickering.events
    cancelled = [ev.index((name, "cancelled")) for name in ("spectrometer-1", "spectrometer-2")
                 if (name, "cancelled") in ev]
    assert cancelled and summary.steps_lost == len(cancelled) and summary.timed_out == 0  # lost, not timed out
    for at in cancelled:  # the device took work again once its link was back
        assert (ev[at][0], "done") in ev[at + 1:], ev


class BlockingHealth(Raises):
    async def health(self):
        import time

        time.sleep(0.2)  # an SDK's synchronous status call, in an async def
        return {"ok": True}


def test_a_health_report_that_blocks_the_lab_is_said_as_a_blocking_step_is(virtual_clock, monkeypatch, caplog):
    """It held the whole lab, unsaid: run() and safe_state() were timed between their awaits, health() was not."""
    import logging

    from twin.core import keys
    from twin.core.bus import open_bus
    from twin.device import habits
    from twin.device.actor import DeviceActor

    monkeypatch.setattr(habits, "BLOCKING_S", 0.1)
    s = parse(qd_lab())

    async def ask():
        bus = open_bus("memory", virtual_clock)
        await bus.start()
        actor = DeviceActor("spectrometer-1", s.devices["spectrometer"], BlockingHealth(None), bus, virtual_clock,
                            s.lab, 0)
        await actor.start()
        try:
            return json.loads(await bus.request(keys.health(s.lab, "spectrometer-1"), b"", timeout=5))
        finally:
            await actor.stop()
            await bus.close()

    with caplog.at_level(logging.WARNING):
        said = virtual_clock.run(ask())
    assert said["driver"] == {"ok": True}
    assert any(r.getMessage().startswith("spectrometer-1: its driver ran ") and "without awaiting" in r.getMessage()
               for r in caplog.records), caplog.text


def test_a_labs_devices_are_asked_for_their_health_at_once(monkeypatch):
    """One after another, `twin devices --connect` of a lab whose drivers' health() hung took the wait once per
    device."""
    from twin.core.bus import open_bus
    from twin.core.clock import LabClock
    from twin.device import actor as actors
    from twin.runtime.serve import _ask_health

    monkeypatch.setattr(actors, "HEALTH_WALL_S", 0.3)
    clock = LabClock("virtual")  # a health() cut at 0.3 lab-s: the lab time the asking took tells how
    s = parse(qd_lab(**{"devices.spectrometer.instances": 3}))
    names = [f"spectrometer-{i}" for i in (1, 2, 3)]

    async def ask():
        bus = open_bus("memory", clock)
        await bus.start()
        running = [actors.DeviceActor(name, s.devices["spectrometer"], HangingHealth(None), bus, clock, s.lab, 0)
                   for name in names]
        for a in running:
            await a.start()
        started = clock.now()
        try:
            return await _ask_health(bus, s.lab, names, 5.0), clock.now() - started
        finally:
            for a in running:
                await a.stop()
            await bus.close()

    answers, took = clock.run(ask())
    assert [a["device"] for a in answers] == names
    assert all(a["report"]["driver"]["error"] == "health() did not return within 0.3 s" for a in answers)
    assert took == pytest.approx(0.3)
