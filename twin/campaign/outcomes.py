"""What becomes of an attempt and its experiment: a result moves the experiment on (or finishes it), a
refusal waits and asks again, a failure is retried, put to the operator or abandons the experiment, and a
device that keeps failing is quarantined. The core calls in here with itself.
"""

from __future__ import annotations

import json
from typing import Any

from twin.campaign import consumables, policy, questions, stuck
from twin.campaign.decisions import Outcome
from twin.campaign.events import Code, RecordExperiment, Status, TimerKey, TimerKind
from twin.campaign.ledger import Attempt, Device, Experiment, Task
from twin.core.messages import Kind
from twin.scenario.targets import missing_outputs, scores, unscorable

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)
#: "not now" answers to one step before it is given up: a device that never says yes
MAX_REFUSALS = 100
#: "not now" answers from one device, with no step finished on it in between, before the alert device.refusing
REFUSING_ALERT_AFTER = 10


def resolve(core: CampaignCore, att: Attempt, code: str, body: dict[str, Any]) -> None:
    att.resolved = True
    task, dev = att.task, core.devices[att.device]
    e = task.experiment
    if code != Code.TIMED_OUT:
        core.cancel_timer(TimerKey(TimerKind.DEADLINE, f"{task.id}#{att.n}"))
    dev.attempt = None
    dev.busy_s += core.now - att.t_sent
    core._note(f"attempt.{'done' if code == Code.OK else 'failed'}", e.id, task.id, att.n, dev.name,
               detail=None if code == Code.OK else {"code": str(code), **body})
    if code == Code.TIMED_OUT and dev.name in core.people:
        core.counts.timed_out += 1  # nobody to tell to stop: the person sees the step is gone (twin ctl status)
    elif code == Code.TIMED_OUT:
        core.counts.timed_out += 1
        dev.cancelling = att
        core._timer(TimerKey(TimerKind.CANCEL_GRACE, dev.name), core.s.orchestrator.cancel_grace_s)
        core._send(dev.name, Kind.CANCEL, task.id, att.n, {"reason": body["reason"]}, att.token)
    if code == Code.OK:
        dev.consecutive_failures, dev.probing, dev.refusals_in_a_row = 0, False, 0
        advance(core, task, body)
    elif code == Code.REJECTED:
        if not body.get("began"):  # a step refused never ran: it used nothing, and costs nothing
            core.spent -= core.s.devices[dev.type].cost
            if core.stocks:
                consumables.give_back(core, att)
        refused(core, task, dev, body.get("reason", ""), bool(body.get("infeasible")))
    else:
        failed(core, task, dev, str(code), body.get("reason", ""))
    core._wake = True


def refused(core: CampaignCore, task: Task, dev: Device, reason: str, infeasible: bool) -> None:
    """A refusal is not a fault: no strike against the device, no quarantine."""
    e, o = task.experiment, core.s.orchestrator
    if infeasible:
        core.counts.infeasible += 1
        finish_infeasible(core, e, f"{dev.name} refused {task.step.step!r}: {reason}")
        return
    core.counts.refused_now += 1
    if dev.unanswered is not None:  # still running the step it was told to cancel: no work until it stops
        quarantine(core, dev, stuck.held(core, dev, reason))
    dev.refusals_in_a_row += 1
    if dev.refusals_in_a_row == REFUSING_ALERT_AFTER:  # busy with nothing the lab gave it: said once, until it works
        core._note("device.refusing", e.id, task.id, task.attempts, dev.name,
                   detail={"refusals": dev.refusals_in_a_row, "reason": reason, "max_refusals": MAX_REFUSALS})
    # "not now" does not use up one of the step's attempts; its number is not used again, so an answer that
    # comes later for the refused attempt can never count for the next one
    task.excused += 1
    task.refusals += 1
    counted = task.attempts - task.excused
    retrying_s = core.now - _retrying_since(core, task)
    if (task.refusals < MAX_REFUSALS and not core.stopping
            and policy.may_retry(counted, retrying_s, o.retry)):
        backoff = policy.backoff_s(o.retry, counted + 1, core.seed, task.id)
        core._note("task.refused", e.id, task.id, task.attempts + 1, dev.name,
                   detail={"backoff_s": backoff, "reason": reason})
        core._retrying[task.id] = task
        core._timer(TimerKey(TimerKind.RETRY, task.id), backoff)
    else:
        late = "" if core.stopping or task.refusals >= MAX_REFUSALS else policy.retried_too_long(
            counted, retrying_s, o.retry)
        finish(core, e, Status.ABANDONED, f"step {task.step.step!r} refused {task.refusals} time(s){late}, last by "
                                          f"{dev.name}: {reason}")


def finish_infeasible(core: CampaignCore, e: Experiment, why: str) -> None:
    e.infeasible = True
    finish(core, e, Status.ABANDONED, f"infeasible: {why}")


def advance(core: CampaignCore, task: Task, result: dict[str, Any]) -> None:
    e = task.experiment
    for k, v in (result.get("outputs") or {}).items():
        if not isinstance(v, (list, dict)):  # a spectrum or a trace stays in the journal's msg.result row
            e.outputs[k] = v
    sample = result.get("sample")
    if sample is not None:
        e.sample_made = float(sample.get("t_made", core.now))
        # the sample is the campaign's: its id is given when it is made and checked on every result after
        e.sample = {**sample, "id": e.sample["id"] if e.sample is not None else f"{core.campaign_id}/e{e.id}"}
    e.stage += 1
    if e.stage < len(e.route):
        core._make_ready(e)
    else:
        finish(core, e, Status.DONE)


def failed(core: CampaignCore, task: Task, dev: Device, code: str, reason: str) -> None:
    e, o = task.experiment, core.s.orchestrator
    core.counts.failed += 1
    if code != Code.REJECTED:
        dev.failures += 1
        dev.consecutive_failures += 1
        task.failed_on.append(dev.name)
        if policy.should_quarantine(dev.consecutive_failures, o.quarantine_after, dev.quarantined):
            quarantine(core, dev)
    counted = task.attempts - task.excused
    retrying_s = core.now - _retrying_since(core, task)
    retries_left = policy.may_retry(counted, retrying_s, o.retry) and not core.stopping
    rule = None if core.stopping else questions.rule_for(core, task, dev.type, code, retries_left)
    if rule is not None:
        why = f"step {task.step.step!r} failed {task.attempts} time(s); last: {code} on {dev.name}: {reason}"
        questions.ask(core, task, dev.name, code, why, rule)
    elif retries_left:
        backoff = policy.backoff_s(o.retry, counted, core.seed, task.id)
        e.retries += 1
        core.counts.retried += 1
        core._note("task.retry", e.id, task.id, task.attempts, dev.name, detail={"backoff_s": backoff, "after": code})
        core._retrying[task.id] = task
        core._timer(TimerKey(TimerKind.RETRY, task.id), backoff)
    else:
        late = "" if core.stopping else policy.retried_too_long(counted, retrying_s, o.retry)
        why = f"step {task.step.step!r} failed {task.attempts} time(s){late}; last: {code} on {dev.name}: {reason}"
        finish(core, e, Status.ABANDONED, why)


def _retrying_since(core: CampaignCore, task: Task) -> float:
    """When the step's retries began (now, at its first failure or "not now"): time it spent queued before its
    first attempt is the scheduler's doing, not retrying, and must not cost it its retries."""
    if task.retrying_since is None:
        task.retrying_since = core.now
    return task.retrying_since


def quarantine(core: CampaignCore, dev: Device, why: str = "") -> None:
    dev.quarantined, dev.probing = True, False
    core.counts.quarantined += 1
    probe = core.s.orchestrator.probe_after_s
    core._note("device.quarantined", device=dev.name,
               detail={"probe_after_s": probe, "reason": why} if why else {"probe_after_s": probe})
    core._timer(TimerKey(TimerKind.PROBE, dev.name), probe)


def finish(core: CampaignCore, e: Experiment, status: Status, reason: str = "") -> None:
    e.status, e.reason, e.t_done = status, reason, core.now
    del core.active[e.id]
    if status == Status.DONE:
        e.scores = scores(e.outputs, core.s.chemistry.targets)
        _note_unscorable(core, e)
        for name, sc in e.scores.items():
            if name not in core.best or sc < core.best[name][0]:
                core.best[name] = (sc, e.id)
            if sc == 0 and name not in core.met_at:
                core.met_at[name] = core.now - core.t0
                core.met_after[name] = core.finished_count
                core.met_cost[name] = core.cost
                core._note("target.met", e.id, detail=name)
        core.counts.degraded += e.degraded
    core.history.append(Outcome(e.params, e.outputs if status == Status.DONE else None,
                                min(e.scores.values()) if e.scores else None, reason, e.infeasible))
    numeric = {k: v for k, v in e.outputs.items() if isinstance(v, (int, float))}
    core._note(f"experiment.{status}", e.id, detail={"reason": reason, "outputs": numeric, "scores": e.scores})
    core._out.append(RecordExperiment(e, final=True))


def _note_unscorable(core: CampaignCore, e: Experiment) -> None:
    """A target's output that came as something other than a number, or that an experiment which ran the workflow
    as written did not bring at all: said once per output per campaign."""
    for name, value in unscorable(e.outputs, core.s.chemistry.targets).items():
        if name not in core._unscorable:
            core._unscorable.add(name)
            core._note("output.unscored", e.id, detail=f"{name} = {json.dumps(value)[:60]} is not a number, so no "
                       "target can be scored on it (a device sent it; a NaN arrives as null). Fix the driver; "
                       "later experiments like this are not noted again")
    if e.route is not core._workflow:  # a route the planner chose may measure less, on purpose
        return
    for name in missing_outputs(e.outputs, core.s.chemistry.targets):
        if name not in core._unscorable:
            core._unscorable.add(name)
            had = ", ".join(sorted(e.outputs)[:12]) or "none"
            core._note("output.unscored", e.id, detail=f"{name}, which a target reads, is not among the outputs of "
                       f"the workflow's steps (they gave: {had}), so no target can be scored on it. A driver that "
                       "names it otherwise, or a step that does not measure it? Later experiments like this are not "
                       "noted again")
