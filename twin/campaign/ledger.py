"""What the core keeps about experiments, steps, attempts and devices, and its counters.

An experiment is ``pending`` until its first step is dispatched, ``running``
while any step is in the lab or waiting to retry, then ``done`` or
``abandoned`` with a reason. Shutdown leaves the rest ``pending``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from twin.campaign.events import Status
from twin.campaign.decisions import RouteStep
from twin.core.errors import AccountingError

FINAL = (Status.DONE, Status.ABANDONED)


@dataclass(slots=True)
class Experiment:
    id: int
    params: dict[str, Any]
    route: tuple[RouteStep, ...]
    t_proposed: float
    status: Status = Status.PENDING
    reason: str = ""
    stage: int = 0
    sample: dict[str, Any] | None = None
    sample_made: float | None = None
    outputs: dict[str, Any] = field(default_factory=dict)
    scores: dict[str, float] = field(default_factory=dict)
    attempts: int = 0
    retries: int = 0
    degraded: bool = False
    degraded_before: str = ""  # the step its sample waited for past chemistry.stability_s
    infeasible: bool = False
    t_done: float | None = None


@dataclass(slots=True)
class Task:
    """One step of one experiment, across its attempts."""

    id: str
    experiment: Experiment
    step: RouteStep
    ready_since: float
    expected_s: float
    work_remaining_s: float
    then: tuple[tuple[str, float], ...] = ()  # later steps: (device type, expected s)
    attempts: int = 0
    failed_on: list[str] = field(default_factory=list)  # devices, oldest failure first
    refusals: int = 0  # "not now" answers, which do not count as attempts
    excused: int = 0  # attempts refused "not now" or stopped by an operator: numbered, not counted against retries
    retrying_since: float | None = None  # its first failure or "not now": retry.max_delay_s counts from here
    barred: frozenset[str] = frozenset()  # devices it may not go to (an operator chose another device)
    # its ReadyStep as a scheduler last saw it (dispatch.view builds it again only if it changed): a cache, not state
    shown: Any = field(default=None, compare=False, repr=False)


@dataclass(slots=True)
class Attempt:
    task: Task
    n: int
    device: str
    t_sent: float
    t_accepted: float | None = None
    resolved: bool = False
    token: str = ""


@dataclass(slots=True)
class Device:
    name: str
    type: str
    online: bool = False
    quarantined: bool = False
    attempt: Attempt | None = None
    cancelling: Attempt | None = None  # timed out; the device is not reused before it answers the cancel
    unanswered: Attempt | None = None  # a cancel it never answered: a "not now" from it means it is still busy
    stuck: Attempt | None = None  # refused work with that cancel unanswered: quarantined until it answers (stuck.py)
    said_stuck: bool = False  # the alert device.stuck was given for it (once a campaign)
    refusals_in_a_row: int = 0  # "not now" answers since it last finished a step (device.refusing)
    probing: bool = False  # stuck, and out of quarantine for a probe: back only once a step is done on it
    consecutive_failures: int = 0
    busy_s: float = 0.0
    failures: int = 0
    attempts: int = 0
    lost_at: float | None = None  # when it last left the bus: a loss sooner than a lease after is a flap
    held_by: str = ""  # another campaign of a shared lab has a step on it

    @property
    def free(self) -> bool:
        return (self.online and not self.quarantined and self.attempt is None and self.cancelling is None
                and not self.held_by)

    @property
    def state(self) -> str:
        if not self.online:
            return "offline"
        if self.quarantined:
            return "quarantined"
        return "busy" if self.attempt or self.cancelling or self.held_by else "idle"


#: The reason an experiment the planner proposed wrongly is abandoned with (then what is wrong).
UNRUNNABLE = "the planner proposed what cannot be run"


@dataclass(slots=True)
class Counters:
    """What happened to attempts and messages; ``Summary`` is built from these."""

    attempts: int = 0
    failed: int = 0
    timed_out: int = 0
    retried: int = 0
    invalid: int = 0
    rejected: int = 0  # well-formed but not from the device the attempt is with (forged, misrouted, stale token)
    flaps: int = 0  # presence lost again within a lease: not trusted to fail an attempt
    infeasible: int = 0  # experiments a device refused, or its safe envelope excluded
    refused_now: int = 0  # "not now" refusals: retried, not counted as attempts
    late: int = 0
    device_lost: int = 0  # devices that left the bus (a flap aside)
    steps_lost: int = 0  # attempts failed because their device left
    quarantined: int = 0
    degraded: int = 0
    cancels_unanswered: int = 0
    stuck: int = 0  # quarantines of a device still running a step it was told to cancel


def check_accounting(experiments: list[Experiment], proposed: int) -> None:
    """Every proposed experiment is done, abandoned with a reason, or pending."""
    problems = []
    if len(experiments) != proposed:
        problems.append(f"{proposed} proposed but {len(experiments)} recorded")
    for e in experiments:
        if e.status not in (*FINAL, Status.PENDING):
            problems.append(f"experiment {e.id} is {e.status!r} at shutdown")
        if e.status == Status.ABANDONED and not e.reason:
            problems.append(f"experiment {e.id} abandoned without a reason")
        if e.status == Status.DONE and e.stage != len(e.route):
            problems.append(f"experiment {e.id} done after {e.stage} of {len(e.route)} steps")
    if problems:
        raise AccountingError("accounting invariant broken: " + "; ".join(problems))
