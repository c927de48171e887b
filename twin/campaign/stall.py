"""A scheduler's "wait" that waits for nothing: no device busy and nothing due, so no event would ask it again.

In virtual time nothing else can happen, so the campaign ends at once, naming the scheduler (it idled to
``campaign.max_lab_hours``); on a live clock an operator, or an instrument coming back, may still move the lab, so
it is an alert (``scheduler.stalled``), said once until the scheduler starts a step again, and ``twin ctl status``
shows it meanwhile.
"""

from __future__ import annotations

from typing import Any

from twin.campaign.events import TimerKey, TimerKind

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)

_WHY = ("answered {what} with no device busy and nothing due, so no event would ask {who} again: a scheduler must "
        "start a step when nothing runs")

_NOT_EVENTS = frozenset({TimerKey(TimerKind.LIMIT), TimerKey(TimerKind.STARTUP)})


def waits_for_nothing(core: CampaignCore) -> bool:
    """Whether nothing can happen but the campaign's time limit: it is ``idle`` and no other campaign shares the
    lab (whose steps ending could wake this one; a shared lab asks ``idle`` of all its campaigns at once)."""
    return core.alone and idle(core)


def idle(core: CampaignCore) -> bool:
    """Every device on the bus and idle, none that crashes now and then (and comes back, which asks again), no
    timer but the limit's."""
    return (not core.stopping and all(d.online and d.state == "idle" for d in core.devices.values())
            and not any(spec.faults.mtbc_h for spec in core.s.devices.values()) and core._timers <= _NOT_EVENTS)


def say_for_lab(names: dict[str, str], lab_scheduler: str = "") -> str:
    """Why a shared lab stalls: each campaign's scheduler (campaign -> scheduler), or the lab's one, waits for
    nothing."""
    if lab_scheduler:
        return f"the lab's scheduler ({lab_scheduler}) " + _WHY.format(what="wait", who="it")
    which = ", ".join(f"{c}: {s}" for c, s in names.items())
    return f"the schedulers ({which}) " + _WHY.format(what="wait", who="them")


def say(core: CampaignCore, refused: int = 0) -> None:
    """``refused``: the scheduler's answer was pairs that could not be carried out (``scheduler.invalid``), not a
    wait, and it is as stuck."""
    what = (f"only pairs that cannot be carried out ({refused} refused: scheduler.invalid in the journal)"
            if refused else "wait")
    why = f"the scheduler ({core.s.campaign.scheduler}) " + _WHY.format(what=what, who="it")
    if core.s.clock.mode == "virtual":
        core._on_stop(why)
    elif not core.stalled:  # said once, until the scheduler starts a step again
        core.stalled = why
        core._note("scheduler.stalled", detail=why)
