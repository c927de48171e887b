"""A scheduler plugin that raises or answers garbage: the fallback rule decides that time, the campaign goes on
(it used to end with the plugin's traceback), and the two runtimes agree."""

import pytest

from tests.conftest import qd_lab
from twin.campaign.decisions import Assignment
from twin.campaign.journal_read import read_events
from twin.runtime.checked_scheduler import assignments
from twin.runtime.lab import run
from twin.scenario import parse


class OddScheduler:
    """In turn: None, a list of tuples, a word, an Assignment of no names, a raise, and a proper answer."""

    def __init__(self, **_):
        self.n = 0

    def decide(self, view):
        self.n += 1
        k = self.n % 6
        if k == 0:
            return None
        if k == 1:
            return [(r.task, "spectrometer-1") for r in view.ready]
        if k == 2:
            return "fifo"
        if k == 3:
            return [Assignment(task=None, device=3)]
        if k == 4:
            raise RuntimeError("model file missing")
        out, used = [], set()
        for r in view.ready:
            for d in view.free:
                if d.name not in used and d.device_type == r.device_type:
                    out.append(Assignment(r.task, d.name))
                    used.add(d.name)
                    break
        return out


class SlowOddScheduler(OddScheduler):
    """One that takes its time (a model behind it), so that a live lab asks it off the event loop."""

    runs_long = True


def test_a_slow_scheduler_covered_in_its_worker_thread_is_journalled_by_the_loop(tmp_path):
    """On a scaled clock a slow scheduler is asked in a worker thread, where its checks fell back and noted that
    from the thread: a shared lab's journal (SQLite) refused the write ("objects created in a thread can only be
    used in that same thread") and the lab stopped on a JournalError. Found on a busy machine, where the
    OddScheduler's decisions took over 5 ms and so moved to the worker."""
    from tests.twin.shared_labs import LAB, SMALL, assert_accounted
    from twin.runtime.lab import prepare
    from twin.runtime.shared_run import run_shared

    slow = {**SMALL, "campaigns.0.campaign.scheduler": "tests.twin.test_bad_schedulers:SlowOddScheduler"}
    s = prepare(LAB, seed=1, clock="scaled", speed=20_000, bus="memory", overrides=slow)
    out = run_shared(s, tmp_path, handle_signals=False)
    assert_accounted(out)
    dots = out.campaigns["dots"]
    assert dots.done + dots.abandoned == 6 and not dots.stopped and dots.scheduler_fallbacks > 0, dots
    said = [e["detail"] for e in read_events(tmp_path / "dots.db", "scheduler.fallback")]
    assert any("raised RuntimeError('model file missing')" in s for s in said), said


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_scheduler_that_raises_or_answers_garbage_is_covered_by_the_fallback_rule(tmp_path, runtime):
    lab = parse(qd_lab(**{"campaign.scheduler": "tests.twin.test_bad_schedulers:OddScheduler",
                          "campaign.budget": 10}))
    summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == 10 and summary.abandoned == 0
    assert summary.scheduler_fallbacks > 0 and summary.decisions > summary.scheduler_fallbacks  # it decided too
    said = [e["detail"] for e in read_events(tmp_path / "j.db", "scheduler.fallback")]
    assert any("raised RuntimeError('model file missing')" in s for s in said), said
    assert any("answered 'None', not a list of Assignment(task, device)" in s for s in said), said
    assert all("'tests.twin.test_bad_schedulers:OddScheduler'" in s for s in said)
    # each time it answered properly again after the rule decided, that is journalled too, in turn with them
    turns = [e["kind"] for e in read_events(tmp_path / "j.db") if e["kind"].startswith("scheduler.")]
    assert turns[0] == "scheduler.fallback" and "scheduler.recovered" in turns, turns
    assert not any(a == b == "scheduler.recovered" for a, b in zip(turns, turns[1:])), turns  # once per recovery
    assert [e["detail"] for e in read_events(tmp_path / "j.db", "scheduler.recovered")][0] == \
        "\"scheduler 'tests.twin.test_bad_schedulers:OddScheduler' decides again\""


def test_both_runtimes_decide_alike_with_it(tmp_path):
    lab = parse(qd_lab(**{"campaign.scheduler": "tests.twin.test_bad_schedulers:OddScheduler",
                          "campaign.budget": 10}))
    fast = run(lab, journal=tmp_path / "fast.db", runtime="auto")
    slow = run(lab, journal=tmp_path / "slow.db", runtime="asyncio")
    assert fast.scheduler_fallbacks == slow.scheduler_fallbacks and fast.lab_hours == pytest.approx(slow.lab_hours)


def test_what_counts_as_an_answer():
    class Named:
        task, device = "e1s0", "spectrometer-2"

    assert assignments([Assignment("e0s0", "spectrometer-1"), Named()]) == [
        Assignment("e0s0", "spectrometer-1"), Assignment("e1s0", "spectrometer-2")]
    assert assignments(()) == [] and assignments(iter([])) == []
    for odd in (None, "fifo", b"x", {"e0s0": "spectrometer-1"}, 3, [("e0s0", "spectrometer-1")],
                [Assignment(None, "x")]):
        assert assignments(odd) is None, odd


@pytest.mark.parametrize("clock", ["virtual", "scaled"])
def test_in_a_lab_of_several_campaigns_too(tmp_path, caplog, clock):
    """The campaigns of a shared lab go on as well, the fallback journalled and counted in each campaign's
    summary as for a campaign on its own."""
    import logging

    from tests.twin.shared_labs import LAB, SMALL, assert_accounted
    from twin.runtime.lab import prepare
    from twin.runtime.shared_run import run_shared

    odd = {**SMALL, "campaigns.0.campaign.scheduler": "tests.twin.test_bad_schedulers:OddScheduler",
           "campaigns.0.campaign.stop_on_target": False}  # its whole budget, however soon a run meets R, G and B
    s = prepare(LAB, seed=1, clock=clock, speed=50_000, bus="memory", overrides=odd)
    with caplog.at_level(logging.WARNING):
        out = run_shared(s, tmp_path, handle_signals=False)
    assert_accounted(out)
    assert out.campaigns["dots"].done + out.campaigns["dots"].abandoned == 6
    assert any("raised RuntimeError('model file missing'): fifo decides instead" in r.getMessage()
               for r in caplog.records)
    dots = out.campaigns["dots"]
    assert dots.scheduler_fallbacks > 0 and all(c.scheduler_fallbacks == 0 for n, c in out.campaigns.items()
                                                if n != "dots")
    noted = [e for e in read_events(tmp_path / "dots.db") if e["kind"] == "scheduler.fallback"]
    assert any("model file missing" in e["detail"] for e in noted)


class Patient:
    """Starts a step only while another runs: with nothing running it waits, for an event that never comes."""

    def decide(self, view):
        if not any(d.busy_until is not None for d in view.devices):
            return []
        return [Assignment(view.ready[0].task, d.name) for d in view.free
                if d.device_type == view.ready[0].device_type][:1]


class FirstThenPatient(Patient):
    """Starts the first step, then is Patient: it waits while that one runs (legitimately), then for nothing."""

    def __init__(self):
        self.started = False

    def decide(self, view):
        if not self.started:
            self.started = True
            r = view.ready[0]
            return [Assignment(r.task, next(d.name for d in view.free if d.device_type == r.device_type))]
        return super().decide(view)


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_scheduler_that_waits_with_nothing_running_ends_the_campaign_saying_so_not_at_max_lab_hours(
        tmp_path, runtime):
    """A wait with no device busy and nothing due waits for nothing: the lab jumped to campaign.max_lab_hours
    (10,000 lab-h) and ended "max_lab_hours reached" with its experiments pending. Now it ends at once, naming the
    scheduler; a wait while a step runs is a wait like any other."""
    for scheduler, ran in (("Patient", 0), ("FirstThenPatient", 1)):
        lab = parse(qd_lab(**{"campaign.scheduler": f"tests.twin.test_bad_schedulers:{scheduler}",
                              "campaign.budget": 3, "campaign.max_lab_hours": 5000}))
        summary = run(lab, journal=tmp_path / f"{scheduler}.db", runtime=runtime)
        assert "answered wait with no device busy and nothing due" in summary.stopped, summary.stopped
        assert f"test_bad_schedulers:{scheduler}" in summary.stopped
        assert summary.lab_hours < 1 and summary.attempts == ran
        assert summary.proposed == summary.done + summary.abandoned + summary.pending  # accounted for


@pytest.mark.parametrize("stalled", [("dots",), ("dots", "catalyst"), "lab"])
def test_a_shared_lab_whose_schedulers_wait_for_nothing_ends_in_virtual_time(tmp_path, stalled):
    """A lab of several campaigns idled to max_lab_hours (10,001 lab-h) when every campaign still running had
    steps ready and a scheduler that waited with the whole lab idle. It ends once the others are done (or have
    started: catalyst starts at 1 lab-h), naming each stalled campaign's scheduler."""
    from tests.twin.shared_labs import LAB, SMALL
    from twin.runtime.lab import prepare
    from twin.runtime.shared_run import run_shared

    if stalled == "lab":  # one scheduler for the lab (orchestrator.lab_scheduler) that waits: both stall
        patient, stalled = {"orchestrator.lab_scheduler": "tests.twin.test_bad_schedulers:Patient"}, ()
    else:
        patient = {f"campaigns.{['dots', 'catalyst'].index(n)}.campaign.scheduler":
                   "tests.twin.test_bad_schedulers:Patient" for n in stalled}
    s = prepare(LAB, seed=1, clock="virtual", bus="memory", overrides={**SMALL, **patient})
    out = run_shared(s, tmp_path, handle_signals=False)
    assert out.lab_hours < 24
    if not stalled:
        for c in out.campaigns.values():
            assert c.done == 0 and c.pending > 0, c
            assert "the lab's scheduler (tests.twin.test_bad_schedulers:Patient) answered wait" in c.stopped
        return
    for name, c in out.campaigns.items():
        if name in stalled:
            assert c.done == 0 and c.pending > 0 and "answered wait with no device busy" in c.stopped, c
            assert f"{name}: tests.twin.test_bad_schedulers:Patient" in c.stopped
        else:
            assert c.done + c.abandoned == 4 and c.pending == 0, c


def test_a_bench_counts_a_stalled_run_at_the_campaigns_limit_not_as_the_shortest():
    """Ended at once, a stall would read as a makespan of nothing: the best scheduler of the bench."""
    from twin.tools.planner_bench import trial
    from twin.tools.scheduler_bench import one

    lab = parse(qd_lab(**{"campaign.budget": 3, "campaign.max_lab_hours": 5000}))
    stalled = one(lab, "tests.twin.test_bad_schedulers:Patient", 0)
    assert stalled.makespan_s == 5000 * 3600 and "answered wait" in stalled.stopped
    assert one(lab, "fifo", 0).makespan_s < 5 * 3600
    assert trial(lab, "random@tests.twin.test_bad_schedulers:Patient", 0).lab_hours == 5000


def test_a_live_lab_whose_scheduler_waits_for_nothing_says_so_once_and_stays_open_to_its_operator(scenario_of):
    """On a live clock an operator (or an instrument coming back) can still move the lab: the stall is an alert
    in the journal and the log, not an end."""
    from twin.campaign import Ask, CampaignCore, Decided, Note, Presence, Proposed
    from twin.campaign.decisions import Proposal

    core = CampaignCore(scenario_of(**{"clock": {"mode": "scaled", "speed": 3600}, "campaign.budget": 1}))
    core.start(0.0)
    for name in core.devices:
        core.feed(Presence(name, True))
    core.advance(0.0)
    core.feed(Proposed([Proposal({"concentration_mm": 5, "temperature_c": 250, "time_s": 60})]))
    assert [a for a in core.advance(0.0) if isinstance(a, Ask)][0].what == "schedule"
    core.feed(Decided([]))
    notes = [a for a in core.advance(0.0) if isinstance(a, Note)]
    assert [n.kind for n in notes] == ["scheduler.stalled"] and not core.stopping
    from twin.campaign.decisions import Assignment
    from twin.campaign.events import Operator
    from twin.campaign.operator import status

    assert "answered wait with no device busy" in status(core, 0.0)["stalled"]  # `twin ctl status` says it
    core.feed(Operator("pause", "alice"))
    core.feed(Operator("resume", "alice"))  # the lab is asked again; this time the scheduler starts the step
    ask = [a for a in core.advance(10.0) if isinstance(a, Ask) and a.what == "schedule"][0]
    step = ask.view.ready[0]
    device = next(d for d in ask.view.free if d.device_type == step.device_type)
    core.feed(Decided([Assignment(step.task, device.name)]))
    core.advance(10.0)
    assert status(core, 10.0)["stalled"] == ""  # a stall a later wait for nothing would say again


class WrongDevices:
    """Every step to a free device of another type: pairs of which none can run, on every decision."""

    def decide(self, view):
        return [Assignment(r.task, d.name) for r in view.ready for d in view.free
                if d.device_type != r.device_type][:2]


class OneGoodOneBad(WrongDevices):
    """A pair that can run, and one that cannot: the first is carried out, the second refused."""

    def decide(self, view):
        good = [Assignment(r.task, d.name) for r in view.ready for d in view.free if d.device_type == r.device_type]
        return good[:1] + [Assignment("e999s0", good[0].device)] if good else []


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_scheduler_whose_pairs_cannot_run_is_covered_by_the_fallback_rule(tmp_path, runtime):
    """Each pair was refused (scheduler.invalid) and nothing else happened: the lab idled to
    campaign.max_lab_hours, 10,000 lab-h, and ended "max_lab_hours reached" with every experiment pending, the
    scheduler unnamed. An answer of which no pair can run is a mistake the fallback rule covers, as a garbled one."""
    lab = parse(qd_lab(**{"campaign.scheduler": "tests.twin.test_bad_schedulers:WrongDevices",
                          "campaign.budget": 4}))
    summary = run(lab, journal=tmp_path / "w.db", runtime=runtime)
    assert summary.done == 4 and summary.lab_hours < 24 and not summary.stopped, summary
    assert summary.scheduler_fallbacks == summary.decisions > 0
    (said,) = [e["detail"] for e in read_events(tmp_path / "w.db", "scheduler.fallback")]  # once, not per decision
    assert "scheduler 'tests.twin.test_bad_schedulers:WrongDevices' answered nothing that can run (e0s0 → " in said
    assert "the step needs a synthesiser" in said, said
    assert not read_events(tmp_path / "w.db", "scheduler.invalid")

    lab = parse(qd_lab(**{"campaign.scheduler": "tests.twin.test_bad_schedulers:OneGoodOneBad",
                          "campaign.budget": 4}))
    summary = run(lab, journal=tmp_path / "g.db", runtime=runtime)
    assert summary.done == 4 and summary.scheduler_fallbacks == 0
    refused = read_events(tmp_path / "g.db", "scheduler.invalid")
    assert refused and all("'e999s0' is not ready" in e["detail"] for e in refused)


def test_a_scheduler_whose_pairs_the_orchestrator_refuses_with_the_lab_idle_is_stalled_not_waited_for(scenario_of):
    """The pairs the view cannot judge (a device an operator barred, a stock gone) are refused by the
    orchestrator; when all of an answer's are and nothing runs, no event would ask again: a stall, as a wait is."""
    from twin.campaign import Ask, CampaignCore, Decided, Note, Presence, Proposed
    from twin.campaign.decisions import Proposal

    for mode, speed in (("virtual", 1.0), ("scaled", 3600.0)):
        core = CampaignCore(scenario_of(**{"clock": {"mode": mode, "speed": speed}, "campaign.budget": 1}))
        core.start(0.0)
        for name in core.devices:
            core.feed(Presence(name, True))
        core.advance(0.0)
        core.feed(Proposed([Proposal({"concentration_mm": 5, "temperature_c": 250, "time_s": 60})]))
        ask = [a for a in core.advance(0.0) if isinstance(a, Ask) and a.what == "schedule"][0]
        core.feed(Decided([Assignment(ask.view.ready[0].task, "nowhere-1")]))
        notes = [a for a in core.advance(0.0) if isinstance(a, Note)]
        assert notes[0].kind == "scheduler.invalid", notes
        if mode == "virtual":
            assert "answered only pairs that cannot be carried out (1 refused" in core.stopping, core.stopping
        else:
            assert notes[-1].kind == "scheduler.stalled" and not core.stopping
            assert "answered only pairs that cannot be carried out" in notes[-1].detail


class ExitingScheduler:
    def decide(self, view):
        raise SystemExit(3)


class ExitingPlanner:
    def propose(self, n, history, pending):
        raise SystemExit("no licence")


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_plugin_that_calls_sys_exit_is_covered_like_one_that_raises(tmp_path, runtime):
    """SystemExit is no Exception: a scheduler or planner that called sys.exit ended the lab, summary unwritten."""
    lab = parse(qd_lab(**{"campaign.scheduler": "tests.twin.test_bad_schedulers:ExitingScheduler",
                          "campaign.budget": 3}))
    summary = run(lab, journal=tmp_path / "s.db", runtime=runtime)
    assert summary.done == 3 and summary.scheduler_fallbacks == summary.decisions > 0
    lab = parse(qd_lab(**{"campaign.planner": "tests.twin.test_bad_schedulers:ExitingPlanner",
                          "campaign.budget": 3}))
    summary = run(lab, journal=tmp_path / "p.db", runtime=runtime)
    assert "SystemExit('no licence')" in summary.stopped and summary.proposed == 0


def test_names_held_as_numpy_strings_are_names():
    """A scheduler that picks names out of a numpy array answers np.str_: every decision went to the fallback."""
    import numpy as np

    names = np.array(["e0s0", "synthesiser-1"])
    (a,) = assignments([Assignment(names[0], names[1])])
    assert (a.task, a.device) == ("e0s0", "synthesiser-1") and type(a.task) is type(a.device) is str
    assert assignments([Assignment(np.int64(3), "synthesiser-1")]) is None


def test_a_class_that_is_no_plugin_is_sent_to_the_page_that_says_what_one_is():
    """A scheduler or planner was sent to docs/drivers.md and docs/architecture.md, which do not say."""
    from twin.core import plugins
    from twin.core.errors import DriverError, PluginError

    here = "tests.twin.test_bad_schedulers"
    for kind, cls, error, page in (("planners", "Patient", PluginError, "docs/plugins.md"),
                                   ("schedulers", "ExitingPlanner", PluginError, "docs/plugins.md"),
                                   ("devices", "Patient", DriverError, "docs/drivers.md")):
        with pytest.raises(error, match=rf"is the class {cls}, not a .* \(see {page}\)$"):
            plugins.load(kind, f"{here}:{cls}")


def test_every_alert_is_a_warning_or_an_error_in_the_viewer_log():
    """What a runtime logs as an alert (a stalled scheduler among them) the viewer's log does not file as INFO."""
    from twin.campaign.events import ALERTS
    from twin.view.observer import _level

    assert "scheduler.stalled" in ALERTS
    assert {kind: _level(kind) for kind in ALERTS if _level(kind) not in ("WARN", "ERROR")} == {}


@pytest.mark.parametrize("lab_scheduler", [False, True])
def test_a_live_shared_lab_whose_schedulers_wait_for_nothing_says_so_in_each_journal(tmp_path, lab_scheduler):
    """On a live clock a shared lab stalled silently until the campaigns' max_lab_hours. Now each stalled campaign
    notes scheduler.stalled (an alert, not an end: an operator may still move the lab), once, naming each
    scheduler, and not before the second campaign (at 1 lab-h) has started (its steps could have woken the
    first); the campaigns still end at their limit with their experiments accounted for. The alert is one of
    the lab's inputs, so a lab killed before its campaigns' journals had it gets it back on resuming. The same
    with one scheduler for the lab (orchestrator.lab_scheduler), named instead."""
    import sqlite3

    from tests.twin.shared_labs import LAB, SMALL
    from twin.runtime.lab import prepare
    from twin.runtime.resume_lab import resume_lab
    from twin.runtime.shared_run import run_shared

    who = "tests.twin.test_bad_schedulers:Patient"
    patient = {"orchestrator.lab_scheduler": who} if lab_scheduler else {
        f"campaigns.{i}.campaign.scheduler": who for i in (0, 1)}
    limits = {f"campaigns.{i}.campaign.max_lab_hours": 2 for i in (0, 1)}
    s = prepare(LAB, seed=1, clock="scaled", speed=20_000, bus="memory", overrides={**SMALL, **patient, **limits})
    out = run_shared(s, tmp_path, handle_signals=False)
    for name, c in out.campaigns.items():
        assert c.done == 0 and c.pending > 0 and "max_lab_hours" in c.stopped, c
        said = [e for e in read_events(tmp_path / f"{name}.db") if e["kind"] == "scheduler.stalled"]
        assert len(said) == 1 and said[0]["t_lab"] >= 3600, said
        if lab_scheduler:
            assert f"the lab's scheduler ({who}) answered wait" in said[0]["detail"]
        else:
            assert f"dots: {who}" in said[0]["detail"] and f"catalyst: {who}" in said[0]["detail"]
    for db in tmp_path.glob("*.db"):  # as if killed before the campaigns' journals had the alert
        with sqlite3.connect(db) as c:
            c.execute("DELETE FROM run WHERE key='summary'")
            c.execute("DELETE FROM events WHERE seq >= (SELECT seq FROM events WHERE kind='scheduler.stalled')")
    resume_lab(tmp_path, handle_signals=False)
    for name in out.campaigns:
        kinds = [e["kind"] for e in read_events(tmp_path / f"{name}.db")]
        assert kinds.count("scheduler.stalled") == 1 and kinds.index("scheduler.stalled") < kinds.index(
            "campaign.resumed"), kinds


def test_a_paused_campaign_of_a_shared_lab_is_not_called_stalled():
    """Waiting because an operator paused it is not a scheduler's wait for nothing: with one campaign paused, the
    lab is not said to stall (its operator resumes it), and the alert comes back only if it does again."""
    from tests.twin.shared_labs import LAB, SMALL
    from twin.campaign import Ask, Decided, Presence, Proposed
    from twin.campaign.decisions import Proposal
    from twin.campaign.events import Operator
    from twin.campaign.sharing import SharedLab
    from twin.runtime.lab import prepare
    from twin.scenario.sharing import campaign_scenarios

    who = "tests.twin.test_bad_schedulers:Patient"
    lab = prepare(LAB, seed=1, overrides={**SMALL, "campaigns.1.start_h": 0, "clock.mode": "scaled",
                                          **{f"campaigns.{i}.campaign.scheduler": who for i in (0, 1)}})
    shared = SharedLab(lab, campaign_scenarios(lab))
    shared.start(0.0)
    for device in shared.online:
        shared.feed_device(Presence(device, True))

    def settle(now: float) -> None:  # every question answered: mid-box proposals, and the schedulers' wait
        while shared.has_work:
            for name, a in shared.advance(now):
                if type(a) is Ask and a.what == "plan":
                    box = shared.cores[name].s.chemistry.parameters
                    mid = {k: (p.low + p.high) / 2 for k, p in box.items()}
                    shared.feed(name, Proposed([Proposal(dict(mid)) for _ in range(a.n)]))
                elif type(a) is Ask:
                    shared.feed(name, Decided([]))

    settle(1.0)
    why, stalled = shared.newly_stalled()
    assert stalled == ["dots", "catalyst"] and f"dots: {who}, catalyst: {who}" in why
    shared.feed("dots", Operator("pause", "alice"))
    settle(2.0)
    assert shared.newly_stalled() == ("", []) and all(not c.stalled for c in shared.cores.values())
    shared.feed("dots", Operator("resume", "alice"))
    settle(3.0)
    assert shared.newly_stalled()[1] == ["dots", "catalyst"]
