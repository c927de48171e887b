"""A driver's habits that hurt the lab (twin/device/habits.py), and what the lab does about them on either runtime:
a blocking call between two awaits, telemetry or progress in a loop that does not wait, a safe_state that never
returns."""

import asyncio
import re

import pytest

from tests.conftest import qd_lab
from tests.twin.test_bad_drivers import Raises
from twin.device.driver import StepResult
from twin.runtime.lab import run
from twin.scenario import parse


class Blocks(Raises):
    """A driver that calls a blocking vendor SDK (time.sleep) instead of awaiting the lab clock."""

    async def run(self, step, params, sample, ctx):
        import time

        await ctx.clock.sleep(30)
        time.sleep(0.2)
        return StepResult({"peak_nm": 500.0}, sample)


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_a_driver_that_blocks_the_lab_is_named_once_on_either_runtime(tmp_path, caplog, monkeypatch, runtime):
    """A 3 s time.sleep in run() held the whole lab 3 s per step, silently, and took no lab time."""
    import logging

    from twin.device import habits

    monkeypatch.setattr(habits, "BLOCKING_S", 0.1)
    lab = parse(qd_lab(**{
        "devices.spectrometer": {"driver": "tests.twin.test_driver_habits:Blocks", "instances": 2, "steps": ["measure"],
                                 "duration": {"mean_s": 60, "cv": 0.1}},
        "campaign.budget": 3, "bus.kind": "memory"}))
    with caplog.at_level(logging.WARNING):
        summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    said = [r.getMessage() for r in caplog.records if "without awaiting" in r.getMessage()]
    assert summary.done == 3
    devices = {message.split(":")[0] for message in said}
    assert len(said) == len(devices) and devices <= {"spectrometer-1", "spectrometer-2"} and devices
    assert all(re.search(r"its driver ran \d+\.\d s of wall time without awaiting \(a blocking call: time\.sleep, a "
                         r"vendor SDK\?\)", m) and "await asyncio.to_thread(call)" in m for m in said)


class StuckSafe(Raises):
    """Its step hangs until the lab cancels it, and its safe_state never returns."""

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(float("inf"))

    async def safe_state(self):
        await asyncio.Event().wait()


def test_a_safe_state_that_never_returns_does_not_keep_the_lab_from_ending(tmp_path):
    """The campaign abandoned the experiment and printed nothing more: the process hung at shutdown for ever, in
    the device's last safe_state()."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    code = ("from tests.conftest import qd_lab\nfrom twin.scenario import parse\nfrom twin.runtime.lab import run\n"
            "lab = parse(qd_lab(**{'devices.spectrometer': {'driver': 'tests.twin.test_driver_habits:StuckSafe', "
            "'instances': 1, 'steps': ['measure'], 'duration': {'mean_s': 60}}, 'campaign.budget': 1, "
            "'bus.kind': 'memory'}))\n"
            f"s = run(lab, journal={str(tmp_path / 'j.db')!r}, runtime='asyncio')\nprint('ended', s.abandoned)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, timeout=90)
    assert res.returncode == 0 and "ended 1" in res.stdout, res.stderr[-2000:]
    assert "spectrometer: safe_state() did not return within 60 lab-s at shutdown (orchestrator.cancel_grace_s)" \
        in res.stderr


class Chatters(Raises):
    """Reports in a loop: without waiting (``tight``), or once every lab-second; telemetry, or progress."""

    tight, telemetry = True, True

    async def run(self, step, params, sample, ctx):
        for i in range(150):
            if self.telemetry:
                ctx.telemetry({"lamp_c": 40.0 + i % 3})
            else:
                ctx.progress(i / 150, "scanning")
            if not self.tight:
                await ctx.clock.sleep(1)
        return StepResult({"peak_nm": 500.0}, sample)


class Paced(Chatters):
    tight = False


class Scans(Chatters):
    telemetry = False


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_telemetry_or_progress_reported_in_a_loop_that_does_not_wait_is_named_once(tmp_path, caplog, runtime):
    """100,000 readings in one step made a 97 MB journal for three experiments, silently (100,000 progress
    reports 77 MB)."""
    import logging

    def said(driver):
        lab = parse(qd_lab(**{
            "devices.spectrometer": {"driver": f"tests.twin.test_driver_habits:{driver}", "instances": 1,
                                     "steps": ["measure"], "duration": {"mean_s": 150}},
            "campaign.budget": 2, "bus.kind": "memory"}))
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            summary = run(lab, journal=tmp_path / f"{driver}.db", runtime=runtime)
        assert summary.done == 2
        return [r.getMessage() for r in caplog.records if "reports at one lab instant" in r.getMessage()]

    for driver, what in (("Chatters", "telemetry"), ("Scans", "progress")):
        tight = said(driver)
        assert len(tight) == 1 and tight[0].startswith("spectrometer: its driver made 100 reports at one lab instant")
        assert f"the last by ctx.{what}), in a loop that does not wait" in tight[0]
        assert "report between awaits of ctx.clock.sleep" in tight[0]
    assert said("Paced") == []  # as many readings, a lab-second apart


class ForgetsAwait(Raises):
    """Calls ctx.clock.sleep without ``await`` (``forgets``), or awaits a sleep it asked for earlier."""

    forgets = True

    async def run(self, step, params, sample, ctx):
        if self.forgets:
            ctx.clock.sleep(ctx.expected_s)
        else:
            later = ctx.clock.sleep(ctx.expected_s)
            ctx.progress(0.5)
            await later
        return StepResult({"peak_nm": 500.0}, sample)


class AwaitsLater(ForgetsAwait):
    forgets = False


def test_a_sleep_the_driver_did_not_await_is_named_once_per_device(tmp_path, caplog):
    """`ctx.clock.sleep(s)` without await took no lab time and nothing said so on the fast runtime (on asyncio,
    Python warns of the coroutine never awaited)."""
    import logging

    def run_with(driver):
        lab = parse(qd_lab(**{
            "devices.spectrometer": {"driver": f"tests.twin.test_driver_habits:{driver}", "instances": 2,
                                     "steps": ["measure"], "duration": {"mean_s": 600, "cv": 0}},
            "campaign.budget": 4, "bus.kind": "memory"}))  # two instances: a step that takes no time uses one
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            summary = run(lab, journal=tmp_path / f"{driver}.db", runtime="fast")
        assert summary.done == 4
        return summary, [r.getMessage() for r in caplog.records if "did not await it" in r.getMessage()]

    forgot, said = run_with("ForgetsAwait")
    assert len(said) == 1 and said[0].startswith("spectrometer-1: "), said  # once per device, not once per step
    assert all("called ctx.clock.sleep(...) during measure and did not await it, so the step waited no lab time "
               "for it: write `await ctx.clock.sleep(...)`" in m for m in said)
    awaited, said = run_with("AwaitsLater")
    assert said == [] and awaited.lab_hours > forgot.lab_hours + 600 / 3600  # the sleeps took lab time
