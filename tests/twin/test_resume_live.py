"""A live (scaled-clock) campaign SIGKILLed mid-step is resumed from its journal: nothing lost, nothing twice."""

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import assert_adopted_once, qd_lab
from twin.campaign.journal_read import read_events, read_run
from twin.runtime.resume import resume

ROOT = Path(__file__).resolve().parents[2]
TWIN = [sys.executable, "-m", "twin"]


def _count(db, sql):
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as c:
            return c.execute(sql).fetchone()[0]
    except sqlite3.Error:
        return 0


def _killed(lab: dict, db: Path, when) -> None:
    """``twin run`` of ``lab`` (a scenario's mapping) on journal ``db``, SIGKILLed once ``when()`` holds."""
    path = db.with_name("lab.yaml")
    path.write_text(yaml.safe_dump(lab))
    _signalled(["run", str(path), "--journal", str(db)], when, signal.SIGKILL)
    assert "summary" not in read_run(db), "the campaign finished before it could be killed"


def _signalled(args: list[str], when, sig: int) -> int:
    """``twin ARGS --quiet``, sent ``sig`` once ``when()`` holds; its exit status. Its journal is committed row by
    row: a live run's rows wait for its next command otherwise, and ``when()`` would read the lab as it was (on a
    busy machine the experiments it waited for were journalled only as the campaign ended)."""
    proc = subprocess.Popen(TWIN + args + ["--quiet"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "LABTWIN_FLUSH_EVERY": "1"})
    deadline = time.monotonic() + 60
    while proc.poll() is None and time.monotonic() < deadline:
        if when():
            break
        time.sleep(0.01)
    os.kill(proc.pid, sig)
    proc.wait()
    return proc.returncode


@pytest.mark.process
def test_a_killed_live_campaign_resumes_where_it_was(tmp_path):
    lab = qd_lab(**{"campaign.budget": 8, "clock": {"mode": "scaled", "speed": 600},
                    "devices.spectrometer.duration": {"mean_s": 120, "cv": 0.0}})
    db = tmp_path / "j.db"
    in_lab = "SELECT COUNT(*) FROM events WHERE kind='attempt.running' AND task LIKE '%s1'"
    measured = "SELECT COUNT(*) FROM events WHERE kind='attempt.done' AND task LIKE '%s1'"

    def measuring() -> bool:  # two experiments done, and a measurement in the lab
        return _count(db, "SELECT COUNT(*) FROM events WHERE kind='experiment.done'") >= 2 and \
            _count(db, in_lab) > _count(db, measured)

    _killed(lab, db, measuring)
    before = read_events(db)
    done_before = {e["experiment"] for e in before if e["kind"] == "experiment.done"}
    # its progress bar goes on from there (it started at 0/8, lab 0 s)
    from twin.cli.campaign_bar import resumed_from
    from twin.runtime.resume import recorded

    assert resumed_from(db, recorded(db)[0]) == (len(done_before), pytest.approx(max(e["t_lab"] for e in before)))

    resumed = subprocess.run(TWIN + ["resume", str(db), "--json"], cwd=ROOT, capture_output=True, text=True,
                             timeout=120)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    summary = json.loads(resumed.stdout)
    events = read_events(db)
    assert any(e["kind"] == "campaign.resumed" for e in events)
    finals = [e["experiment"] for e in events if e["kind"] in ("experiment.done", "experiment.abandoned")]
    assert len(finals) == len(set(finals)), "an experiment finished twice"
    assert done_before <= set(finals)
    assert summary["proposed"] == 8 and summary["done"] + summary["abandoned"] + summary["pending"] == 8
    assert summary["done"] == 8, summary["abandoned_reasons"]
    # the measurement that was in the lab when the process died was taken up again after the resume
    resumed_at = next(e["t_lab"] for e in events if e["kind"] == "campaign.resumed")
    lost = [e for e in events if e["kind"] == "attempt.failed" and e["t_lab"] >= resumed_at
            and "when the campaign resumed" in (e["detail"] or "")]
    assert lost, "the in-process device died with the campaign: its step must be found lost and retried"
    assert all(any(x["kind"] == "attempt.done" and x["task"] == e["task"] for x in events) for e in lost)


@pytest.mark.process
def test_ctrl_c_resumed_killed_and_resumed_again_sends_its_cancelled_steps_again_without_a_strike(tmp_path):
    lab = qd_lab(**{"campaign.budget": 10, "clock": {"mode": "scaled", "speed": 600},
                    "devices.spectrometer.duration": {"mean_s": 120, "cv": 0.0}})
    db = tmp_path / "j.db"
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(lab))

    def measuring(done: int):  # experiments done, and a measurement in the lab
        return lambda: _count(db, "SELECT COUNT(*) FROM events WHERE kind='experiment.done'") >= done and _count(
            db, "SELECT COUNT(*) FROM events WHERE kind='attempt.running' AND task LIKE '%s1'") > _count(
            db, "SELECT COUNT(*) FROM events WHERE kind='attempt.done' AND task LIKE '%s1'")

    assert _signalled(["run", str(path), "--journal", str(db)], measuring(2), signal.SIGINT) == 130
    first = read_run(db)["summary"]
    assert first["stopped"] == "interrupted (SIGINT)" and first["resumable"] and first["pending"] > 0
    assert _signalled(["resume", str(db)], measuring(4), signal.SIGKILL) == -signal.SIGKILL
    assert "summary" not in read_run(db), "a resumed campaign killed reads as killed, not as the stop before"
    done_before = _count(db, "SELECT COUNT(*) FROM events WHERE kind='experiment.done'")
    last_done = max(e["t_lab"] for e in read_events(db) if e["kind"] == "experiment.done")
    progress: list[tuple[int, float]] = []
    summary = resume(db, on_progress=lambda core: progress.append((core.finished_count, core.now))).to_dict()
    # where it was: its experiments done and its lab time (not 0 done at lab 0 s until the first step ends); what
    # is in the lab then depends on how soon the devices, which died with it, answered that their steps are lost
    assert progress[0][0] == done_before >= 4 and progress[0][1] >= last_done > 0, "a progress bar starts where it was"
    assert summary["done"] == summary["proposed"] == 10 and not summary["stopped"], summary
    events = read_events(db)
    finals = [e["experiment"] for e in events if e["kind"] in ("experiment.done", "experiment.abandoned")]
    assert sorted(finals) == list(range(10)), "each experiment finished once"
    cancelled = [e["task"] for e in events if e["kind"] == "attempt.cancelled"]
    assert cancelled, "the stop cancelled what was in the lab"
    sent_again = [e for e in events if e["kind"] == "task.refused" and "when the campaign was stopped" in e["detail"]]
    assert sorted(e["task"] for e in sent_again) == sorted(cancelled)  # a "not now": no attempt used, no strike
    assert all(any(x["kind"] == "attempt.done" and x["task"] == t for x in events) for t in cancelled)
    assert [json.loads(e["detail"]).get("after") for e in events if e["kind"] == "campaign.resumed"] == [
        "interrupted (SIGINT)", None]
    stopped_at = next(e["t_lab"] for e in events if e["kind"] == "campaign.stopping")
    assert next(e["t_lab"] for e in events if e["kind"] == "campaign.resumed") >= stopped_at  # lab time went on
    assert not [e for e in events if e["kind"] == "attempt.failed" and '"cancelled"' in e["detail"]]


@pytest.mark.process
def test_a_result_finished_while_the_campaign_was_dead_is_adopted_once(tmp_path):
    from tests.twin.test_device_process import free_port
    from tests.twin.test_distributed_lab import start

    router = f"tcp/127.0.0.1:{free_port()}"
    speed = 200.0
    lab = qd_lab(**{"campaign.budget": 6, "campaign.max_in_flight": 2,
                    "devices.synthesiser.duration": {"mean_s": 20, "cv": 0.0},
                    "devices.spectrometer.duration": {"mean_s": 200, "cv": 0.0},
                    "clock": {"mode": "scaled", "speed": speed},
                    "bus": {"kind": "zenoh", "listen": [], "connect": [router], "lease_ms": 1000},
                    "orchestrator.startup_s": 4000, "orchestrator.orphan_grace_s": 100000,
                    "orchestrator.timeout_slack_s": 4000})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(lab))
    db = tmp_path / "j.db"
    procs = {"router": start(["router", "--listen", router], "router")}
    procs["spec2"] = start(["device", "serve", str(path), "--id", "spectrometer-2", "--connect", router,
                            "--clock", "scaled", "--speed", str(speed)], "ready spectrometer-2")
    try:
        lab_run = subprocess.Popen(TWIN + ["run", str(path), "--journal", str(db), "--quiet", "--external",
                                           "spectrometer-2"], cwd=ROOT, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.PIPE)
        on_spec2 = "SELECT COUNT(*) FROM events WHERE kind='attempt.running' AND device='spectrometer-2'"
        deadline = time.monotonic() + 60
        while lab_run.poll() is None and time.monotonic() < deadline and _count(db, on_spec2) == 0:
            time.sleep(0.01)
        os.kill(lab_run.pid, signal.SIGKILL)  # the campaign dies with a measurement running on the remote device
        lab_run.wait()
        assert "summary" not in read_run(db)
        killed_task = next(e["task"] for e in reversed(read_events(db))
                           if e["kind"] == "attempt.running" and e["device"] == "spectrometer-2")
        time.sleep(1.5)  # the remote measurement (1 s of wall time) finishes while nobody listens
        resumed = subprocess.run(TWIN + ["resume", str(db), "--json"], cwd=ROOT, capture_output=True, text=True,
                                 timeout=120)
        assert resumed.returncode == 0, resumed.stderr[-3000:]
    finally:
        for p in procs.values():
            p.kill()
            p.wait()
    summary = json.loads(resumed.stdout)
    events = read_events(db)
    assert_adopted_once(events, killed_task, "spectrometer-2")
    finals = [e["experiment"] for e in events if e["kind"] in ("experiment.done", "experiment.abandoned")]
    assert len(finals) == len(set(finals))
    assert summary["done"] + summary["abandoned"] + summary["pending"] == summary["proposed"] == 6


@pytest.mark.parametrize("damage", ['{"events": [["bogus", 1]]}', '{"events": [["msg"]]}', "not json",
                                    '{"events": [["operator", "stop"]]}', '{"events": [["stop"]]}'])
def test_damaged_inputs_are_named_and_nothing_runs(tmp_path, damage):
    from twin.core.errors import TwinError
    from twin.runtime.lab import run
    from twin.runtime.resume import resume
    from twin.scenario import parse

    db = tmp_path / "j.db"
    run(parse(qd_lab(**{"campaign.budget": 2, "clock": {"mode": "scaled", "speed": 100000}})), journal=db)
    with sqlite3.connect(db) as c:  # as if killed, then damaged
        c.execute("DELETE FROM run WHERE key='summary'")
        c.execute("UPDATE inputs SET batch=? WHERE seq=3", (damage,))
        events = c.execute("SELECT COUNT(*) FROM events").fetchone()[0]
    with pytest.raises(TwinError, match=r"input batch 3 of \d+|inputs are damaged"):
        resume(db)
    assert _count(db, "SELECT COUNT(*) FROM events") == events


@pytest.mark.process
def test_a_campaign_still_running_is_not_resumed_a_second_time(tmp_path):
    from tests.twin.test_device_process import free_port
    from tests.twin.test_distributed_lab import start

    router = f"tcp/127.0.0.1:{free_port()}"
    lab = qd_lab(**{"campaign.budget": 50, "clock": {"mode": "scaled", "speed": 100},
                    "bus": {"kind": "zenoh", "listen": [], "connect": [router], "lease_ms": 1000}})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(lab))
    db = tmp_path / "j.db"
    router_proc = start(["router", "--listen", router], "router")
    lab_run = subprocess.Popen(TWIN + ["run", str(path), "--journal", str(db), "--quiet"], cwd=ROOT,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and _count(db, "SELECT COUNT(*) FROM events WHERE kind='attempt.done'") < 1:
            time.sleep(0.05)
        second = subprocess.run(TWIN + ["resume", str(db)], cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert lab_run.poll() is None, "the campaign ended before the second resume was tried"
    finally:
        lab_run.kill()
        lab_run.wait()
        router_proc.kill()
        router_proc.wait()
    assert second.returncode == 2
    assert "still running" in second.stderr and "orchestrator/alive" in second.stderr


@pytest.mark.process
def test_a_killed_live_job_shop_resumes_on_the_plan_its_scheduler_made(tmp_path):
    """The rl scheduler plays a job shop ahead and the lab follows the plan. Resumed after SIGKILL, it dropped the
    plan at once ("the campaign had started before the plan was made") and the policy decided the rest; now the
    plan goes on with the steps not started, and those in the lab when the process died are put back where the plan
    had them when they come back from their retries."""
    lab = {"name": "ft06", "lab": "ft06", "jobshop": {"file": str(ROOT / "scenarios" / "jobshop" / "ft06.txt")},
           "clock": {"mode": "scaled", "speed": 15}, "orchestrator": {"timeout_slack_s": 5},
           "campaign": {"scheduler": f"rl:{ROOT / 'agents' / 'policies' / 'jobshop_scheduler.zip'}",
                        "local_search": 500}}
    db = tmp_path / "j.db"
    _killed(lab, db, lambda: _count(db, "SELECT COUNT(*) FROM events WHERE kind='attempt.done'") >= 8)
    resumed = subprocess.run(TWIN + ["resume", str(db), "--json"], cwd=ROOT, capture_output=True, text=True,
                             timeout=120)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "left the plan" not in resumed.stderr, resumed.stderr[-3000:]
    summary = json.loads(resumed.stdout)
    assert summary["done"] == 6 and summary["abandoned"] == 0
    # the steps in the lab died with the process: asked about before their deadlines are re-armed, they are lost
    # and retried at once, not timed out and cancelled (a cancel nobody answers held each device 60 lab-s)
    events = read_events(db)
    resumed_at = next(e["seq"] for e in events if e["kind"] == "campaign.resumed")
    after = [e["kind"] for e in events if e["seq"] > resumed_at]
    assert "attempt.cancel_unanswered" not in after and after.count("task.retry") >= 1


def test_a_rebuild_leaves_out_each_stop_that_was_resumed_and_the_last_one():
    from twin.campaign.replay import RESUMED, unstopped

    msg, op_stop = ["presence", "a", True], ["operator", "stop", "carol", "", None, False, "lunch", "", "", "", 0, ""]
    batches = [(0.0, {"start": True}), (1.0, {"events": [msg, ["stop", "interrupted (SIGINT)"], msg]}),
               (2.0, {"events": [msg]}), (3.0, {RESUMED: "interrupted (SIGINT)"}), (4.0, {"events": [msg]}),
               (5.0, {"events": [op_stop]}), (6.0, {"events": [msg]})]
    kept, stopped, at = unstopped(batches)
    assert kept == [(0.0, {"start": True}), (1.0, {"events": [msg]}), (4.0, {"events": [msg]})]
    assert (stopped, at) == ("stopped by carol: lunch", 5.0)  # the last stop, not yet resumed: its steps cancelled
    kept, stopped, at = unstopped(batches[:4] + [(4.0, {"events": [msg, ["stop", "nothing left", False]]})])
    assert (stopped, at) == ("", 0.0) and kept[-1] == (4.0, {"events": [msg, ["stop", "nothing left", False]]})


@pytest.mark.parametrize("report", [[1, 2], "x", None, {"recent": 5}, {"recent": [[1]]}, {"recent": [["e0s1", 1, 7]]},
                                    {"running": "yes", "recent": [None, "e0s1"]}, {"recent": {"e0s1": 1}}])
def test_a_health_report_of_another_shape_says_nothing_of_the_step(report):
    """A device that is not ours may answer `health` with anything: the resume had unpacked it blindly."""
    from twin.runtime.take_over import reported

    assert reported(report, "e0s1", 1) == (False, None)


def test_a_health_report_says_the_step_runs_or_how_it_ended():
    from twin.runtime.take_over import reported

    done, cancelled = '{"kind": "result"}', '{"kind": "fault", "body": {"code": "cancelled"}}'
    assert reported({"running": ["e0s1", 1]}, "e0s1", 1) == (True, None)
    assert reported({"recent": [["e0s0", 1, "x"], ["e0s1", 1, done]]}, "e0s1", 1) == (False, done)
    assert reported({"recent": [["e0s1", 1, cancelled]]}, "e0s1", 1) == (False, cancelled)  # killed: taken
    assert reported({"recent": [["e0s1", 1, cancelled]]}, "e0s1", 1, "interrupted (SIGINT)") == (False, None)


@pytest.mark.process
@pytest.mark.parametrize("planner", ["random", "fixed"])
def test_a_resumed_live_campaigns_planner_goes_on_where_it_was_not_from_its_first_proposal(tmp_path, planner):
    """A new planner made for the resume started again: random (and lhs) drew the first experiments again, the fixed
    list proposed its first entries again — 12 experiments for a list of 8. Each proposal now is the one an
    unbroken run makes (the same seed, in virtual time)."""
    given = [{"params": {"x": 0.1 * i}} for i in range(8)]
    lab = {"name": "ovens", "lab": "ovens", "chemistry": {"parameters": {"x": {"low": 0, "high": 1}}},
           "devices": {"oven": {"driver": "machine", "steps": ["bake"], "instances": 2,
                                "duration": {"mean_s": 600, "cv": 0.1}}},
           "workflow": [{"step": "bake", "device": "oven"}],
           "campaign": {"planner": planner, "budget": 8, "max_in_flight": 2,
                        **({"planner_options": {"proposals": given}} if planner == "fixed" else {})},
           "clock": {"mode": "scaled", "speed": 600}, "bus": {"kind": "memory"}}
    db = tmp_path / "j.db"
    _killed(lab, db, lambda: _count(db, "SELECT COUNT(*) FROM events WHERE kind='experiment.done'") >= 3)
    resumed = subprocess.run(TWIN + ["resume", str(db), "--json"], cwd=ROOT, capture_output=True, text=True,
                             timeout=120)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert json.loads(resumed.stdout)["proposed"] == 8
    proposed = [json.loads(e["detail"]) for e in read_events(db) if e["kind"] == "experiment.proposed"]
    unbroken = tmp_path / "unbroken.db"
    subprocess.run(TWIN + ["run", str(db.with_name("lab.yaml")), "--clock", "virtual", "--journal", str(unbroken),
                           "--quiet"], cwd=ROOT, check=True, capture_output=True, timeout=120)
    assert proposed == [json.loads(e["detail"]) for e in read_events(unbroken) if e["kind"] == "experiment.proposed"]
    assert len({p["x"] for p in proposed}) == 8  # none twice


class Remembers:
    """A planner that notes what it was asked, and takes ``wait`` wall seconds a question."""

    def __init__(self, wait=0.0):
        self.asked, self.wait = [], wait

    def propose(self, n, history, pending):
        self.asked.append((n, [o.params["x"] for o in history], pending))
        time.sleep(self.wait)
        return []


def test_a_resumed_planner_is_asked_its_questions_again_in_order_for_thirty_seconds_at_most(monkeypatch, caplog):
    """Each question with the history it had (a prefix of the rebuilt core's) and its pending experiments; and not
    for ever: GP-BO asked 400 questions again refits for many minutes, and its proposals follow from the history."""
    import logging

    from twin.campaign.decisions import Outcome
    from twin.campaign.replay import PlannerAsk
    from twin.runtime import checked_planner

    history = [Outcome({"x": float(i)}, {"y": 1.0}, 1.0) for i in range(4)]
    asks = [PlannerAsk(3, 0, ()), PlannerAsk(1, 2, ({"x": 2.0},)), PlannerAsk(2, 4, ())]
    quick = checked_planner.caught_up(Remembers(), "remembers", asks, history)
    assert quick.inner.asked == [(3, [], []), (1, [0.0, 1.0], [{"x": 2.0}]), (2, [0.0, 1.0, 2.0, 3.0], [])]
    monkeypatch.setattr(checked_planner, "CATCH_UP_S", 0.2)
    with caplog.at_level(logging.WARNING):
        slow = checked_planner.caught_up(Remembers(wait=0.05), "slow", [PlannerAsk(1, 0, ())] * 100, [])
    assert 2 <= len(slow.inner.asked) < 100
    said = [r.getMessage() for r in caplog.records if "was asked again" in r.getMessage()]
    assert said == [f"planner 'slow' was asked again {len(slow.inner.asked)} of the 100 questions it had answered "
                    "before the campaign stopped, in 0.2 s, and not the rest: it goes on from the history it is given "
                    "(a planner whose proposals follow from it, as GP-BO's do, proposes as it would have; one that "
                    "keeps a place in a list of its own may propose an experiment again)"]
