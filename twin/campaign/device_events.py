"""What a device tells the campaign: a message about one of its attempts (checked for its provenance first:
from the device the step went to, with the attempt's token), and its presence on the bus coming or going.
The core calls in here with itself.
"""

from __future__ import annotations

from typing import Any

from twin.campaign import floods, outcomes, provenance, results, stuck
from twin.campaign.events import Code, DeviceMessage, RecordMessage, TimerKey, TimerKind
from twin.campaign.ledger import Attempt
from twin.core.messages import Kind

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


def message(core: CampaignCore, m: DeviceMessage) -> None:
    att = core.attempts.get((m.task, m.attempt))
    why = provenance.problem(m, att, core.devices)
    if why:
        _reject(core, m, why)
        return
    if m.kind == Kind.TELEMETRY:
        core._out.append(RecordMessage(core.now, "msg.telemetry", None, m.task or None, m.attempt, m.device,
                                       m.payload))
        return
    assert att is not None  # provenance vouched for it
    exp = att.task.experiment.id
    core._out.append(RecordMessage(core.now, f"msg.{m.kind}", exp, m.task, m.attempt, m.device, m.payload))
    if att.resolved:
        _after_resolved(core, att, m)
        return
    if m.kind == Kind.ACCEPTED:
        att.t_accepted = core.now
        core._note("attempt.running", exp, m.task, m.attempt, m.device)
    elif m.kind == Kind.RESULT:
        bad = results.problem(m.body, core.now)
        if bad:
            outcomes.resolve(core, att, Code.DRIVER_ERROR,
                             {"reason": f"{m.device} returned a result the lab cannot use: {bad}"})
        else:
            outcomes.resolve(core, att, Code.OK, m.body)
    elif m.kind == Kind.FAULT:
        outcomes.resolve(core, att, m.body.get("code", Code.FAILED), {"reason": m.body.get("reason", "")})
    elif m.kind == Kind.REJECTED:
        began = {"began": True} if m.body.get("began") else {}
        outcomes.resolve(core, att, Code.REJECTED, {"reason": m.body.get("reason", ""),
                                           "infeasible": bool(m.body.get("infeasible", False)), **began})


def _reject(core: CampaignCore, m: DeviceMessage, why: str) -> None:
    core.counts.rejected += 1
    more = floods.left_out(core.counts.rejected - 1, core.counts.rejected)
    if more is not None:
        detail = provenance.rejection(m, why, core.s.lab)
        core._note("message.rejected", device=m.key or m.device,
                   detail={**detail, "left_out": more} if more else detail)


def _after_resolved(core: CampaignCore, att: Attempt, m: DeviceMessage) -> None:
    """A message about an attempt already decided: the answer to a cancel, or late."""
    dev = core.devices[att.device]
    final = m.kind in (Kind.FAULT, Kind.RESULT, Kind.REJECTED)
    acked = final and (dev.cancelling is att or dev.unanswered is att)  # after the grace too: answered late
    if final and dev.unanswered is att:
        dev.unanswered = None
    if final and dev.stuck is att:
        stuck.ended(core, dev, "it answered the cancel")
    if acked and dev.cancelling is att:
        dev.cancelling = None
        core.cancel_timer(TimerKey(TimerKind.CANCEL_GRACE, dev.name))
        core._wake = True
    if acked and m.kind == Kind.FAULT and m.body.get("code") == Code.CANCELLED:
        core._note("attempt.cancel_acknowledged", att.task.experiment.id, att.task.id, att.n, dev.name)
    elif m.kind in (Kind.RESULT, Kind.FAULT):
        core.counts.late += 1
        core._note("result.late", att.task.experiment.id, att.task.id, att.n, dev.name, detail=str(m.kind))


def presence(core: CampaignCore, name: str, alive: bool) -> None:
    dev = core.devices.get(name)
    if dev is None or dev.online == alive:
        return
    dev.online = alive
    if not alive and core.awaited is not None:
        core.awaited.add(name)
    core._note("device.online" if alive else "device.lost", device=dev.name)
    if not alive:
        flap = dev.lost_at is not None and core.now - dev.lost_at < core._flap_s
        dev.lost_at = core.now
        if flap:  # gone again within a lease: an impostor's token, or a bad link; the deadline still holds
            core.counts.flaps += 1
            core._note("device.flapping", device=dev.name, detail={"within_s": core._flap_s})
            core._wake = True
            return
        core.counts.device_lost += 1
        dev.unanswered = None
        stuck.ended(core, dev, "it left the bus, which ended the step it did not stop")
        if dev.cancelling is not None:
            dev.cancelling = None
            core.cancel_timer(TimerKey(TimerKind.CANCEL_GRACE, dev.name))
        if dev.attempt is not None:
            core.counts.steps_lost += 1
            outcomes.resolve(core, dev.attempt, Code.DEVICE_LOST,
                             {"reason": f"{dev.name} left the bus (liveliness lost)"})
    if not core._running and _all_online(core):
        core.cancel_timer(TimerKey(TimerKind.STARTUP))
        core._begin()
    core._wake = True


def _all_online(core: CampaignCore) -> bool:
    """Whether every device is online, as the campaign waits to start. Each arrival checked them all, which is
    quadratic in the lab's size (a lab of thousands of instances took seconds to start); the devices still to
    come are kept instead, each checked off once it is seen online."""
    if core.awaited is None:
        core.awaited = {d.name for d in core.devices.values() if not d.online}
    while core.awaited:
        first = next(iter(core.awaited))
        if not core.devices[first].online:
            return False
        core.awaited.discard(first)
    return True
