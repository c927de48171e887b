"""What the campaign does when one of its timers fires: a deadline passes, a retry's back-off ends, a quarantined
device is probed, a cancel goes unanswered, a question or a human step times out, a simulated refill comes,
the lab-time limit or the start-up wait is reached. The core calls in here with itself.
"""

from __future__ import annotations

from typing import Any

from twin.campaign import consumables, human, outcomes, policy, questions, stranded
from twin.campaign.events import Code, TimerKey, TimerKind

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


def fired(core: CampaignCore, key: TimerKey) -> None:
    kind = key.kind
    if kind == TimerKind.DEADLINE:
        task, _, n = key.ref.rpartition("#")
        att = core.attempts.get((task, int(n)))
        if att is not None and not att.resolved:
            limit = policy.deadline_s(att.task.expected_s, core.s.orchestrator)
            outcomes.resolve(core, att, Code.TIMED_OUT, {"reason": f"no result within {limit:.0f} lab-s"})
    elif kind == TimerKind.RETRY:
        waiting = core._retrying.pop(key.ref, None)
        if waiting is not None and not core.stopping:
            core._make_ready(waiting.experiment, waiting)
    elif kind == TimerKind.PROBE:
        dev = core.devices[key.ref]
        dev.quarantined, dev.probing = False, dev.stuck is not None
        core._note("device.probe", device=dev.name)
        core._wake = True
    elif kind == TimerKind.CANCEL_GRACE:
        dev = core.devices[key.ref]
        if dev.cancelling is not None:
            att, dev.cancelling = dev.cancelling, None
            dev.unanswered = att
            core.counts.cancels_unanswered += 1
            core._note("attempt.cancel_unanswered", att.task.experiment.id, att.task.id, att.n, dev.name,
                       detail={"grace_s": core.s.orchestrator.cancel_grace_s})
            core._wake = True
    elif kind == TimerKind.GIVE_UP:
        stranded.give_up(core, key.ref)
    elif kind in (TimerKind.QUESTION, TimerKind.ANSWER):
        questions.on_timer(core, kind, key.ref)
    elif kind == TimerKind.CONFIRM:
        human.on_timer(core, key.ref)
    elif kind == TimerKind.REFILL:
        consumables.refill(core, key.ref, None, "simulated operator")
    elif kind == TimerKind.LIMIT:
        core._on_stop("max_lab_hours reached")
    elif kind == TimerKind.STARTUP and not core._running:
        missing = [d.name for d in core.devices.values() if not d.online]
        core._note("devices.missing", detail=missing)
        core._begin()
