"""An operator's acts on a running campaign: pause, resume, abort or retry an experiment, stop.

Each act is an ``Operator`` event, so it is journalled with the core's other inputs and a resumed
campaign replays it (a paused campaign stays paused). Each ends in one note: ``operator.<command>`` when
it took effect, ``operator.refused`` with the reason when it could not; both carry who sent it and the
request's ``ref``, which the runtime answers the operator with.
"""

from __future__ import annotations

from typing import Any

from twin.campaign import consumables, human, questions
from twin.campaign.events import Operator, Status, TimerKey, TimerKind
from twin.campaign.ledger import Attempt
from twin.core.messages import Kind

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


def act(core: CampaignCore, op: Operator) -> None:
    """Carry out ``op`` on ``core`` and note what became of it."""
    do = _ACTS.get(op.command)
    why = f"unknown command {op.command!r}: use one of {', '.join(_ACTS)}" if do is None else do(core, op)
    detail: dict[str, Any] = {"who": op.who, "ref": op.ref}
    if op.reason:
        detail["reason"] = op.reason
    if op.question:
        detail.update(question=op.question, option=op.option)
    if op.item:
        detail.update(item=op.item, amount=op.amount)
    if op.task:
        detail["task"] = op.task
    if why:
        core._note("operator.refused", op.experiment, detail={**detail, "command": op.command, "why": why})
        return
    if op.now:
        detail["now"] = True
    core._note(f"operator.{op.command}", op.experiment, detail=detail)
    core._wake = True


def _pause(core: CampaignCore, op: Operator) -> str:
    if core.stopping:
        return f"the campaign is stopping ({core.stopping})"
    if core.paused_by and not op.now:
        return f"already paused by {core.paused_by}"
    core.paused_by = op.who
    if op.now:
        for dev in core.devices.values():
            if dev.attempt is not None and not dev.attempt.resolved:
                task = dev.attempt.task
                _cancel(core, dev.attempt, f"paused by {op.who}")
                task.excused += 1  # stopped by the operator, not failed: the step keeps its attempts
                core._make_ready(task.experiment, task)
    return ""


def _resume(core: CampaignCore, op: Operator) -> str:
    if not core.paused_by:
        return "the campaign is not paused"
    core.paused_by = ""
    return ""


def _abort(core: CampaignCore, op: Operator) -> str:
    e = core.active.get(op.experiment) if op.experiment is not None else None
    if e is None:
        return _not_active(core, op.experiment)
    for dev in core.devices.values():
        if dev.attempt is not None and not dev.attempt.resolved and dev.attempt.task.experiment is e:
            _cancel(core, dev.attempt, f"experiment {e.id} aborted by {op.who}")
    questions.withdraw(core, f"experiment {e.id} aborted by {op.who}", e)
    for task_id in [t for t, task in core.ready.items() if task.experiment is e]:
        del core.ready[task_id]
    for task_id in [t for t, task in core.starved.items() if task.experiment is e]:
        del core.starved[task_id]
    for task_id in [t for t, task in core._retrying.items() if task.experiment is e]:
        del core._retrying[task_id]
        core.cancel_timer(TimerKey(TimerKind.RETRY, task_id))
    core._finish(e, Status.ABANDONED, f"aborted by {op.who}" + (f": {op.reason}" if op.reason else ""))
    return ""


def _retry(core: CampaignCore, op: Operator) -> str:
    """A step waiting out its back-off goes now; an experiment abandoned after its retries runs again from the
    step that failed, with fresh attempts (an infeasible one, or one still running, is refused)."""
    n = op.experiment
    if n is None or not 0 <= n < len(core.experiments):
        return _not_active(core, n)
    e = core.experiments[n]
    waiting = [t for t in core._retrying.values() if t.experiment is e]
    if waiting:
        for task in waiting:
            del core._retrying[task.id]
            core.cancel_timer(TimerKey(TimerKind.RETRY, task.id))
            core._make_ready(e, task)
        return ""
    if e.status != Status.ABANDONED:
        return f"experiment {n} is {e.status}: only an abandoned one, or one waiting to retry a step, can be retried"
    if e.infeasible:
        return f"experiment {n} was refused as infeasible ({e.reason}); retrying cannot change that"
    if core.stopping:
        return f"the campaign is stopping ({core.stopping})"
    e.status, e.reason, e.t_done = Status.PENDING, "", None
    core.active[e.id] = e
    core._note("experiment.reopened", e.id, detail={"who": op.who, "stage": e.stage})
    core._make_ready(e)
    task_id = f"e{e.id}s{e.stage}"
    task = core.ready.get(task_id) or core.starved.get(task_id)  # a step short of stock waits, reopened all the same
    if task is not None:
        # its attempts go on being numbered where they stopped (a late answer to an old one matches nothing),
        # and none of those counts against the fresh retries
        task.attempts = task.excused = max((n for t, n in core.attempts if t == task.id), default=0)
    return ""


def stop_reason(who: str, reason: str) -> str:
    """How a campaign an operator stopped says why."""
    return f"stopped by {who}" + (f": {reason}" if reason else "")


def _stop(core: CampaignCore, op: Operator) -> str:
    if core.stopping:
        return f"the campaign is already stopping ({core.stopping})"
    # a campaign of a lab of several stays stopped when the lab resumes (only the lab's own stop is undone)
    core._on_stop(stop_reason(op.who, op.reason), outside=core.alone)
    return ""


def _refill(core: CampaignCore, op: Operator) -> str:
    if not core.stocks.known(op.item):
        have = ", ".join(core.stocks.items) or "none"
        return f"there is no consumable {op.item!r} (this lab's: {have})"
    if op.amount is not None and not 0 < op.amount < 1e15:
        return f"amount {op.amount}: a refill adds a positive amount (or, without one, fills to the starting level)"
    consumables.refill(core, op.item, op.amount, op.who)
    return ""


_ACTS = {"pause": _pause, "resume": _resume, "abort": _abort, "retry": _retry, "stop": _stop, "answer": questions.answer,
         "refill": _refill, "confirm": human.confirm}


def _not_active(core: CampaignCore, n: int | None) -> str:
    if n is None:
        return "name the experiment (its number, as `twin ctl status` lists them)"
    if not 0 <= n < len(core.experiments):
        return f"there is no experiment {n} (the campaign has proposed {len(core.experiments)})"
    e = core.experiments[n]
    return f"experiment {n} is already {e.status}" + (f" ({e.reason})" if e.reason else "")


def _cancel(core: CampaignCore, att: Attempt, why: str) -> None:
    """Take ``att`` out of the lab: the device is told to stop in a safe state, and gets no new step until it
    has said it stopped (or its cancel grace is over)."""
    dev = core.devices[att.device]
    att.resolved = True
    core.cancel_timer(TimerKey(TimerKind.DEADLINE, f"{att.task.id}#{att.n}"))
    dev.busy_s += core.now - att.t_sent
    dev.attempt = None
    dev.cancelling = att
    core._timer(TimerKey(TimerKind.CANCEL_GRACE, dev.name), core.s.orchestrator.cancel_grace_s)
    core._send(dev.name, Kind.CANCEL, att.task.id, att.n, {"reason": why}, att.token)
    core._note("attempt.cancelled", att.task.experiment.id, att.task.id, att.n, dev.name, detail=why)


def status(core: CampaignCore, now: float | None = None) -> dict[str, Any]:
    """What ``twin ctl status`` shows at lab time ``now`` (default: the core's last step): the campaign's state,
    its experiments, what is in the lab and what waits."""
    now = core.now if now is None else now
    counts = {str(s): 0 for s in Status}
    for e in core.experiments:
        counts[str(e.status)] += 1
    in_lab = [{"device": d.name, "task": d.attempt.task.id, "attempt": d.attempt.n,
               "for_s": round(now - d.attempt.t_sent, 1)} for d in core.devices.values() if d.attempt]
    state = ("finished" if core.finished else "stopping" if core.stopping else "paused" if core.paused_by
             else "running" if core._running else "starting")
    return {"campaign": core.campaign_id, "scenario": core.s.name, "lab": core.s.lab, "state": state,
            "paused_by": core.paused_by, "stopping": core.stopping, "stalled": core.stalled, "lab_hours": round((now - core.t0) / 3600, 4),
            "started_lab_hours": None if core.alone else round(core.t0 / 3600, 4),  # one of a lab's campaigns
            "budget": core.s.campaign.budget, "experiments": counts, "in_lab": in_lab,
            "ready": sorted(core.ready), "retrying": sorted(core._retrying),
            "consumables": {name: {"level": round(st.level, 6), "unit": st.unit, "reorder_at": st.reorder_at,
                                   "used": round(st.used, 6), "depleted": st.depleted,
                                   "runs_out_in_s": core.stocks.runs_out_in_s(st, now - core.t0),
                                   "waiting": sorted(t.id for t in core.starved.values()
                                                     if name in core.stocks.short(core._needs(t), barred=t.barred))}
                            for name, st in core.stocks.items.items()},
            "abandoned": {e.id: e.reason for e in core.experiments if e.status == Status.ABANDONED},
            "human_steps": [{"task": d.attempt.task.id, "device": d.name, "step": d.attempt.task.step.step,
                             "for_s": round(now - d.attempt.t_sent, 1),
                             "instructions": str(core.s.devices[d.type].options.get("instructions", ""))[:500]}
                            for d in core.devices.values() if d.name in core.people and d.attempt is not None],
            "questions": [{"id": q.id, "experiment": q.task.experiment.id, "task": q.task.id, "device": q.device,
                           "fault": q.fault, "why": q.why, "options": list(q.options), "default": q.default,
                           "default_in_s": round(q.deadline - now, 1)} for q in core.questions.values()],
            "devices": {d.name: d.state for d in core.devices.values()},
            "stuck": {d.name: {"task": d.stuck.task.id, "attempt": d.stuck.n} for d in core.devices.values()
                      if d.stuck is not None}}
