"""A driver that raises, returns garbage, or never answers is isolated and reported with its name."""

import asyncio
import json
import re

import pytest

from tests.conftest import qd_lab
from twin.device.driver import StepResult
from twin.campaign.journal import read_events
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


@pytest.mark.parametrize("cls, says", [
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
    with pytest.raises(DriverError, match=re.escape(says)):
        run(parse(lab), journal=tmp_path / "j.db")


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


class OddSpectra:
    """A spectrometer whose spectra are JSON but not curves: the fifth of each kind is fine, the others not."""

    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm", "spectrum"})
    ODD = [{"y": ["high", "low"]}, {"y": 3.0}, {"y": [[1.0, 2.0], [3.0, 4.0]]}, {"start_nm": "blue", "y": [1.0]},
           {"x": [1.0, 2.0]}, {"y": [1.0, None, 2.0]}, {"y": []}, "a spectrum", {"y": [1e308, -1e308, 0.5]}]

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        self.n += 1
        spectrum = self.ODD[self.n % len(self.ODD)] if self.n % 5 else {"start_nm": 400.0, "step_nm": 2.0,
                                                                          "y": [0.0, 0.5, 1.0, 0.5]}
        return StepResult({"peak_nm": 404.0, "spectrum": spectrum}, sample)

    async def safe_state(self):
        pass


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_spectra_that_are_not_curves_are_not_drawn_and_change_nothing_else(tmp_path, runtime):
    """The recorder skips what it cannot draw: the campaign runs as it does unrecorded, the good spectra are drawn."""
    from tests.rrd import read_rrd
    from twin.view.watch import RecordOptions

    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:OddSpectra",
                          "devices.spectrometer.instances": 1,
                          "campaign.budget": 20}))
    plain = run(lab, journal=tmp_path / "plain.db", runtime=runtime)
    drawn = run(lab, journal=tmp_path / "drawn.db", runtime=runtime, record=RecordOptions(save=tmp_path / "r.rrd"))
    assert drawn.done == plain.done == 20 and drawn.attempts == plain.attempts == 40 and not drawn.failed_attempts
    strips = [r["LineStrips2D:strips"][0] for r in read_rrd(tmp_path / "r.rrd")["spectra/measurement"]]
    good = [[400.0, 300.0], [402.0, 150.0], [404.0, 0.0], [406.0, 150.0]]
    assert strips.count(good) == 4  # experiments 5, 10, 15, 20
    assert all(s == good or len(s) == 3 for s in strips), strips  # [1e308, -1e308, .5] at infinity, [1, None, 2] a gap


class OddNumbers:
    """A spectrometer whose peak comes as null (a NaN), a string, a boolean, or a number, in turn; its telemetry
    has a NaN reading every other time."""

    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm"})
    PEAKS = [float("nan"), "630", True, 630.0]

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        ctx.telemetry({"lamp_k": float("nan") if self.n % 2 else 300.0})
        self.n += 1
        return StepResult({"peak_nm": self.PEAKS[(self.n - 1) % 4]}, sample)

    async def safe_state(self):
        pass


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_an_output_that_is_not_a_number_is_never_scored_and_is_said_once(tmp_path, runtime, caplog):
    """null, "630" and true are not 630: no target is met by them (true once scored as 1), the first is noted and
    logged naming the output, and a NaN telemetry reading is an invalid message on either runtime."""
    import logging

    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_drivers:OddNumbers",
                          "devices.spectrometer.instances": 1, "campaign.budget": 8, "campaign.max_in_flight": 1,
                          "chemistry.targets": [{"name": "one", "outputs": {"peak_nm": {"value": 1, "tol": 5}}},
                                                {"name": "R", "outputs": {"peak_nm": {"value": 630, "tol": 5}}}]}))
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == 8 and "one" not in summary.targets_met_h and "R" in summary.targets_met_h
    noted = read_events(tmp_path / "j.db", "output.unscored")
    assert len(noted) == 1 and "peak_nm = null is not a number" in noted[0]["detail"]
    assert [r for r in caplog.records if "output.unscored" in r.getMessage()]
    assert summary.invalid_messages == 4  # the telemetry of steps 2, 4, 6, 8
    invalid = read_events(tmp_path / "j.db", "message.invalid")
    assert len(invalid) == 4 and all("readings" in e["detail"] and e["device"] == "spectrometer" for e in invalid)


def test_a_target_scores_only_finite_numbers():
    from twin.scenario.targets import score, unscorable

    target = parse(qd_lab()).chemistry.targets[0]  # R: peak_nm 630 ± 5
    assert score({"peak_nm": 630}, target) == 0 and score({"peak_nm": 640.0}, target) == 1.0
    for odd in (None, "630", True, float("nan"), float("inf")):
        assert score({"peak_nm": odd}, target) == float("inf"), odd
    assert unscorable({"peak_nm": "630", "other": "x"}, [target]) == {"peak_nm": "630"}
    assert unscorable({"intensity": 1.0}, [target]) == {}  # missing is not listed: not every workflow measures it


class OddSample:
    """A synthesiser whose samples are not what the lab can carry: in turn, t_made a word, null, a NaN, a list,
    far in the future, and a sample that is a number; every seventh is fine."""

    capabilities = frozenset({"synthesise"})
    SAMPLES = [{"t_made": "yesterday"}, {"t_made": None}, {"t_made": float("nan")}, {"t_made": [1]},
               {"t_made": 1e300}, 5]

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        self.n += 1
        if self.n % 7 == 0:
            return StepResult({}, {"kind": "qd", "peak_nm": 630.0, "fwhm_nm": 30.0, "amplitude": 1.0,
                                   "t_made": ctx.clock.now()})
        return StepResult({}, self.SAMPLES[self.n % 7 - 1])

    async def safe_state(self):
        pass


def test_a_result_whose_sample_the_lab_cannot_carry_fails_its_attempt_alike_on_both_runtimes(tmp_path, caplog):
    """Once it stopped the campaign (float(None)); now each is a failed attempt naming the device and the field,
    retried like any other, and the two runtimes agree to the attempt (a sample that is not an object is an
    invalid message on a bus, so in the fast runtime too, where it is now logged as a bus receiver logs it)."""
    import logging

    lab = parse(qd_lab(**{"devices.synthesiser.driver": "tests.twin.test_bad_drivers:OddSample",
                          "campaign.budget": 6, "orchestrator.quarantine_after": 100}))
    with caplog.at_level(logging.WARNING):
        fast = run(lab, journal=tmp_path / "fast.db", runtime="auto")
    assert any(r.getMessage().startswith("dropped a message from synthesiser: invalid message from synthesiser")
               for r in caplog.records)
    slow = run(lab, journal=tmp_path / "slow.db", runtime="asyncio")
    assert fast.done + fast.abandoned == 6 and fast.done >= 1
    for field in ("done", "abandoned", "attempts", "failed_attempts", "invalid_messages", "timed_out"):
        assert getattr(fast, field) == getattr(slow, field), field
    assert fast.invalid_messages > 0  # the sample that is a number
    reasons = [json.loads(e["detail"])["reason"] for e in read_events(tmp_path / "fast.db", "attempt.failed")
               if json.loads(e["detail"])["code"] == "driver_error"]
    assert {"'yesterday'", "'None'", "'[1]'", "after the lab's time now"} <= {
        w for r in reasons for w in ("'yesterday'", "'None'", "'[1]'", "after the lab's time now") if w in r}
    assert all(r.startswith("synthesiser returned a result the lab cannot use") for r in reasons)


def test_what_a_result_must_hold():
    from twin.campaign.results import problem

    assert problem({"outputs": {}, "sample": {"t_made": 10.0}}, now=20.0) == ""
    assert problem({"outputs": {}, "sample": None}, now=0.0) == ""
    assert problem({"outputs": {}, "sample": {"kind": "qd"}}, now=0.0) == ""  # no t_made: made when it arrives
    assert "t_made" in problem({"outputs": {}, "sample": {"t_made": True}}, now=0.0)
    assert "t_made" in problem({"outputs": {}, "sample": {"t_made": float("inf")}}, now=0.0)
    assert "after the lab's time" in problem({"outputs": {}, "sample": {"t_made": 100.0}}, now=20.0)
    assert "JSON object" in problem({"outputs": [1], "sample": None}, now=0.0)


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
