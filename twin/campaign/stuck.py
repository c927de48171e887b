"""A device still running a step the lab cancelled: its cancel went unanswered through the grace
(``orchestrator.cancel_grace_s``), and it then refused work. Its driver did not stop (it caught the cancel and went
on), or needs longer to stop than the grace allows.

Such a device is quarantined until it answers the cancel (or leaves the bus, which ends what it ran), so no step is
sent to it and refused again and again while another instance could run it; its probe after
``orchestrator.probe_after_s`` asks it once more. The first time for each device it is said as an alert
(``device.stuck``) naming the step and what to do; with no other instance of its type, the steps waiting for one
are given up on as for a lost one (``campaign.give_up_after_s``).
"""

from __future__ import annotations

from typing import Any

from twin.campaign.events import TimerKey, TimerKind
from twin.campaign.ledger import Device

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


def held(core: CampaignCore, dev: Device, reason: str) -> str:
    """``dev`` answered "not now" (``reason``) with a cancel of it unanswered: it is still running the cancelled
    step. Marks it and says so (the alert the first time for this device; the caller quarantines it); returns why,
    for the quarantine's note."""
    att = dev.unanswered
    assert att is not None
    dev.stuck = att
    core.counts.stuck += 1
    if not dev.said_stuck:
        dev.said_stuck = True
        o = core.s.orchestrator
        core._note("device.stuck", att.task.experiment.id, att.task.id, att.n, dev.name,
                   detail={"reason": reason, "grace_s": o.cancel_grace_s, "probe_after_s": o.probe_after_s})
    return f"still running {att.task.id} (attempt {att.n}), told to cancel: {reason}"


def ended(core: CampaignCore, dev: Device, why: str) -> None:
    """The cancelled step ended at last (``why``: its cancel answered, the device left the bus): out of quarantine."""
    if dev.stuck is None:
        return
    dev.stuck, dev.probing = None, False
    if dev.quarantined:
        dev.quarantined = False
        core.cancel_timer(TimerKey(TimerKind.PROBE, dev.name))
        core._note("device.probe", device=dev.name, detail={"after": why})
        core._wake = True
