"""What the orchestrator keeps about experiments, steps, attempts and devices.

An experiment is ``pending`` until its first step is dispatched, ``running``
while any step is in the lab or waiting to retry, then ``done`` or
``abandoned`` with a reason. Shutdown leaves the rest ``pending``.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Any

from twin.decisions import RouteStep
from twin.errors import AccountingError

FINAL = ("done", "abandoned")


@dataclass
class Experiment:
    id: int
    params: dict[str, Any]
    route: tuple[RouteStep, ...]
    t_proposed: float
    status: str = "pending"
    reason: str = ""
    stage: int = 0
    sample: dict[str, Any] | None = None
    sample_made: float | None = None
    outputs: dict[str, Any] = field(default_factory=dict)
    scores: dict[str, float] = field(default_factory=dict)
    attempts: int = 0
    retries: int = 0
    degraded: bool = False
    t_done: float | None = None


@dataclass
class Task:
    """One step of one experiment, across its attempts."""

    id: str
    experiment: Experiment
    step: RouteStep
    first_ready: float
    ready_since: float
    expected_s: float
    work_remaining_s: float
    then: tuple[tuple[str, float], ...] = ()  # later steps: (device type, expected s)
    attempts: int = 0
    failed_on: list[str] = field(default_factory=list)  # devices, oldest failure first


@dataclass
class Attempt:
    task: Task
    n: int
    device: str
    t_sent: float
    deadline: asyncio.TimerHandle | None = None
    t_accepted: float | None = None
    resolved: bool = False


@dataclass
class Device:
    name: str
    type: str
    online: bool = False
    quarantined: bool = False
    attempt: Attempt | None = None
    consecutive_failures: int = 0
    busy_s: float = 0.0
    failures: int = 0
    steps_done: int = 0
    attempts: int = 0

    @property
    def free(self) -> bool:
        return self.online and not self.quarantined and self.attempt is None

    @property
    def state(self) -> str:
        if not self.online:
            return "offline"
        if self.quarantined:
            return "quarantined"
        return "busy" if self.attempt else "idle"


def check_accounting(experiments: list[Experiment], proposed: int) -> None:
    """Every proposed experiment is done, abandoned with a reason, or pending."""
    problems = []
    if len(experiments) != proposed:
        problems.append(f"{proposed} proposed but {len(experiments)} recorded")
    for e in experiments:
        if e.status not in (*FINAL, "pending"):
            problems.append(f"experiment {e.id} is {e.status!r} at shutdown")
        if e.status == "abandoned" and not e.reason:
            problems.append(f"experiment {e.id} abandoned without a reason")
        if e.status == "done" and e.stage != len(e.route):
            problems.append(f"experiment {e.id} done after {e.stage} of {len(e.route)} steps")
    if problems:
        raise AccountingError("accounting invariant broken: " + "; ".join(problems))
