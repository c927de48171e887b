"""An operator's acts on the campaign core: pause (and pause now), resume, abort, retry, stop — each one note,
refused with the reason where it cannot apply, and replayed from the journal's inputs like any other input."""

from twin.campaign import Ask, Decided, Operator, Presence, Proposed, Send, TimerFired
from twin.campaign.decisions import Assignment, Proposal
from twin.campaign.events import TimerKey, TimerKind
from twin.campaign.replay import decode_input, encode, rebuild
from twin.core.messages import Kind

from tests.twin.test_core import SECRET, msg, notes, of, started

P = {"concentration_mm": 5, "temperature_c": 250, "time_s": 60}


def running(scenario_of, device="synthesiser", **changes):
    """A core with experiment 0's first step on ``device`` (a synthesiser) and experiment 1's waiting for one."""
    core, _ = started(scenario_of, **{"campaign.budget": 2, **changes})
    core.feed(Proposed([Proposal(P), Proposal(P)]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", device)]))
    out = core.advance(0.0)
    assert [s.task for s in of(out, Send)] == ["e0s0"]
    return core


def op(core, command, t, **kw):
    core.feed(Operator(command, kw.pop("who", "alice"), kw.pop("ref", f"r{t}"), **kw))
    return core.advance(t)


def test_a_paused_campaign_dispatches_nothing_until_resumed(scenario_of):
    core = running(scenario_of)
    out = op(core, "pause", 1.0, reason="refilling")
    (paused,) = notes(out, "operator.pause")
    assert paused.detail == {"who": "alice", "ref": "r1.0", "reason": "refilling"} and core.paused_by == "alice"
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0}))
    out = core.advance(60.0)
    assert notes(out, "attempt.done") and not of(out, Ask), "paused: the scheduler is not even asked"
    assert sorted(core.ready) == ["e0s1", "e1s0"]
    assert "already paused by alice" in notes(op(core, "pause", 61.0, who="bob"), "operator.refused")[0].detail["why"]
    out = op(core, "resume", 62.0, who="bob")
    assert notes(out, "operator.resume") and core.paused_by == ""
    (ask,) = of(out, Ask)
    assert ask.what == "schedule" and {r.task for r in ask.view.ready} == {"e0s1", "e1s0"}
    assert "not paused" in notes(op(core, "resume", 63.0), "operator.refused")[0].detail["why"]


def test_pause_now_takes_the_step_out_of_the_lab_without_spending_one_of_its_attempts(scenario_of):
    core = running(scenario_of, **{"orchestrator.retry.max_attempts": 1})
    out = op(core, "pause", 5.0, now=True)
    (cancel,) = [s for s in of(out, Send) if s.kind == Kind.CANCEL]
    assert cancel.task == "e0s0" and "paused by alice" in cancel.body["reason"]
    assert notes(out, "attempt.cancelled") and notes(out, "operator.pause")[0].detail["now"] is True
    assert "e0s0" in core.ready and core.devices["synthesiser"].state == "busy"  # until it says it stopped
    core.feed(msg(Kind.FAULT, "synthesiser", "e0s0", 1, code="cancelled", reason="cancelled"))
    out = core.advance(6.0)
    assert notes(out, "attempt.cancel_acknowledged") and not of(out, Ask)
    out = op(core, "resume", 7.0)
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    out = core.advance(7.0)
    (again,) = of(out, Send)
    assert (again.task, again.attempt) == ("e0s0", 2)  # a new attempt number: a late answer to the first is no match
    # one attempt allowed, and it fails: the stopped one did not count, so this is a real failure, then abandoned
    core.feed(msg(Kind.FAULT, "synthesiser", "e0s0", 2, code="failed", reason="clogged"))
    out = core.advance(8.0)
    (gone,) = notes(out, "experiment.abandoned")
    assert "failed 2 time(s)" in gone.detail["reason"] and core.counts.retried == 0


def test_abort_ends_an_experiment_in_the_lab_and_a_finished_one_is_refused_with_its_state(scenario_of):
    core = running(scenario_of, **{"campaign.budget": 3})  # a third to come: the campaign goes on after both
    out = op(core, "abort", 2.0, experiment=0, reason="wrong vial")
    assert [s.task for s in of(out, Send) if s.kind == Kind.CANCEL] == ["e0s0"]
    (gone,) = notes(out, "experiment.abandoned")
    assert gone.experiment == 0 and gone.detail["reason"] == "aborted by alice: wrong vial"
    assert notes(out, "operator.abort")[0].experiment == 0 and 0 not in core.active
    out = op(core, "abort", 3.0, experiment=1)
    assert notes(out, "experiment.abandoned")[0].experiment == 1 and "e1s0" not in core.ready
    why = notes(op(core, "abort", 4.0, experiment=0), "operator.refused")[0].detail["why"]
    assert why == "experiment 0 is already abandoned (aborted by alice: wrong vial)"
    assert "there is no experiment 7" in notes(op(core, "abort", 5.0, experiment=7), "operator.refused")[0].detail["why"]
    assert "name the experiment" in notes(op(core, "retry", 6.0), "operator.refused")[0].detail["why"]
    assert "unknown command 'explode'" in notes(op(core, "explode", 7.0), "operator.refused")[0].detail["why"]


def test_retry_reopens_an_abandoned_experiment_and_it_can_finish(scenario_of):
    core = running(scenario_of, **{"orchestrator.retry.max_attempts": 1})
    core.feed(msg(Kind.FAULT, "synthesiser", "e0s0", 1, code="failed", reason="clogged"))
    out = core.advance(10.0)
    assert notes(out, "experiment.abandoned") and core.experiments[0].status == "abandoned"
    out = op(core, "retry", 11.0, experiment=0)
    assert notes(out, "experiment.reopened")[0].experiment == 0 and notes(out, "operator.retry")
    assert core.experiments[0].status == "pending" and "e0s0" in core.ready
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    core.advance(11.0)
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 2, outputs={}, sample={"t_made": 70.0}))
    core.advance(70.0)
    assert core.experiments[0].stage == 1 and "e0s1" in core.ready
    assert "is running" in notes(op(core, "retry", 71.0, experiment=0), "operator.refused")[0].detail["why"]


def test_retry_during_a_back_off_sends_the_step_at_once(scenario_of):
    core = running(scenario_of, **{"orchestrator.retry.backoff_s": 1000, "orchestrator.retry.jitter": 0})
    core.feed(msg(Kind.FAULT, "synthesiser", "e0s0", 1, code="failed", reason="clogged"))
    out = core.advance(10.0)
    assert notes(out, "task.retry") and "e0s0" not in core.ready
    out = op(core, "retry", 12.0, experiment=0)
    assert "e0s0" in core.ready and notes(out, "operator.retry")
    assert TimerKey(TimerKind.RETRY, "e0s0") in [a.key for a in out if type(a).__name__ == "CancelTimer"]
    core.feed(TimerFired(TimerKey(TimerKind.RETRY, "e0s0")))  # were the timer to fire anyway: nothing twice
    core.advance(13.0)
    assert list(core.ready).count("e0s0") == 1


def test_stop_by_an_operator_ends_the_campaign_with_its_name(scenario_of):
    core = running(scenario_of)
    out = op(core, "stop", 3.0, who="carol", reason="end of shift")
    assert core.finished and core.stopping == "stopped by carol: end of shift"
    assert notes(out, "operator.stop") and not notes(out, "operator.refused")


def test_operator_acts_are_replayed_from_the_journal_inputs(scenario_of):
    act = Operator("pause", "alice", "1700000000000000000", None, True, "refill")
    assert decode_input(encode(act)) == act
    s = scenario_of(**{"campaign.budget": 2})
    # the inputs a live runtime journals: start, everyone present, proposals, a dispatch, then the pause
    batches = [(0.0, {"start": True}),
               (0.0, {"events": [encode(Presence(d, True)) for d in ("spectrometer-1", "spectrometer-2",
                                                                      "synthesiser")]}),
               (0.0, {"events": [encode(Proposed([Proposal(P), Proposal(P)]))]}),
               (0.0, {"events": [encode(Decided([Assignment("e0s0", "synthesiser")]))]}),
               (5.0, {"events": [encode(act)]})]
    rebuilt = rebuild(s, batches, secret=SECRET)
    assert rebuilt.core.paused_by == "alice" and "e0s0" in rebuilt.core.ready
    assert rebuilt.asked is None, "paused: the rebuilt core asks nobody for anything"


async def test_a_virtual_time_campaign_answers_status_and_refuses_acts(scenario_of):
    import json

    from twin.core.clock import LabClock
    from twin.runtime.control import ControlDesk

    core = running(scenario_of)
    fed = []
    desk = ControlDesk(core, LabClock("virtual"), fed.append, lambda: None)
    st = json.loads(await desk.serve("labtwin/t/control/status", b""))
    assert st["ok"] and st["status"]["state"] == "running" and st["status"]["in_lab"][0]["task"] == "e0s0"
    no = json.loads(await desk.serve("labtwin/t/control/pause", b'{"who": "alice"}'))
    assert not no["ok"] and "virtual time" in no["error"] and fed == []


def test_the_progress_line_says_who_paused_the_campaign():
    from twin.cli.campaign_bar import waiting_for

    assert "paused by alice (twin ctl resume)" in waiting_for([], "alice")
    assert "waiting: no usable reactor" in waiting_for(["reactor"], "alice") and waiting_for([]) == ""
    said = waiting_for([], "", ["argon", "jars@mill-1"])
    assert "waiting for a refill of argon, jars@mill-1 (twin ctl refill)" in said


def test_retry_of_an_experiment_whose_step_is_short_of_stock_reopens_it_waiting(scenario_of):
    stock = {"precursor": {"level": 4, "used_by": {"synthesise": 3}}}
    core = running(scenario_of, **{"orchestrator.retry.max_attempts": 1, "consumables": stock})
    core.feed(msg(Kind.FAULT, "synthesiser", "e0s0", 1, code="failed", reason="clogged"))
    core.advance(10.0)
    out = op(core, "retry", 11.0, experiment=0)
    assert notes(out, "operator.retry") and core.experiments[0].status == "pending"
    assert "e0s0" in core.starved and core.starved["e0s0"].attempts == 1  # numbered on, waiting for a refill


def test_people_are_not_devices_to_serve_or_to_ask_for_their_health(tmp_path):
    """`twin device health` asked staffed_lab's technician too, who has no health key: "answered: no" and exit 1 on
    a lab in good health; `twin device serve --id technician` said "no device instance 'technician'; the scenario
    has ['technician', ...]"."""
    from pathlib import Path

    from tests.conftest import twin_cli
    from twin.runtime.lab import prepare
    from twin.runtime.serve import _devices

    lab = Path(__file__).resolve().parents[2] / "scenarios" / "staffed_lab.yaml"
    assert _devices(prepare(lab)) == ["synthesiser-1", "synthesiser-2", "spectrometer"]  # what health asks
    res = twin_cli("device", "serve", lab, "--id", "technician", "--connect", "tcp/127.0.0.1:9")
    assert res.exit_code != 0
    said = " ".join(res.output.split())
    assert "'technician' is people (driver: operator), not a device: the campaign serves their steps itself" in said
    assert "the devices are ['synthesiser-1', 'synthesiser-2', 'spectrometer']" in said
