"""What a scheduler sees (``LabView``) and whether its answer can be carried out."""

from __future__ import annotations

from collections.abc import Callable, Iterable

from twin.campaign import policy
from twin.campaign.ledger import Device, Task
from twin.campaign.decisions import Assignment, DeviceState, FreeDevice, LabView, ReadyStep


#: the instances a step may not go to because their own stock of something it uses is short (``Stocks.dry``)
Dry = Callable[[Task], frozenset[str]]


def avoid_for(t: Task, devices: Iterable[Device], dry: Dry | None = None) -> frozenset[str]:
    barred = t.barred | dry(t) if dry is not None else t.barred
    if not t.failed_on:
        return barred
    # an instance short of the step's stock is not usable: fail-over must not avoid the only one left with some
    usable = {d.name for d in devices if d.type == t.step.device and d.online and not d.quarantined} - barred
    return policy.avoid(t.failed_on, usable) | barred


def pair_possible(ready: Iterable[Task], devices: dict[str, Device], dry: Dry | None = None) -> bool:
    """Whether some free device could take some ready step (cheaper than building the view)."""
    free: dict[str, set[str]] = {}
    for d in devices.values():
        if d.free:
            free.setdefault(d.type, set()).add(d.name)
    if not free:
        return False
    for t in ready:
        names = free.get(t.step.device)
        if names and (not (t.failed_on or t.barred or dry) or names - avoid_for(t, devices.values(), dry)):
            return True
    return False


def view(now: float, ready: Iterable[Task], devices: dict[str, Device], finished: int, budget: int,
         in_lab: int, dry: Dry | None = None) -> LabView:
    devs = devices.values()
    steps = tuple(_shown(t, avoid_for(t, devs, dry)) for t in ready)
    free = tuple(FreeDevice(d.name, d.type) for d in devs if d.free)
    states = tuple(
        DeviceState(d.name, d.type, d.free, d.online,
                    d.attempt.t_sent + d.attempt.task.expected_s if d.attempt else None, d.attempts, d.failures,
                    d.busy_s, d.attempt.task.then if d.attempt else (), d.attempt.task.id if d.attempt else "")
        for d in devs
    )
    return LabView(now, steps, free, states, finished, budget, in_lab)


def _shown(t: Task, avoid: frozenset[str]) -> ReadyStep:
    """``t`` as a scheduler sees it: the one built before while nothing in it changed (a view is built for every
    decision, and a lab of hundreds of ready steps spent most of its time building them again)."""
    made, last = t.experiment.sample_made, t.shown
    if last is None or last.ready_since != t.ready_since or last.sample_made != made or last.avoid != avoid:
        last = t.shown = ReadyStep(t.id, t.experiment.id, t.step.step, t.step.device, t.ready_since, made,
                                   t.expected_s, t.work_remaining_s, avoid, t.then)
    return last


def problem(a: Assignment, ready: dict[str, Task], devices: dict[str, Device], dry: Dry | None = None) -> str:
    """Why an assignment cannot be carried out, or ''."""
    task, dev = ready.get(a.task), devices.get(a.device)
    if task is None:
        return f"task {a.task!r} is not ready"
    if dev is None or not dev.free:
        return f"device {a.device!r} is not free"
    if dev.type != task.step.device:
        return f"device {a.device!r} is a {dev.type}, task {a.task} needs a {task.step.device}"
    if a.device in task.barred:
        return f"an operator chose another device than {a.device!r} for task {a.task}"
    if dry is not None and a.device in dry(task):
        return f"device {a.device!r} has too little left of its own stock of what task {a.task} uses (twin ctl pending)"
    return ""
