"""Human steps: a device type whose driver is `operator` gets no command; its step waits for a confirmation (an
operator's, or in virtual time the simulated operator's after the step's expected time), with a deadline."""

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

from tests.conftest import qd_lab
from tests.twin.test_core import notes, of
from twin.campaign import CampaignCore, Decided, Operator, Presence, Proposed, Send, TimerFired
from twin.campaign.decisions import Assignment, Proposal
from twin.campaign.events import TimerKey, TimerKind
from twin.campaign.journal_read import read_events
from twin.core.errors import TwinError
from twin.runtime.checks import check
from twin.runtime.lab import run
from twin.runtime.asked_of_people import ctl_options
from twin.scenario import parse

ROOT = Path(__file__).resolve().parents[2]
HUMAN = {"devices.operator": {"driver": "operator", "instances": 1, "steps": ["load_rack"],
                              "duration": {"mean_s": 300, "cv": 0},
                              "options": {"instructions": "load the precursor rack into bay 2"}},
         "workflow": [{"step": "load_rack", "device": "operator"}, {"step": "synthesise", "device": "synthesiser"},
                      {"step": "measure", "device": "spectrometer"}]}


def dispatched_to_people(**changes):
    """A wall-clock core whose first experiment's first step was just given to the operator; and its actions."""
    s = parse(qd_lab(**{**HUMAN, "campaign.budget": 1, "clock": {"mode": "wall"}, **changes}), "lab.yaml")
    core = CampaignCore(s, secret=b"x")
    core.start(0.0)
    assert core.devices["operator"].online, "people have no presence token to wait for"
    for name in ("synthesiser", "spectrometer-1", "spectrometer-2"):
        core.feed(Presence(name, True))
    core.advance(0.0)
    core.feed(Proposed([Proposal({"concentration_mm": 5, "temperature_c": 250, "time_s": 60})]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "operator")]))
    return core, core.advance(0.0)


def test_a_human_step_is_announced_not_sent_and_done_when_confirmed():
    core, out = dispatched_to_people()
    assert not of(out, Send), "nothing is sent to people"
    (step,) = notes(out, "operator.step")
    assert step.detail["instructions"] == "load the precursor rack into bay 2" and step.detail["step"] == "load_rack"
    assert TimerKey(TimerKind.DEADLINE, "e0s0#1") in [a.key for a in out if hasattr(a, "delay")]
    assert not [a for a in out if getattr(a, "key", None) == TimerKey(TimerKind.CONFIRM, "e0s0#1")], \
        "on a wall clock only a person confirms"
    core.feed(Operator("confirm", "alice", "r1", task="e9s9"))
    assert "'e9s9' is not a human step waiting" in notes(core.advance(10.0), "operator.refused")[0].detail["why"]
    core.feed(Operator("confirm", "alice", "r2", task="e0s0"))
    out = core.advance(200.0)
    assert notes(out, "attempt.confirmed")[0].detail == {"who": "alice"} and notes(out, "attempt.done")
    assert "e0s1" in core.ready


def test_an_unconfirmed_human_step_times_out_like_any_step():
    core, _ = dispatched_to_people(**{"orchestrator.retry.max_attempts": 1})
    core.feed(TimerFired(TimerKey(TimerKind.DEADLINE, "e0s0#1")))
    out = core.advance(2000.0)
    assert notes(out, "attempt.failed")[0].detail["code"] == "timed_out" and not of(out, Send)
    assert notes(out, "experiment.abandoned") and core.devices["operator"].state == "idle"


def test_in_virtual_time_the_simulated_operator_confirms_after_the_expected_time(tmp_path):
    s = parse(qd_lab(**{**HUMAN, "campaign.budget": 3}), "lab.yaml")
    check(s)  # `twin validate`: the operator needs no installed driver and produces no outputs
    db = tmp_path / "j.db"
    summary = run(s, journal=db)
    assert summary.done == 3
    events = read_events(db)
    asked = {e["task"]: e["t_lab"] for e in events if e["kind"] == "operator.step"}
    confirmed = {e["task"]: (e["t_lab"], json.loads(e["detail"])["who"]) for e in events
                 if e["kind"] == "attempt.confirmed"}
    assert set(asked) == set(confirmed) == {"e0s0", "e1s0", "e2s0"}
    assert all(abs(confirmed[t][0] - asked[t] - 300) < 1e-6 and confirmed[t][1] == "simulated operator"
               for t in asked)
    assert summary.utilisation["operator"] > 0


def test_a_misspelt_option_for_people_is_named():
    """Their instructions are all their options: `instrutions` would have shown an empty operator.step."""
    import pytest

    from twin.core.errors import ScenarioError

    misspelt = {**HUMAN, "devices.operator": {**HUMAN["devices.operator"], "options": {"instrutions": "x"}}}
    with pytest.raises(ScenarioError, match=r"devices\.operator\.options\.instrutions: people \('operator'\) take "
                                            "only instructions"):
        check(parse(qd_lab(**misspelt), "lab.yaml"))


@pytest.mark.parametrize("clock, bus, warned", [("scaled", "memory", True), ("wall", "memory", True),
                                                ("scaled", "zenoh", False), ("virtual", "memory", False)])
def test_people_a_live_lab_cannot_hear_from_are_warned_of(caplog, clock, bus, warned):
    """On a memory bus nothing outside the process reaches the campaign: `twin ctl confirm` cannot, and every step
    of theirs would time out with nobody told why."""
    lab = parse(qd_lab(**{**HUMAN, "clock": {"mode": clock, "speed": 20}, "bus": {"kind": bus}}), "lab.yaml")
    with caplog.at_level("WARNING", logger="twin.runtime.checks"):
        check(lab)
    said = [r.getMessage() for r in caplog.records if "memory bus" in r.getMessage()]
    assert said == ([f"on a {clock} clock and a memory bus, which twin ctl cannot reach (it reaches a campaign over "
                     "Zenoh only): devices.operator is people (driver: operator), whose steps wait for `twin ctl "
                     "confirm` and would each time out. Run it with --bus zenoh --listen tcp/127.0.0.1:7447 (and twin "
                     "ctl … --connect there)"] if warned else [])


@pytest.mark.process
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_a_human_step_waiting_when_the_campaign_died_or_stopped_still_waits_for_its_person_when_resumed(tmp_path, sig):
    """People have no health key to ask: a resume once asked, heard nothing and declared the person gone
    ("left the bus"), abandoning the step and leaving every later human step without anyone to give it to."""
    lab = qd_lab(**{**HUMAN, "campaign.budget": 1, "clock": {"mode": "scaled", "speed": 600},
                    "orchestrator.retry.max_attempts": 1})
    path, db = tmp_path / "lab.yaml", tmp_path / "j.db"
    path.write_text(yaml.safe_dump(lab))
    proc = subprocess.Popen([sys.executable, "-m", "twin", "run", str(path), "--journal", str(db), "--quiet"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "LABTWIN_FLUSH_EVERY": "1"})
    while proc.poll() is None and not any(e["kind"] == "operator.step" for e in _events(db)):
        time.sleep(0.01)
    proc.send_signal(sig)
    proc.wait()
    assert proc.returncode in (-signal.SIGKILL, 130)
    said = " ".join(proc.stderr.read().decode().split())  # the lab is on a memory bus: no twin ctl reaches it
    assert ("operator.step e0s0: load_rack on operator waits for a person — load the precursor rack into bay 2. "
            "Nobody can say it is done: twin ctl reaches a campaign over Zenoh, and this lab's bus is memory; "
            "unconfirmed within ") in said, said
    assert not any(e["kind"] == "attempt.failed" for e in _events(db)), "the step ended before the campaign did"
    resumed = subprocess.run([sys.executable, "-m", "twin", "resume", str(db), "--json"], cwd=ROOT,
                             capture_output=True, text=True, timeout=120)
    assert resumed.returncode == 0 and "does not answer" not in resumed.stderr, resumed.stderr[-2000:]
    events = read_events(db)
    assert not [e for e in events if e["kind"] == "device.lost"]
    ended = [json.loads(e["detail"])["code"] for e in events if e["kind"] == "attempt.failed"]
    assert ended == ["timed_out"], ended  # nobody confirmed it: its deadline, as for any step
    # and the step is announced again when the campaign resumes, for whoever pages people from the announcements
    said = [(e["task"], e["attempt"], json.loads(e["detail"])) for e in events if e["kind"] == "operator.step"]
    assert len(said) == 2 and said[0][:2] == said[1][:2] and "again" not in said[0][2], said
    assert said[1][2]["again"].startswith("the campaign was resumed") and said[1][2]["step"] == said[0][2]["step"]
    assert said[1][2]["instructions"] == said[0][2]["instructions"] and said[1][2]["params"] == said[0][2]["params"]
    assert ("operator.step e0s0: load_rack on operator waits for a person (again: the campaign was resumed; the step "
            "still waits for twin ctl confirm) — load the precursor rack") in " ".join(resumed.stderr.split())


def _events(db):
    try:
        return read_events(db)
    except (TwinError, sqlite3.Error):  # not written yet
        return []


@pytest.mark.parametrize("bus, campaign, options", [
    ({"kind": "zenoh", "listen": ["tcp/127.0.0.1:7447"]}, None, "--lab t --connect tcp/127.0.0.1:7447"),
    ({"kind": "zenoh", "connect": ["tcp/10.0.0.1:7447"], "listen": []}, "dots",
     "--lab t --campaign dots --connect tcp/10.0.0.1:7447"),  # a lab behind a router: where its operator goes too
    ({"kind": "zenoh"}, None, "--lab t --connect ENDPOINT (a port the lab chose: give it --listen tcp/127.0.0.1:PORT "
                              "to know it)"),
    ({"kind": "memory"}, None, None),
])
def test_the_twin_ctl_a_person_is_told_to_run_reaches_the_lab_as_its_scenario_says(bus, campaign, options):
    assert ctl_options(parse(qd_lab(bus=bus), "lab.yaml"), campaign) == options
