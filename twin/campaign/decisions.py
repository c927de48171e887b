"""The two decisions that close the loop, as small protocols.

- a ``Planner`` says which experiments to try next;
- a ``Scheduler`` says which ready step runs on which free device, or to wait.

Both see read-only views built by the orchestrator; they never touch the bus.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol


@dataclass(frozen=True)
class RouteStep:
    step: str
    device: str  # a device type
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Proposal:
    params: dict[str, Any]
    route: tuple[RouteStep, ...] | None = None  # None: the scenario's workflow
    cost: float = 0.0  # what the experiment's materials cost (reagents bought): added to the campaign's cost


@dataclass(frozen=True)
class Outcome:
    """One finished experiment as a planner sees it."""

    params: dict[str, Any]
    outputs: dict[str, Any] | None  # None when abandoned
    score: float | None  # distance to the nearest unmet target; 0 = met
    reason: str = ""
    infeasible: bool = False  # a device refused these parameters (or they are outside its safe envelope)


class Planner(Protocol):
    """``propose`` may answer fewer than ``n``, or none; a planner with nothing more may say why in an optional
    ``why_no_more`` attribute of text, which the summary's ``ended`` then gives."""

    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]: ...


@dataclass(frozen=True)
class ReadyStep:
    task: str
    experiment: int
    step: str
    device_type: str
    ready_since: float
    sample_made: float | None  # lab time the experiment's sample was made, if any
    expected_s: float
    work_remaining_s: float
    avoid: frozenset[str] = frozenset()  # failed this step, and another instance can take it
    then: tuple[tuple[str, float], ...] = ()  # the experiment's later steps: (device type, expected s)
    campaign: str = ""  # in a lab of several campaigns with one scheduler: whose step (``LabView.campaigns``)


@dataclass(frozen=True)
class FreeDevice:
    name: str
    device_type: str


@dataclass(frozen=True)
class DeviceState:
    """Every device of the lab, free or not, as a scheduler may weigh it."""

    name: str
    device_type: str
    free: bool
    online: bool
    busy_until: float | None  # expected end of its current step (lab time), if busy
    attempts: int  # steps sent to it so far
    failures: int
    busy_s: float
    then: tuple[tuple[str, float], ...] = ()  # its running experiment's later steps, if busy
    task: str = ""  # the step it runs now, if busy (a plan kept by the scheduler can go on after a resume)


@dataclass(frozen=True)
class CampaignState:
    """One campaign of a shared lab, as the lab's one scheduler may weigh its steps."""

    name: str
    priority: int
    share: float  # the part of the device time it is due, among the campaigns running (they sum to 1)
    used: float  # the part of the device time it has had so far
    finished: int  # its experiments done or abandoned
    budget: int
    stability_s: float = 0.0  # how long its samples keep (its chemistry's; 0: for ever)


@dataclass(frozen=True)
class LabView:
    now: float
    ready: tuple[ReadyStep, ...]
    free: tuple[FreeDevice, ...]
    devices: tuple[DeviceState, ...] = ()
    finished: int = 0  # experiments done or abandoned
    budget: int = 0
    in_lab: int = 0  # experiments proposed and not finished
    campaigns: tuple[CampaignState, ...] = ()  # a lab of several campaigns with one scheduler: each running one


@dataclass(frozen=True)
class Assignment:
    task: str
    device: str


class Scheduler(Protocol):
    """``decide`` may also return an awaitable of the list (an agent on the bus, a training env).

    The orchestrator asks again at once while it sent something and a free
    device could still take a ready step, so a scheduler may assign one pair
    at a time; an empty list means wait for the next event.
    """

    def decide(self, view: LabView) -> list[Assignment]: ...


def capable(step: ReadyStep, free: tuple[FreeDevice, ...]) -> list[FreeDevice]:
    """Free devices of the step's type that it need not avoid."""
    return [d for d in free if d.device_type == step.device_type and d.name not in step.avoid]


def unfit(a: Assignment, step: ReadyStep | None, device: FreeDevice | None) -> str:
    """Why the view rules out ``a`` (``step`` and ``device``: what the view holds under its names), or ''."""
    if step is None:
        return f"{a.task} → {a.device}: step {a.task!r} is not ready"
    if device is None:
        return f"{a.task} → {a.device}: device {a.device!r} is not free"
    if device.device_type != step.device_type:
        return f"{a.task} → {a.device}: {a.device} is a {device.device_type}, the step needs a {step.device_type}"
    return ""
