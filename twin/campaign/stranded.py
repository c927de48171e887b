"""Work stranded without a usable device: what the core does as ``Availability`` sees a device type's
instances all lost or quarantined while work waits for it — say so at once, arm ``campaign.give_up_after_s``,
abandon the work when it fires, say when an instance is back. The core calls in here with itself.
"""

from __future__ import annotations

from typing import Any

from twin.campaign import outcomes
from twin.campaign.events import UNUSABLE, Status, TimerKey, TimerKind
from twin.campaign.human import DRIVER as PERSON
from twin.core.counts import counted

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)
GIVEN_UP = "given up"  # CampaignCore.why_no_proposals: a device type the workflow needs was given up on


def review(core: CampaignCore) -> None:
    """Say at once when the work waiting for a device type has no usable instance left, and give it
    ``campaign.give_up_after_s`` before abandoning it; an instance that comes back resumes it."""
    # a stuck device (stuck.py) probed is back once a step is done on it: a probe it refuses, still stuck, must
    # not reset the give-up timer, nor say the type is back and gone again (a probe that fails uses an attempt)
    stranded, given_up = core._availability.stranded, core._availability.given_up
    usable = {d.type for d in core.devices.values()
              if d.online and not d.quarantined and not (d.probing and (d.type in stranded or d.type in given_up))}
    if usable.issuperset(core.s.devices) and not (stranded or given_up):
        return  # every type has a usable instance and none was stranded: nothing to say (the common case)
    waiting: dict[str, list[int]] = {}
    for t in [*core.ready.values(), *core._retrying.values()]:
        waiting.setdefault(t.step.device, []).append(t.experiment.id)
    after = core.s.campaign.give_up_after_s
    for what, dtype in core._availability.review(waiting, usable, bool(core.stopping)):
        if what == "unavailable":
            detail = {"type": dtype, "experiments": sorted(waiting[dtype]), "give_up_after_s": after}
            if core.s.devices[dtype].driver == PERSON:
                detail["people"] = True  # said as a person's absence, not a device's loss
            core._note("devices.unavailable", device=dtype, detail=detail)
            core._timer(TimerKey(TimerKind.GIVE_UP, dtype), after)
            continue
        core.cancel_timer(TimerKey(TimerKind.GIVE_UP, dtype))
        if what == "available":
            core._note("devices.available", device=dtype, detail={"type": dtype})


def give_up(core: CampaignCore, dtype: str) -> None:
    """The give-up timer of ``dtype`` fired: its waiting work is abandoned, unless an instance came back."""
    if not core._availability.give_up(dtype):
        return
    after = core.s.campaign.give_up_after_s
    for t in [t for t in [*core.ready.values(), *core._retrying.values()] if t.step.device == dtype]:
        core.ready.pop(t.id, None)
        core._retrying.pop(t.id, None)
        core.cancel_timer(TimerKey(TimerKind.RETRY, t.id))
        outcomes.finish(core, t.experiment, Status.ABANDONED, f"no usable {dtype} ({unusable(core, dtype)}) for "
                                                              f"{after:.0f} lab-s (campaign.give_up_after_s)")
    core._wake = True


def unusable(core: CampaignCore, dtype: str) -> str:
    """How the instances of ``dtype`` became unusable, in words for what they are."""
    return UNUSABLE[core.s.devices[dtype].driver == PERSON]


def cut_short(core: CampaignCore) -> str:
    """Why a campaign that ended on its own left some of its budget unproposed, when the reason is a device type
    its workflow needs given up on (no other limit would have ended it); '' otherwise. A bench counts such a run
    as one that ended early, not as a short one."""
    if core.stopping or core.why_no_proposals() != GIVEN_UP:
        return ""
    c = core.s.campaign
    lost = [t for t in dict.fromkeys(step.device for step in core._workflow) if t in core._availability.given_up]
    left = c.budget + core.replaced - len(core.experiments)
    return (f"no usable {', '.join(lost)} for {c.give_up_after_s:g} lab-s (campaign.give_up_after_s), so "
            f"{counted(left, 'experiment', 'experiments')} of the budget {'was' if left == 1 else 'were'} never "
            "proposed")


def ran_out(core: CampaignCore) -> str:
    """Why a campaign that ended on its own proposed less than its budget when its planner had nothing more to
    propose (a route planner with no route, a design run through); '' otherwise. Not a stop: a bench counts the
    run as it ended."""
    c, targets = core.s.campaign, core.s.chemistry.targets
    if (core.stopping or core.planner_failed or core.why_no_proposals() != "planner" or core.active
            or (targets and len(core.met_at) == len(targets))):
        return ""
    return (f"the planner proposed no more experiments after {len(core.experiments)} of the budget's "
            f"{c.budget + core.replaced}" + (f": {core.planner_why}" if core.planner_why else ""))
