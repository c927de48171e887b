"""A scheduler's answer carried out: each pair the lab can run is dispatched, each it cannot is refused
(``scheduler.invalid``, with why), and a pass that sent nothing with the lab idle is a stall (``stall``). The core
calls in here with itself.
"""

from __future__ import annotations

from typing import Any

from twin.campaign import dispatch, stall
from twin.campaign.events import Decided

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


def carry_out(core: CampaignCore, d: Decided) -> None:
    core.decision_wall_s.append(d.wall_s)
    sent = refused = 0
    for a in d.assignments if not core.stopping else ():
        why = dispatch.problem(a, core.ready, core.devices, core.dry)
        if why:
            core._note("scheduler.invalid", task=a.task, device=a.device, detail=why)
            refused += 1
            continue
        task = core.ready.pop(a.task)
        short = core.stocks.short(core._needs(task), a.device) if core.stocks else []
        if short:  # an assignment earlier in this answer used up what this one needs
            core._starve(task, short)
            continue
        core._dispatch(task, core.devices[a.device])
        sent += 1
    if sent:
        core.stalled = ""
    if core._wake:
        # the lab changed while the scheduler looked at it (a step ended, a device came back): the view it
        # answered is stale, so the pass goes on from the lab as it is, the planner's turn included; ending
        # it on a stale "wait" could leave nothing running and nobody to ask again
        core._filled = False
    elif sent:
        core._wake = True  # more may pair now
    else:
        core._end_pass()
        if refused == len(d.assignments) and stall.waits_for_nothing(core):  # a wait, or only refused pairs
            stall.say(core, refused)
