"""The campaign core as a specification: feed it events, read its actions. No loop, no bus, no clock."""

from types import SimpleNamespace

from twin.campaign import (Ask, CampaignCore, Decided, DeviceMessage, Finished, Note, Presence, Proposed, Send,
                           SetTimer, TimerFired)
from twin.campaign import operator
from twin.campaign.events import CancelTimer, TimerKey, TimerKind, alert_text
from twin.campaign.decisions import Assignment, Proposal
from twin.core.messages import Kind

QD = {"concentration_mm": 5, "temperature_c": 250, "time_s": 60}  # a proposal inside qd_lab's box


def notes(actions, kind=None):
    return [a for a in actions if isinstance(a, Note) and (kind is None or a.kind == kind)]


def of(actions, cls):
    return [a for a in actions if isinstance(a, cls)]


def started(scenario_of, **changes):
    """A core with every device present, asked for its first experiments."""
    core = CampaignCore(scenario_of(**changes), secret=SECRET)
    out = core.start(0.0)
    assert of(out, SetTimer)[0].key.kind == TimerKind.STARTUP  # nobody is on the bus yet
    for name in core.devices:
        core.feed(Presence(name, True))
    out = core.advance(0.0)
    assert [n.device for n in notes(out, "device.online")] == sorted(core.devices)
    return core, out


SECRET = b"a test's secret"


def msg(kind, device, task, attempt, token=None, key="", **body):
    """A device's message, with the token the orchestrator gave the attempt unless ``token`` says otherwise."""
    if token is None:
        token = CampaignCore.token(SimpleNamespace(secret=SECRET, campaign_id="c1"), task, attempt)
    return DeviceMessage(kind, device, task, attempt, body, b"{}", key, token)


def test_the_campaign_starts_when_every_device_is_present_whatever_their_order_and_comings_and_goings(scenario_of):
    """Every device but one ("last") arrives, one of them ("leaver") leaves again, the last arrives: still one short;
    the leaver back: the campaign begins (each pair, as a set of the devices still to come sees them in any order)."""
    lab = scenario_of(**{"devices.synthesiser.instances": 3, "devices.spectrometer.instances": 2})
    names = sorted(CampaignCore(lab, secret=SECRET).devices)
    began = lambda out: bool(of(out, Ask))  # noqa: E731
    for last in names:
        for leaver in [n for n in names if n != last]:
            core = CampaignCore(lab, secret=SECRET)
            core.start(0.0)
            order = [(n, True) for n in names if n != last] + [(leaver, False), (last, True)]
            for t, (name, alive) in enumerate(order, 1):
                core.feed(Presence(name, alive))
                assert not began(core.advance(float(t))), (last, leaver, name, alive)
            core.feed(Presence(leaver, True))
            out = core.advance(10.0)
            assert began(out) and CancelTimer(TimerKey(TimerKind.STARTUP)) in out, (last, leaver)


def test_a_step_goes_out_when_the_scheduler_assigns_it_and_finishes_with_its_result(scenario_of):
    core, out = started(scenario_of, **{"campaign.budget": 1})
    (ask,) = of(out, Ask)
    assert ask.what == "plan" and ask.n == 1
    core.feed(Proposed([Proposal({"concentration_mm": 5, "temperature_c": 250, "time_s": 60})]))
    out = core.advance(0.0)
    (ask,) = of(out, Ask)
    assert ask.what == "schedule" and [r.task for r in ask.view.ready] == ["e0s0"]
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    out = core.advance(0.0)
    (send,) = of(out, Send)
    assert (send.device, send.kind, send.task, send.attempt) == ("synthesiser", Kind.COMMAND, "e0s0", 1)
    assert TimerKey(TimerKind.DEADLINE, "e0s0#1") in [a.key for a in of(out, SetTimer)]
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0}))
    out = core.advance(60.0)
    assert notes(out, "attempt.done") and of(out, Ask)[0].view.ready[0].task == "e0s1"


def test_a_timed_out_device_gets_no_work_until_it_answers_the_cancel(scenario_of):
    core, out = started(scenario_of, **{"campaign.budget": 2, "devices.spectrometer.instances": 1,
                                        "workflow": [{"step": "measure", "device": "spectrometer"}]})
    core.feed(Proposed([Proposal({**QD, "concentration_mm": 1}), Proposal({**QD, "concentration_mm": 2})]))
    ask = of(core.advance(0.0), Ask)[0]
    core.feed(Decided([Assignment(ask.view.ready[0].task, "spectrometer")]))
    core.advance(0.0)
    core.feed(TimerFired(TimerKey(TimerKind.DEADLINE, "e0s0#1")))
    out = core.advance(500.0)
    cancel = [s for s in of(out, Send) if s.kind == Kind.CANCEL]
    assert cancel and cancel[0].task == "e0s0"
    assert not of(out, Ask), "the device is still cancelling: nothing may be scheduled on it"
    assert core.devices["spectrometer"].state == "busy"
    core.feed(msg(Kind.FAULT, "spectrometer", "e0s0", 1, code="cancelled", reason="cancelled"))
    out = core.advance(500.0)
    assert notes(out, "attempt.cancel_acknowledged") and core.counts.late == 0
    assert "spectrometer" in [d.name for d in of(out, Ask)[0].view.free]


def test_a_cancel_never_answered_frees_the_device_after_the_grace_period(scenario_of):
    core, _ = started(scenario_of, **{"campaign.budget": 1, "devices.spectrometer.instances": 1,
                                      "workflow": [{"step": "measure", "device": "spectrometer"}],
                                      "orchestrator.cancel_grace_s": 42})
    core.feed(Proposed([Proposal({**QD, "concentration_mm": 1})]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "spectrometer")]))
    core.advance(0.0)
    core.feed(TimerFired(TimerKey(TimerKind.DEADLINE, "e0s0#1")))
    out = core.advance(500.0)
    grace = [a for a in of(out, SetTimer) if a.key.kind == TimerKind.CANCEL_GRACE]
    assert grace and grace[0].delay == 42
    core.feed(TimerFired(grace[0].key))
    out = core.advance(542.0)
    assert notes(out, "attempt.cancel_unanswered") and core.counts.cancels_unanswered == 1
    assert core.devices["spectrometer"].free


def test_a_device_that_refuses_work_with_its_cancel_unanswered_is_quarantined_until_it_answers(scenario_of):
    core, _ = started(scenario_of, **{"campaign.budget": 2, "devices.spectrometer.instances": 1,
                                      "workflow": [{"step": "measure", "device": "spectrometer"}]})
    core.feed(Proposed([Proposal({**QD, "concentration_mm": 1}), Proposal({**QD, "concentration_mm": 2})]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "spectrometer")]))
    core.advance(0.0)
    core.feed(TimerFired(TimerKey(TimerKind.DEADLINE, "e0s0#1")))
    core.advance(500.0)
    core.feed(TimerFired(TimerKey(TimerKind.CANCEL_GRACE, "spectrometer")))
    ask = of(core.advance(560.0), Ask)[0]
    core.feed(Decided([Assignment(ask.view.ready[0].task, "spectrometer")]))
    (send,) = [s for s in of(core.advance(560.0), Send) if s.kind == Kind.COMMAND]
    core.feed(msg(Kind.REJECTED, "spectrometer", send.task, send.attempt, reason="busy with e0s0 (attempt 1)"))
    out = core.advance(560.0)
    (said,) = notes(out, "device.stuck")
    assert (said.device, said.task, said.attempt) == ("spectrometer", "e0s0", 1)
    assert "busy with e0s0" in alert_text(said) and "orchestrator.cancel_grace_s" in alert_text(said)
    assert core.devices["spectrometer"].state == "quarantined" and not of(out, Ask)
    assert operator.status(core)["stuck"] == {"spectrometer": {"task": "e0s0", "attempt": 1}}
    core.feed(msg(Kind.FAULT, "spectrometer", "e0s0", 1, code="cancelled", reason="stopped at last"))
    out = core.advance(900.0)  # the cancel answered: out of quarantine at once, not at its probe
    assert notes(out, "attempt.cancel_acknowledged") and core.counts.late == 0
    assert [n.detail for n in notes(out, "device.probe")] == [{"after": "it answered the cancel"}]
    assert TimerKey(TimerKind.PROBE, "spectrometer") in [a.key for a in of(out, CancelTimer)]
    assert core.devices["spectrometer"].free and operator.status(core)["stuck"] == {}


def test_events_of_one_instant_give_the_same_actions_whatever_order_they_came_in(scenario_of):
    def run(order):
        core, _ = started(scenario_of, **{"campaign.budget": 2, "campaign.max_in_flight": 2,
                                          "workflow": [{"step": "measure", "device": "spectrometer"}]})
        core.feed(Proposed([Proposal({**QD, "concentration_mm": 1}), Proposal({**QD, "concentration_mm": 2})]))
        core.advance(0.0)
        core.feed(Decided([Assignment("e0s0", "spectrometer-1"), Assignment("e1s0", "spectrometer-2")]))
        core.advance(0.0)
        events = [msg(Kind.RESULT, "spectrometer-1", "e0s0", 1, outputs={"peak_nm": 600}, sample=None),
                  msg(Kind.RESULT, "spectrometer-2", "e1s0", 1, outputs={"peak_nm": 630}, sample=None),
                  Presence("synthesiser", False)]
        for i in order:
            core.feed(events[i])
        return core.advance(60.0)

    assert run([0, 1, 2]) == run([2, 1, 0]) == run([1, 2, 0])


def test_the_campaign_ends_with_every_experiment_accounted_for(scenario_of):
    core, _ = started(scenario_of, **{"campaign.budget": 1, "workflow": [{"step": "measure", "device": "spectrometer"}]})
    core.feed(Proposed([Proposal({**QD, "concentration_mm": 1})]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "spectrometer-2")]))
    core.advance(0.0)
    core.feed(msg(Kind.FAULT, "spectrometer-2", "e0s0", 1, code="failed", reason="lamp"))
    out = core.advance(10.0)
    retry = [a for a in of(out, SetTimer) if a.key.kind == TimerKind.RETRY]
    assert retry, "a failed step is retried after a back-off"
    core.feed(TimerFired(retry[0].key))
    ask = of(core.advance(10.0 + retry[0].delay), Ask)[0]
    assert ask.view.ready[0].avoid == frozenset({"spectrometer-2"})  # fail-over to the other instance
    core.stop("enough")
    out = core.advance(100.0)
    assert of(out, Finished) and core.experiments[0].status == "pending"


def running_step(scenario_of):
    """A core with e0s0 dispatched to the synthesiser; returns the core and the command's token."""
    core, _ = started(scenario_of, **{"campaign.budget": 1})
    core.feed(Proposed([Proposal({"concentration_mm": 5, "temperature_c": 250, "time_s": 60})]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    (send,) = of(core.advance(0.0), Send)
    return core, send.token


def test_the_command_carries_an_unguessable_token_that_differs_per_attempt_and_per_secret(scenario_of):
    core, token = running_step(scenario_of)
    assert len(token) == 32 and token == core.token("e0s0", 1)
    assert core.token("e0s0", 2) != token
    assert CampaignCore(core.s, secret=b"another").token("e0s0", 1) != token
    assert CampaignCore(core.s).secret != CampaignCore(core.s).secret  # random unless given


def test_a_message_without_the_attempts_provenance_is_rejected_and_never_touches_the_ledger(scenario_of):
    forged = {
        "no token": msg(Kind.RESULT, "synthesiser", "e0s0", 1, token="", outputs={"x": 1}),
        "wrong token": msg(Kind.RESULT, "synthesiser", "e0s0", 1, token="0" * 32, outputs={"x": 1}),
        "another key": msg(Kind.RESULT, "synthesiser", "e0s0", 1, key="spectrometer-1", outputs={"x": 1}),
        "another device": msg(Kind.RESULT, "spectrometer-1", "e0s0", 1, outputs={"x": 1}),
        "no such device": msg(Kind.FAULT, "intruder", "e0s0", 1, code="failed", reason="x"),
        "no such attempt": msg(Kind.FAULT, "synthesiser", "e0s0", 7, code="failed", reason="x"),
        "a forged cancel answer": msg(Kind.FAULT, "synthesiser", "e0s0", 1, token="f" * 32, code="cancelled",
                                      reason="x"),
    }
    core, _ = running_step(scenario_of)
    for m in forged.values():
        core.feed(m)
    out = core.advance(10.0)
    rejected = notes(out, "message.rejected")
    assert len(rejected) == len(forged) == core.counts.rejected
    assert not notes(out, "attempt.done") and not notes(out, "attempt.failed")
    assert core.counts.failed == 0 and core.experiments[0].outputs == {}
    reasons = " | ".join(n.detail["reason"] for n in rejected)
    for words in ("no attempt token", "a wrong attempt token", "own key", "dispatched to synthesiser",
                  "not a device of this lab", "no attempt e0s0#7"):
        assert words in reasons
    assert all(set(n.detail) >= {"key", "sender", "kind", "reason", "excerpt"} for n in rejected)
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0}))
    assert notes(core.advance(60.0), "attempt.done")  # the real one still counts


def test_a_device_cannot_hand_back_another_experiments_sample(scenario_of):
    core, _ = running_step(scenario_of)
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0, "id": "forged"}))
    out = core.advance(60.0)
    assert notes(out, "attempt.done")
    assert core.experiments[0].sample["id"] == "c1/e0"  # the campaign names the sample it made
    core.feed(Decided([Assignment("e0s1", "spectrometer-1")]))
    (send,) = of(core.advance(60.0), Send)
    assert send.body["sample"]["id"] == "c1/e0"
    core.feed(msg(Kind.RESULT, "spectrometer-1", "e0s1", 1, outputs={"peak_nm": 1.0}, sample={"id": "c1/e9"}))
    out = core.advance(70.0)
    (rej,) = notes(out, "message.rejected")
    assert "is not the one it was given" in rej.detail["reason"] and core.experiments[0].status == "running"


def test_presence_that_flaps_within_a_lease_does_not_fail_a_second_attempt(scenario_of):
    core, _ = running_step(lambda **changes: scenario_of(**changes, bus={"kind": "zenoh"}))
    core.feed(Presence("synthesiser", False))
    out = core.advance(10.0)
    assert notes(out, "device.lost") and notes(out, "attempt.failed")  # the first loss counts
    core.feed(Presence("synthesiser", True))
    core.feed(TimerFired(TimerKey(TimerKind.RETRY, "e0s0")))
    assert of(core.advance(10.2), Ask)[0].what == "schedule"
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    (send,) = of(core.advance(10.3), Send)
    assert send.attempt == 2
    core.feed(Presence("synthesiser", False))  # again, 0.5 lab-s after the first loss: within the lease (1 s)
    out = core.advance(10.5)
    assert notes(out, "device.flapping") and not notes(out, "attempt.failed")
    assert alert_text(notes(out, "device.flapping")[0]) == (  # said on the log in words, not as a dict
        "device.flapping synthesiser: left the bus again within 1 lab-s of its last loss (a bad link, or another "
        "process announcing its name); its running step keeps its deadline")
    assert core.counts.flaps == 1 and core.counts.device_lost == 1
    assert core.devices["synthesiser"].attempt.n == 2  # left to its deadline, or to its result


def test_a_device_not_on_the_bus_at_the_end_of_startup_is_named_and_the_campaign_starts_without_it(scenario_of):
    core = CampaignCore(scenario_of(**{"devices.spectrometer.instances": 2}), secret=SECRET)
    core.start(0.0)
    for name in core.devices:
        if name != "spectrometer-2":
            core.feed(Presence(name, True))
    core.advance(0.0)
    core.feed(TimerFired(TimerKey(TimerKind.STARTUP)))
    out = core.advance(60.0)
    (missing,) = notes(out, "devices.missing")
    assert missing.detail == ["spectrometer-2"] and of(out, Ask)[0].what == "plan"  # it starts without it
    assert alert_text(missing).startswith("devices.missing: spectrometer-2 not on the bus within "
                                          "orchestrator.startup_s: the campaign starts without it, and it takes "
                                          "work once its driver joins the bus")
    assert "one whose driver connects to its instrument: once the instrument answers" in alert_text(missing)


def test_work_with_no_usable_instance_left_is_said_at_once_and_given_up_after_a_while(scenario_of):
    core, _ = started(scenario_of, **{"campaign.budget": 1, "devices.spectrometer.instances": 1,
                                      "campaign.give_up_after_s": 5000,
                                      "clock": {"mode": "scaled", "speed": 3600}})  # its wait at 100 stalls a virtual lab
    core.feed(Proposed([Proposal({"concentration_mm": 5, "temperature_c": 250, "time_s": 60})]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    core.advance(0.0)
    core.feed(Presence("spectrometer", False))  # the only spectrometer is gone
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0}))
    out = core.advance(60.0)
    (said,) = notes(out, "devices.unavailable")
    assert said.detail == {"type": "spectrometer", "experiments": [0], "give_up_after_s": 5000}
    assert alert_text(said).startswith("devices.unavailable spectrometer: no spectrometer is usable (each lost or "
                                       "quarantined); experiment 0 waits for one, and is abandoned if none is back "
                                       "within 5000 lab-s (campaign.give_up_after_s)")
    assert TimerKey(TimerKind.GIVE_UP, "spectrometer") in [a.key for a in of(out, SetTimer)]
    core.feed(Presence("spectrometer", True))  # it comes back: the work resumes
    out = core.advance(100.0)
    assert notes(out, "devices.available") and of(out, Ask)[0].what == "schedule"
    core.feed(Decided([]))
    core.advance(100.0)
    core.feed(Presence("spectrometer", False))  # gone again, for good
    core.advance(200.0)
    core.feed(TimerFired(TimerKey(TimerKind.GIVE_UP, "spectrometer")))
    out = core.advance(5200.0)
    (gone,) = notes(out, "experiment.abandoned")
    assert "no usable spectrometer" in gone.detail["reason"] and "give_up_after_s" in gone.detail["reason"]
    assert of(out, Finished)  # nothing left: the campaign ends instead of waiting for max_lab_hours


def test_a_wait_answered_on_a_view_the_lab_has_since_left_is_asked_again(scenario_of):
    """The scheduler saw a step still running and said wait; the step ended before its answer came. Ending the
    pass on that stale "wait" left nothing running and nobody to ask: the lab idled until
    campaign.max_lab_hours (a job shop with a zero-length operation, the rl agent in the bench's process)."""
    core, out = started(scenario_of, **{"campaign.budget": 2, "devices.synthesiser.instances": 2})
    core.feed(Proposed([Proposal({**QD, "concentration_mm": 1}), Proposal({**QD, "concentration_mm": 2})]))
    ask = of(core.advance(0.0), Ask)[0]
    core.feed(Decided([Assignment("e0s0", "synthesiser-1")]))
    (ask,) = of(core.advance(0.0), Ask)
    assert [r.task for r in ask.view.ready] == ["e1s0"] and "synthesiser-2" in [d.name for d in ask.view.free]
    core.feed(msg(Kind.RESULT, "synthesiser-1", "e0s0", 1, outputs={}, sample={"t_made": 60.0}))  # before the answer
    core.advance(60.0)
    core.feed(Decided([]))  # "wait", on the view in which synthesiser-1 was busy
    (again,) = of(core.advance(60.0), Ask)
    assert again.what == "schedule" and {r.task for r in again.view.ready} == {"e0s1", "e1s0"}


def test_people_no_one_can_use_are_said_to_be_away_or_set_aside_not_lost(scenario_of):
    """A technician whose steps nobody confirms is set aside as a failing device is; the words for it are a
    person's, and say how to confirm, where a device's say lost or quarantined."""
    core = CampaignCore(scenario_of(**{
        "campaign.budget": 1, "devices.spectrometer.instances": 1, "devices.spectrometer.driver": "operator",
        "campaign.give_up_after_s": 5000, "orchestrator.quarantine_after": 1,
        "clock": {"mode": "scaled", "speed": 3600}}), secret=SECRET)  # nobody confirms for it
    core.start(0.0)
    for t, event in ((0.0, Presence("synthesiser", True)),  # people are not on the bus
                     (0.0, Proposed([Proposal({"concentration_mm": 5, "temperature_c": 250, "time_s": 60})])),
                     (0.0, Decided([Assignment("e0s0", "synthesiser")])),
                     (60.0, msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0})),
                     (60.0, Decided([Assignment("e0s1", "spectrometer")]))):  # the technician's step
        core.feed(event)
        core.advance(t)
    core.feed(TimerFired(TimerKey(TimerKind.DEADLINE, "e0s1#1")))  # its time is up, unconfirmed
    out = core.advance(1000.0)
    assert notes(out, "device.quarantined")
    (said,) = notes(out, "devices.unavailable")
    assert said.detail["people"] is True
    assert "no spectrometer is usable (each away, or set aside after steps nobody confirmed in time: `twin ctl " \
           "confirm` confirms one)" in alert_text(said)
    core.feed(TimerFired(TimerKey(TimerKind.GIVE_UP, "spectrometer")))
    (gone,) = notes(core.advance(6000.0), "experiment.abandoned")
    assert gone.detail["reason"].startswith("no usable spectrometer (away, or set aside after steps nobody "
                                            "confirmed in time")
