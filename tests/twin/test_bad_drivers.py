"""A driver that raises, returns garbage, or never answers is isolated and reported with its name."""

import asyncio
import json

import pytest

from tests.conftest import qd_lab
from twin.device.driver import StepResult
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run
from twin.scenario import parse


class Raises:
    capabilities = frozenset({"measure"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        raise RuntimeError("lamp broken")

    async def safe_state(self):
        pass


class Garbage(Raises):
    async def run(self, step, params, sample, ctx):
        return 42


class Pair(Raises):
    async def run(self, step, params, sample, ctx):
        return {"peak_nm": 600.0}, sample


class NotJson(Raises):
    async def run(self, step, params, sample, ctx):
        return StepResult({"peak_nm": object()}, sample)


class Huge(Raises):
    """A raw trace of 200,000 points as an output: over a message's 1 MiB, every receiver dropped the result and
    the step waited out its deadline ("timed_out": raise the duration, said the summary)."""

    async def run(self, step, params, sample, ctx):
        return StepResult({"peak_nm": 600.0, "trace": [0.123456789] * 200_000}, sample)


class HugeTelemetry(Raises):
    async def run(self, step, params, sample, ctx):
        ctx.telemetry({f"channel_{i}": 1.0 for i in range(100_000)})
        return StepResult({"peak_nm": 600.0}, sample)


class Exits(Raises):
    """An instrument SDK that gives up with sys.exit: it ended the whole lab, no summary, on both runtimes."""

    async def run(self, step, params, sample, ctx):
        raise SystemExit("instrument SDK gave up")


class Verbose(Raises):
    """An SDK error carrying a whole trace dump: the log printed it twice a failure (4 MB a line), and the fault
    it made was over a message's size, so the step failed as "TooLarge" instead of with the driver's words."""

    async def run(self, step, params, sample, ctx):
        raise RuntimeError("trace dump: " + "x" * 2_000_000)


class SafeStateRaises(Raises):
    async def safe_state(self):
        raise RuntimeError("arm stuck")


class Never(Raises):
    async def run(self, step, params, sample, ctx):
        await asyncio.Event().wait()


@pytest.mark.parametrize("bad, says", [("Raises", "lamp broken"), ("NotJson", "object"),
                                       ("Garbage", "Garbage.run() returned int 42, not a StepResult: return "
                                                   "StepResult(outputs, sample)"),
                                       ("Pair", "Pair.run() returned tuple ({'peak_nm': 600.0}"),
                                       ("Pair", "a tuple (outputs, sample)? return StepResult(outputs, sample)"),
                                       ("Never", "no result within"), ("SafeStateRaises", "arm stuck"),
                                       ("Exits", "SystemExit: instrument SDK gave up"),
                                       ("Verbose", "RuntimeError: trace dump: xxx"),
                                       ("Verbose", "… (2,000,026 characters)"),
                                       ("Huge", "TooLarge: the result message would be 2,"),
                                       ("HugeTelemetry", "TooLarge: the telemetry message would be ")])
@pytest.mark.parametrize("runtime", ["auto", "asyncio"])  # auto: fast, unless the driver awaits asyncio
def test_a_bad_driver_is_isolated_and_reported_by_name_and_nothing_is_lost(tmp_path, bad, says, runtime):
    lab = qd_lab(**{
        "devices.broken": {"driver": f"tests.twin.test_bad_drivers:{bad}", "instances": 1, "steps": ["measure"],
                           "duration": {"mean_s": 60, "cv": 0.1}},
        "workflow": [{"step": "synthesise", "device": "synthesiser"}, {"step": "measure", "device": "broken"}],
        "campaign.budget": 2,
    })
    summary = run(parse(lab), journal=tmp_path / "j.db", runtime=runtime)
    assert summary.abandoned == 2 and summary.done == 0  # nothing lost: every experiment is accounted for
    failed = [e for e in read_events(tmp_path / "j.db") if e["kind"] == "attempt.failed"]
    assert failed and all(e["device"] == "broken" and says in e["detail"] for e in failed), failed[:1]


class FromTheFuture(Raises):
    labtwin_api = 2


class Partial(Raises):
    capabilities = frozenset({"synthesise"})


class WordCaps(Raises):
    capabilities = "measure"  # a string, whose letters would be the steps


class NoCaps(Raises):
    capabilities = None


class SyncRun(Raises):
    def run(self, step, params, sample, ctx):  # not async: the lab would fail every step with a TypeError
        return StepResult({}, sample)


class KeyedByName(Raises):
    def __init__(self, setup):
        self.port = {"spectrometer-1": 1}[setup.name]  # a driver that expected one instance only


class TakesNothing(Raises):
    def __init__(self):  # the DriverSetup it is given has nowhere to go
        pass


class FailsInside(Raises):
    def __init__(self, setup):
        len(5)  # a TypeError of its own: not the constructor's arguments


@pytest.mark.parametrize("cls, says", [
    ("TakesNothing", "TakesNothing.__init__() takes 1 positional argument but 2 were given (a driver's constructor is "
                     "given one argument, its DriverSetup: `def __init__(self, setup)`; docs/drivers.md)"),
    ("FailsInside", "failed to start: TypeError: object of type 'int' has no len()\n"),
    ("KeyedByName", "driver 'tests.twin.test_bad_drivers:KeyedByName' for spectrometer-2 failed to start: "
                    "KeyError: 'spectrometer-2'"),
    ("FromTheFuture", "driver API 2; this labtwin speaks 1"),
    ("Partial", "runs ['synthesise'], but the scenario asks it for ['measure']"),
    ("WordCaps", "capabilities is 'measure', not a set of step names: write capabilities = frozenset({'measure'})"),
    ("NoCaps", "declares no capabilities: give its class capabilities = frozenset({'measure', ...})"),
    ("SyncRun", "run() must be `async def`: the lab awaits it"),
])
def test_version_and_capabilities_are_checked_at_load(tmp_path, cls, says):
    from twin.core.errors import DriverError

    lab = qd_lab(**{"devices.spectrometer.driver": f"tests.twin.test_bad_drivers:{cls}"})
    with pytest.raises(DriverError) as raised:
        run(parse(lab), journal=tmp_path / "j.db")
    assert says in str(raised.value) + "\n", str(raised.value)  # "\n": the message ends there


def test_a_training_episode_keeps_a_raising_driver_in_its_run_not_in_the_log(tmp_path, caplog):
    """A run warns once per raise; a training episode (thousands of them) records the fault and logs it at debug."""
    import logging

    from twin import SteppedCampaign, load_plugin

    lab = parse(qd_lab(**{
        "devices.broken": {"driver": "tests.twin.test_bad_drivers:Raises", "instances": 1, "steps": ["measure"],
                           "duration": {"mean_s": 60, "cv": 0.1}},
        "workflow": [{"step": "synthesise", "device": "synthesiser"}, {"step": "measure", "device": "broken"}],
        "campaign.budget": 2,
    }))
    with caplog.at_level(logging.WARNING):
        run(lab, journal=tmp_path / "j.db")
    assert any("driver raised during measure" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        episode, fifo = SteppedCampaign(lab), load_plugin("schedulers", "fifo")()
        while not episode.done:
            episode.answer(fifo.decide(episode.view))
        episode.close()
    assert episode.summary.abandoned == 2 and episode.summary.attempts > 0
    assert not any("driver raised" in r.getMessage() for r in caplog.records)


class OddSleep:
    """A spectrometer that waits NaN, -5, forever, a minute, '10' or None lab seconds, in turn."""

    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm"})
    WAITS = [float("nan"), -5.0, float("inf"), 60.0, "10", None]

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        self.n += 1
        await ctx.clock.sleep(self.WAITS[self.n % 6])
        return StepResult({"peak_nm": 600.0}, sample)

    async def safe_state(self):
        pass


def test_a_wait_that_is_not_a_number_is_the_drivers_error_on_both_runtimes(tmp_path):
    """Once ctx.clock.sleep('10') stopped a campaign on the fast runtime (a TypeError in the runtime's own
    loop); now a wait of a word, None or NaN fails the step as driver_error, said at the call, a negative wait is
    no wait and an infinite one times out — the same, to the lab-second, on both runtimes."""
    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:OddSleep",
                          "devices.spectrometer.instances": 1, "campaign.budget": 8}))
    fast = run(lab, journal=tmp_path / "fast.db", runtime="auto")
    slow = run(lab, journal=tmp_path / "slow.db", runtime="asyncio")
    assert fast.done + fast.abandoned == 8 and fast.done > 0 and fast.timed_out > 0
    assert fast.lab_hours == pytest.approx(slow.lab_hours, abs=1e-9)
    for field in ("done", "abandoned", "attempts", "failed_attempts", "timed_out", "abandoned_reasons"):
        assert getattr(fast, field) == getattr(slow, field), field
    reasons = {json.loads(e["detail"])["reason"] for e in read_events(tmp_path / "fast.db", "attempt.failed")}
    for said in ("clock.sleep('10'): lab seconds must be a number, not str", "not NoneType", "not NaN"):
        assert any(said in r for r in reasons), (said, reasons)



class NumpySleep(Raises):
    async def run(self, step, params, sample, ctx):
        import numpy as np

        await ctx.clock.sleep(np.float32(45.5))  # a duration from a float32 array: a number like any other
        await ctx.clock.sleep(np.int64(14))
        return StepResult({"peak_nm": 600.0}, sample)


def test_a_wait_of_numpy_seconds_is_a_wait():
    """np.float32 is no Python float: the wait failed its step, "lab seconds must be a number, not float32"."""
    from twin.tools.testing import run_step

    assert run_step(NumpySleep(None), "measure", {})[1] == pytest.approx(59.5)


class ProgressWithoutNote(Raises):
    """Reports progress as `ctx.progress(done / total)`: the note is optional (run_step and the planning
    environment took it so, while the lab's devices failed every step with a TypeError)."""

    async def run(self, step, params, sample, ctx):
        for i in range(1, 4):
            await ctx.clock.sleep(10.0)
            ctx.progress(i / 3)
        ctx.progress(1.0, "scanned")
        return StepResult({"peak_nm": 520.0}, sample)


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_progress_without_a_note_is_reported_not_a_fault(tmp_path, runtime):
    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:ProgressWithoutNote",
                          "campaign.budget": 4, "campaign.stop_on_target": False}))
    summary = run(lab, journal=tmp_path / "j.db", runtime=runtime, bus="memory")
    assert summary.done == 4 and summary.failed_attempts == 0
    notes = [json.loads(e["detail"])["body"]["note"] for e in read_events(tmp_path / "j.db", "msg.progress")]
    assert notes.count("") == 12 and notes.count("scanned") == 4


class TerminalTricks(Raises):
    """Its error would clear the screen, retitle the window and print a green tick over the line's start."""

    async def run(self, step, params, sample, ctx):
        from twin import DriverError

        raise DriverError("\x1b[2J\x1b]0;owned\x07every target met \x1b[32m✓\x1b[0m\rX\u202e")


def test_a_drivers_error_reaches_the_terminal_as_escapes_and_the_journal_as_it_was(tmp_path):
    import logging
    import yaml

    from tests.conftest import twin_cli

    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:TerminalTricks",
                                             "campaign.budget": 2, "orchestrator.retry.max_attempts": 1})))
    res = twin_cli("run", path, "--journal", tmp_path / "j.db")
    assert res.exit_code == 0, res.output
    assert "\x1b" not in res.output and "\r" not in res.output and "\u202e" not in res.output
    assert "\\x1b[2J\\x1b]0;owned\\x07every" in "".join(res.output.split()).replace("│", "")
    failed = [json.loads(e["detail"]) for e in read_events(tmp_path / "j.db", "attempt.failed")]
    assert failed and all("\x1b[2J\x1b]0;owned\x07every target met" in d["reason"] for d in failed)
    record = logging.LogRecord("twin", logging.WARNING, __file__, 1, "driver raised: %s", ("\x1b[2J\rX",), None)
    assert logging.lastResort.format(record) == "driver raised: \\x1b[2J\\x0dX"  # set by importing twin.cli
    forged = logging.LogRecord("twin", logging.WARNING, __file__, 1, "driver raised: %s",
                               ("boom\nERROR twin.alerts: devices.lost spectrometer-1",), None)
    from twin.cli.printable import FORMAT, PrintableFormatter

    for formatter in (logging.lastResort, PrintableFormatter(FORMAT)):  # a bench's lines, and twin run's
        lines = formatter.format(forged).splitlines()  # a driver's newline cannot forge a log line of its own
        assert len(lines) == 2 and lines[1] == "  ERROR twin.alerts: devices.lost spectrometer-1", lines


class SwallowsCancels(Raises):
    """Every other step never ends and ignores the lab's cancels (`except CancelledError: pass`, a vendor SDK's
    retry loop): the campaign finished, and the process then waited for the step for ever, on both runtimes."""

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        self.n += 1
        if self.n % 2:
            await ctx.clock.sleep(30)
            return StepResult({"peak_nm": 600.0}, sample)
        while True:
            try:
                await ctx.clock.sleep(10)
            except asyncio.CancelledError:
                pass


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_driver_that_swallows_the_cancel_of_its_step_does_not_keep_the_lab_from_ending(tmp_path, runtime, caplog):
    import logging

    lab = qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:SwallowsCancels",
                    "devices.spectrometer.instances": 1, "campaign.budget": 3})
    with caplog.at_level(logging.ERROR):
        summary = run(parse(lab), journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done + summary.abandoned == summary.proposed == 3 and summary.done >= 1
    said = [r.getMessage() for r in caplog.records if "went on after the lab cancelled its step" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("spectrometer: its driver") and "re-raise" in said[0]
    assert not [r for r in caplog.records if "died in the device's own handling" in r.getMessage()]


class StuckOnce(Raises):
    """The first instance's first step never ends and ignores the lab's cancel; the other instance is sound. The lab
    offered the stuck one a step every cancel grace, each answered "busy", and abandoned an experiment after 100 of
    them while the sound instance stood free."""

    def __init__(self, setup):
        self.name, self.n = setup.name, 0

    async def run(self, step, params, sample, ctx):
        self.n += 1
        while self.name in ("spectrometer", "spectrometer-1") and self.n == 1:
            try:
                await ctx.clock.sleep(10)
            except asyncio.CancelledError:
                pass
        await ctx.clock.sleep(30)
        return StepResult({"peak_nm": 600.0}, sample)


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_device_still_running_a_cancelled_step_is_quarantined_and_its_work_goes_elsewhere(tmp_path, runtime,
                                                                                            caplog):
    import logging

    lab = qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:StuckOnce",
                    "devices.spectrometer.instances": 2, "campaign.budget": 12, "campaign.stop_on_target": False})
    with caplog.at_level(logging.WARNING):
        summary = run(parse(lab), journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == summary.proposed == 12 and summary.abandoned == 0
    events = read_events(tmp_path / "j.db")
    stuck = [e for e in events if e["kind"] == "device.stuck"]
    assert [(e["device"], e["task"]) for e in stuck] == [("spectrometer-1", "e0s1")]
    # asked again only at its probes, never once per grace: one "busy" per probe at most
    probes = sum(e["kind"] == "device.probe" for e in events)
    assert 1 <= summary.stuck == summary.refused_now <= probes + 1
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("device.stuck spectrometer-1")]
    assert len(said) == 1 and "e0s1" in said[0] and "orchestrator.cancel_grace_s" in said[0] and "re-raise" in said[0]


class SlowToSafety(Raises):
    """The first instance's first step never ends; cancelled, it stops, and its safe_state() then takes 5 lab-h."""

    def __init__(self, setup):
        self.name, self.n, self.clock = setup.name, 0, None

    async def run(self, step, params, sample, ctx):
        self.n += 1
        self.clock = ctx.clock
        if self.name == "spectrometer-1" and self.n == 1:
            await ctx.clock.sleep(1e9)
        await ctx.clock.sleep(30)
        return StepResult({"peak_nm": 600.0}, sample)

    async def safe_state(self):
        if self.name == "spectrometer-1" and self.n == 1:
            await self.clock.sleep(5 * 3600)


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_device_whose_safe_state_has_not_returned_is_said_to_be_making_itself_safe(tmp_path, runtime, caplog):
    """Its step had stopped, and the lab's advice was to re-raise the cancel: what had not returned was its
    safe_state(), and that is what the device's "busy" and the lab's warning now say."""
    import logging

    lab = qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:SlowToSafety",
                    "devices.spectrometer.instances": 2, "campaign.budget": 8, "campaign.stop_on_target": False})
    with caplog.at_level(logging.WARNING):
        summary = run(parse(lab), journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == summary.proposed == 8
    stuck = [json.loads(e["detail"]) for e in read_events(tmp_path / "j.db", "device.stuck")]
    assert [s["reason"] for s in stuck] == ["busy with e0s1 (attempt 1): its safe_state() has not returned"]
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("device.stuck spectrometer-1")]
    assert len(said) == 1 and "its driver has not made the instrument safe" in said[0], said
    assert "safe_state() must return once the instrument is safe" in said[0] and "re-raise" not in said[0]


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_work_waiting_for_the_only_instance_still_running_a_cancelled_step_is_given_up_on_in_time(tmp_path, runtime):
    lab = qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:StuckOnce",
                    "devices.spectrometer.instances": 1, "campaign.budget": 6, "campaign.stop_on_target": False,
                    "campaign.give_up_after_s": 7200, "orchestrator.probe_after_s": 1800})
    summary = run(parse(lab), journal=tmp_path / "j.db", runtime=runtime)
    assert summary.abandoned == summary.proposed - summary.done >= 1
    assert all(r.startswith("no usable spectrometer") for r in summary.abandoned_reasons), summary.abandoned_reasons
    events = read_events(tmp_path / "j.db")
    # its probes (every 1800 lab-s) did not count as the type being back: said once, given up after 7200 lab-s
    assert sum(e["kind"] == "device.probe" for e in events) >= 3
    assert [e["kind"] for e in events].count("devices.unavailable") == 1
    assert "devices.available" not in [e["kind"] for e in events]
    assert summary.lab_hours < 8
    # the rest of the budget was never proposed: said, and a bench counts the run as one that ended early
    left = 6 - summary.proposed
    assert left >= 1 and summary.stopped == (f"no usable spectrometer for 7200 lab-s (campaign.give_up_after_s), "
                                             f"so {left} experiment{'s' * (left > 1)} of the budget "
                                             f"{'were' if left > 1 else 'was'} never proposed")
    assert summary.hours_compared(50.0) == 50.0
