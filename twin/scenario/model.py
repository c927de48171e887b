"""What a scenario is: its pydantic model (``loading`` reads files into it).

A scenario names the lab (device types, instances, drivers, durations,
faults), the chemistry (model, parameter box, targets), the workflow, the
campaign (budget, planner, scheduler, seed), the orchestrator's timeouts and
retry policy, the bus and the clock. ``twin schema`` exports the JSON Schema.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator



class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Duration(_Spec):
    """Lab seconds of one step: lognormal around ``mean_s`` plus a parameter's value."""

    mean_s: float = Field(ge=0, description="mean duration of the step itself")
    cv: float = Field(default=0.1, ge=0, le=2, description="coefficient of variation")
    plus_param: str | None = Field(
        default=None, description="add this experiment parameter (seconds) to the duration"
    )


class Faults(_Spec):
    fail_p: float = Field(default=0.0, ge=0, le=1, description="probability a step fails")
    hang_p: float = Field(default=0.0, ge=0, le=1, description="probability a step never ends")
    mtbc_h: float = Field(default=0.0, ge=0, description="mean lab-hours between crashes; 0 = never")
    restart_s: float = Field(default=1800, ge=0, description="lab seconds a crashed device stays down")


class DeviceType(_Spec):
    driver: str = Field(description="an installed driver name (`twin devices`) or 'package.module:Class'")
    instances: int = Field(default=1, ge=1, le=64)
    steps: list[str] = Field(min_length=1, description="the steps this device type runs")
    duration: Duration
    setup_s: float = Field(default=0, ge=0)
    clean_s: float = Field(default=0, ge=0)
    faults: Faults = Faults()
    cost: float = Field(default=0, ge=0, description="charged for every attempt dispatched to this device type")
    options: dict[str, Any] = Field(default_factory=dict, description="passed to the driver as is")


class Parameter(_Spec):
    low: float
    high: float
    unit: str = ""

    @model_validator(mode="after")
    def _ordered(self) -> Parameter:
        if not self.low < self.high:
            raise ValueError(f"low ({self.low}) must be below high ({self.high})")
        return self


class Condition(_Spec):
    value: float | None = None
    tol: float | None = Field(default=None, gt=0)
    min: float | None = None
    max: float | None = None

    @model_validator(mode="after")
    def _complete(self) -> Condition:
        if (self.value is None) != (self.tol is None):
            raise ValueError("give value and tol together")
        if self.value is None and self.min is None and self.max is None:
            raise ValueError("give value+tol, min, or max")
        return self


class Target(_Spec):
    name: str
    outputs: dict[str, Condition] = Field(min_length=1)


class Chemistry(_Spec):
    model: str = Field(description="the physical model the simulated devices share")
    parameters: dict[str, Parameter] = Field(default_factory=dict)
    targets: list[Target] = Field(default_factory=list)
    stability_s: float = Field(
        default=0, ge=0, description="e-folding time of a waiting sample's signal; 0 = stable"
    )
    noise: float = Field(default=0.01, ge=0, description="relative measurement noise")
    options: dict[str, Any] = Field(default_factory=dict)


class WorkflowStep(_Spec):
    step: str
    device: str = Field(description="a device type of the lab")


class Campaign(_Spec):
    budget: int = Field(default=30, ge=1, description="experiments to propose at most")
    planner: str = "random"
    scheduler: str = "fifo"
    seed: int = 0
    max_in_flight: int = Field(default=4, ge=1, description="experiments in the lab at once")
    stop_on_target: bool = True
    max_lab_hours: float = Field(default=10_000, gt=0)
    max_cost: float | None = Field(default=None, gt=0, description="stop proposing once this much is spent")
    planner_options: dict[str, Any] = Field(default_factory=dict)
    fallback_scheduler: str = Field(default="fifo", description="decides when a scheduler agent on the bus is "
                                    "absent, late or wrong")
    scheduler_deadline_ms: float = Field(default=1000, gt=0, description="wall ms a scheduler agent has per decision")


class Retry(_Spec):
    max_attempts: int = Field(default=3, ge=1)
    max_delay_s: float = Field(default=24 * 3600, gt=0, description="stop retrying a step after this")
    backoff_s: float = Field(default=60, ge=0)
    backoff_max_s: float = Field(default=3600, ge=0)
    jitter: float = Field(default=0.5, ge=0, le=1)


class Orchestration(_Spec):
    timeout_factor: float = Field(default=2.0, ge=1)
    timeout_slack_s: float = Field(default=300, ge=0)
    retry: Retry = Retry()
    quarantine_after: int = Field(default=3, ge=1, description="consecutive failures")
    probe_after_s: float = Field(default=3600, ge=0)
    startup_s: float = Field(default=60, ge=0, description="lab seconds to wait for devices")
    orphan_grace_s: float = Field(default=300, ge=0, description="lab seconds a device goes on with a step after "
                                  "the orchestrator has left the bus, before it stops it in a safe state")
    cancel_grace_s: float = Field(default=60, ge=0, description="lab seconds a timed-out device has to answer the "
                                  "cancel before it is given work again")


class ClockSpec(_Spec):
    mode: Literal["virtual", "scaled", "wall"] = "virtual"
    speed: float = Field(default=3600, gt=0, description="lab seconds per wall second (scaled)")


class BusSpec(_Spec):
    kind: Literal["zenoh", "memory"] = "zenoh"
    mode: Literal["auto", "peer", "client"] = Field(
        default="auto", description="auto: a peer, or a client when it only connects (to a router)")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    connect: list[str] = Field(default_factory=list)
    lease_ms: int = Field(default=1000, ge=100)
    zenoh: dict[str, Any] = Field(default_factory=dict, description="extra Zenoh config paths")
    security: str | None = Field(default=None, description="the lab's security directory (twin security init), "
                                 "relative to the scenario: mutual TLS to the lab's router, with access control")
    insecure: bool = Field(default=False, description="allow bus.listen beyond loopback without security "
                           "(anyone who reaches it can read and forge messages)")


class JobShop(_Spec):
    file: str = Field(description="a job-shop instance in the standard text format, relative to the scenario")


class Training(_Spec):
    """Domain randomisation for training a scheduler: each episode draws a lab from these ranges."""

    duration_scale: tuple[float, float] = Field(default=(1.0, 1.0), description="multiplies every mean duration")
    fault_scale: tuple[float, float] = Field(default=(1.0, 1.0), description="multiplies fail/hang probabilities and crash rates")
    instances: dict[str, tuple[int, int]] = Field(default_factory=dict, description="device type -> [min, max] instances")
    operation_s: tuple[float, float] | None = Field(
        default=None, description="job shops: draw every operation's duration from [low, high] lab-s")
    shuffle_routes: bool = Field(default=False, description="job shops: draw each job's machine order afresh")
    jobshop_sizes: list[tuple[int, int]] = Field(
        default_factory=list, description="job shops: draw a random instance of one of these [jobs, machines] sizes")

    @model_validator(mode="after")
    def _ordered(self) -> Training:
        ranges = {"duration_scale": self.duration_scale, "fault_scale": self.fault_scale,
                  **({"operation_s": self.operation_s} if self.operation_s else {}),
                  **{f"instances.{k}": v for k, v in self.instances.items()}}
        bad = [f"{k}: [{lo}, {hi}] must be low ≤ high, both > 0" for k, (lo, hi) in ranges.items() if not 0 < lo <= hi]
        if bad:
            raise ValueError("; ".join(bad))
        return self


class Scenario(_Spec):
    name: str
    description: str = ""
    lab: str = Field(default="lab", pattern=r"^[A-Za-z0-9_-]+$", description="bus prefix")
    devices: dict[str, DeviceType] = Field(default_factory=dict)
    chemistry: Chemistry = Chemistry(model="none")
    workflow: list[WorkflowStep] = Field(default_factory=list)
    campaign: Campaign = Campaign()
    orchestrator: Orchestration = Orchestration()
    clock: ClockSpec = ClockSpec()
    bus: BusSpec = BusSpec()
    jobshop: JobShop | None = None
    training: Training = Training()

    @model_validator(mode="after")
    def _consistent(self) -> Scenario:
        problems = [f"training.instances.{k}: {k!r} is not a device type of this lab"
                    for k in self.training.instances if k not in self.devices]
        for i, ws in enumerate(self.workflow):
            dev = self.devices.get(ws.device)
            if dev is None:
                problems.append(f"workflow.{i}.device: {ws.device!r} is not a device type of this lab ({', '.join(self.devices)})")
            elif ws.step not in dev.steps:
                problems.append(f"workflow.{i}.step: device type {ws.device!r} does not run {ws.step!r} (it runs {dev.steps})")
        if not self.workflow and self.jobshop is None:
            problems.append("workflow: empty; give the steps of an experiment, or a jobshop file")
        if problems:
            raise ValueError("; ".join(problems))
        return self

    def instance_names(self, device_type: str) -> list[str]:
        n = self.devices[device_type].instances
        return [f"{device_type}-{i + 1}" for i in range(n)] if n > 1 else [device_type]


def expected_duration(duration: Duration, params: dict[str, Any], setup_s: float, clean_s: float) -> float:
    """A step's mean duration, which the campaign turns into a deadline."""
    extra = float(params.get(duration.plus_param, 0.0)) if duration.plus_param else 0.0
    return duration.mean_s + extra + setup_s + clean_s
