"""What a scenario is: its pydantic model (``loading`` reads files into it; the campaign section is ``campaign``,
the orchestrator and consumables sections ``operations``, the training section ``training``).

A scenario names the lab (device types, instances, drivers, durations,
faults), the chemistry (model, parameter box, targets), the workflow, the
campaign (budget, planner, scheduler, seed), the orchestrator's timeouts and
retry policy, the bus and the clock. ``twin schema`` exports the JSON Schema.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, StringConstraints, ValidationInfo, field_validator, model_validator

from twin.core import keys
from twin.core.bus.endpoints import HOW, not_endpoints
from twin.scenario.campaign import Campaign
from twin.scenario.operations import Consumable, Orchestration, usage_problems
from twin.scenario.spec import MAX_S, MAX_VALUE, Label, Name, Spec
from twin.scenario.training import Training



class Duration(Spec):
    """Lab seconds of one step: lognormal around ``mean_s`` plus a parameter's value."""

    mean_s: float = Field(ge=0, le=MAX_S, description="mean duration of the step itself")
    cv: float = Field(default=0.1, ge=0, le=2, description="coefficient of variation")
    plus_param: str | None = Field(
        default=None, description="add this parameter (seconds) to the duration: one of chemistry.parameters, "
        "or one the workflow's step gives (the step's value wins)"
    )


class Faults(Spec):
    fail_p: float = Field(default=0.0, ge=0, le=1, description="probability a step fails")
    hang_p: float = Field(default=0.0, ge=0, le=1, description="probability a step never ends")
    mtbc_h: float = Field(default=0.0, ge=0, le=1e6, description="mean lab-hours between crashes; 0 = never")
    restart_s: float = Field(default=1800, ge=0, le=MAX_S, description="lab seconds a crashed device stays down")

    @field_validator("mtbc_h")
    @classmethod
    def _crashes_take_time(cls, mtbc_h: float) -> float:
        if 0 < mtbc_h < 0.01:
            raise ValueError("under 0.01 lab-h (36 s), a device would crash before it starts anything: use 0 "
                             "for never, or at least 0.01")
        return mtbc_h


class StandIn(Spec):
    """A simulated driver that runs a device type's steps where the lab runs in virtual time."""

    driver: str = Field(description="an installed driver name (`twin devices`) or 'package.module:Class' that "
                        "simulates the type's steps (waiting with ctx.clock.sleep)")
    options: dict[str, Any] = Field(default_factory=dict, description="passed to that driver as is")


class DeviceType(Spec):
    driver: str = Field(description="an installed driver name (`twin devices`) or 'package.module:Class'")
    twin: StandIn | None = Field(
        default=None, description="the simulated driver that stands in for this one whenever the clock is "
        "virtual (`twin run --clock virtual`, `twin whatif`, `twin bench`, `twin train`): a driver that talks to a "
        "real instrument keeps wall time, and one that waits on I/O cannot be trained on; the type's duration, "
        "set-up, cleaning and faults stay as written")
    instances: int = Field(default=1, ge=1, le=64, description="identical devices of this type (named <type>, or "
                           "<type>-1, <type>-2, ... when several); a step may run on any of them")
    steps: list[Label] = Field(min_length=1, max_length=64, description="the steps this device type runs")
    duration: Duration = Field(description="how long the step itself takes (lab seconds), drawn per attempt")
    setup_s: float = Field(default=0, ge=0, le=MAX_S, description="lab seconds before every step (loading, "
                           "warming up), part of the step's time and its deadline")
    clean_s: float = Field(default=0, ge=0, le=MAX_S, description="lab seconds after every step, before the device "
                           "reports it done: the sample waits (and ages) with the device, and the step's deadline "
                           "includes it")
    faults: Faults = Field(default=Faults(), description="simulated faults, injected by the twin around the "
                           "driver for rehearsing failures")
    cost: float = Field(default=0, ge=0, le=MAX_VALUE, description="charged for every attempt this device type "
                        "runs (a step it refuses, \"not now\" or infeasible, never ran and costs nothing)")
    cost_per_hour: float = Field(default=0, ge=0, le=MAX_VALUE, description="charged for each instance of this "
                                 "type for every lab-hour the campaign runs, busy or not (its rent, upkeep, an "
                                 "operator's time): `twin whatif` then weighs more instances against the hours "
                                 "they save")
    envelope: dict[Label, Parameter] = Field(default_factory=dict, description="the safe range of parameters "
                                             "this device accepts: an experiment outside it is refused before "
                                             "anything is sent (abandoned as infeasible)")
    options: dict[str, Any] = Field(default_factory=dict, description="passed to the driver as is")

    @model_validator(mode="after")
    def _twin_of_a_driver(self) -> DeviceType:
        if self.twin is not None and "operator" in (self.driver, self.twin.driver):
            raise ValueError("twin: a twin stands in for a driver, and people (driver: operator) are not one, nor "
                             "stand in for one: on a virtual clock the campaign confirms their steps itself")
        return self

    @model_validator(mode="after")
    def _faults_of_people(self) -> DeviceType:
        # the twin injects faults around a driver, and people have none: such faults would never happen
        if self.driver == "operator" and self.faults != Faults():
            raise ValueError("faults: people (driver: operator) are not simulated to fail, crash or hang; a step "
                             "of theirs fails when nobody confirms it before its deadline (duration, "
                             "orchestrator.timeout_factor): remove faults here")
        return self


class Parameter(Spec):
    low: float = Field(ge=-MAX_VALUE, le=MAX_VALUE, description="the least value the planner may propose")
    high: float = Field(ge=-MAX_VALUE, le=MAX_VALUE, description="the most (above low)")
    unit: str = Field(default="", max_length=32, description="shown with the value; not converted")

    def __getitem__(self, name: str) -> Any:
        """``p["low"]`` as ``p.low``: a planner may read its box as the mapping the scenario writes it as."""
        if name in ("low", "high", "unit"):
            return getattr(self, name)
        raise KeyError(f"{name!r}: a parameter has low, high and unit")

    @model_validator(mode="after")
    def _ordered(self) -> Parameter:
        if not self.low < self.high:
            raise ValueError(f"low ({self.low}) must be below high ({self.high})")
        return self


class Condition(Spec):
    value: float | None = Field(default=None, description="met within value ± tol (give both)")
    tol: float | None = Field(default=None, gt=0, description="the half-width of the window around value")
    min: float | None = Field(default=None, description="met at or above this")
    max: float | None = Field(default=None, description="met at or below this")

    @model_validator(mode="after")
    def _complete(self) -> Condition:
        if (self.value is None) != (self.tol is None):
            raise ValueError("give value and tol together")
        if self.value is None and self.min is None and self.max is None:
            raise ValueError("give value+tol, min, or max")
        if self.min is not None and self.max is not None and self.min > self.max:
            raise ValueError(f"min ({self.min}) is above max ({self.max}): no output can meet it")
        return self


class Target(Spec):
    name: Label = Field(description="names the target in the summary and the viewer")
    outputs: dict[Label, Condition] = Field(min_length=1, description="output -> the condition it must meet; "
                                            "the target is met when one experiment meets them all")


class Chemistry(Spec):
    model: Label = Field(default="none", description="the physical model the simulated devices share ('none': "
                         "none, for a lab whose devices only keep time, as the machine driver does)")
    parameters: dict[Label, Parameter] = Field(default_factory=dict, max_length=64, description="the box the planner "
                                               "proposes experiments in: parameter -> its range")
    targets: list[Target] = Field(default_factory=list, max_length=64, description="what the campaign looks for; "
                                  "with campaign.stop_on_target it stops proposing once every one is met")
    stability_s: float = Field(
        default=0, ge=0, le=MAX_S, description="e-folding time of a waiting sample's signal; 0 = stable"
    )
    noise: float = Field(default=0.01, ge=0, le=10, description="relative measurement noise")
    options: dict[str, Any] = Field(default_factory=dict, description="passed to the chemistry model as is")

    @field_validator("targets")
    @classmethod
    def _unique_targets(cls, targets: list[Target]) -> list[Target]:
        names = [t.name for t in targets]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"target names {twice} are given more than once: each needs its own name")
        return targets


StepValue = Annotated[float, Field(ge=-MAX_VALUE, le=MAX_VALUE)] | bool | Annotated[str, StringConstraints(max_length=256)]


class WorkflowStep(Spec):
    step: Label = Field(description="the step type, one of the device type's steps")
    device: str = Field(max_length=64, description="a device type of the lab")
    params: dict[Label, StepValue] = Field(default_factory=dict, max_length=64, description="this step's own "
                                           "parameters, sent with the experiment's (these win a clash)")


class ClockSpec(Spec):
    mode: Literal["virtual", "scaled", "wall"] = Field(default="virtual", description="virtual: as fast as the CPU "
                                                       "allows, repeatable; scaled: speed lab seconds per wall "
                                                       "second; wall: real time, for real devices")
    speed: float = Field(default=3600, gt=0, le=1e9, description="lab seconds per wall second (scaled)")


class BusSpec(Spec):
    kind: Literal["zenoh", "memory"] = Field(default="zenoh", description="zenoh (devices may be other processes "
                                             "and hosts) or memory (every device in this process, no sockets)")
    mode: Literal["auto", "peer", "client"] = Field(
        default="auto", description="auto: a peer, or a client when it only connects (to a router)")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:0"], description="Zenoh endpoints the lab "
                              "listens on (port 0: any free one)")
    connect: list[str] = Field(default_factory=list, description="Zenoh endpoints to connect to (a router, `twin "
                               "router`)")
    lease_ms: int = Field(default=1000, ge=100, le=600_000, description="a peer silent this long is gone: a hung "
                          "device's liveliness token lapses after it")
    connect_timeout_ms: int = Field(default=5000, ge=100, le=600_000, description="how long a session that "
                                    "connects waits for its router or lab before it says nothing answered")
    zenoh: dict[str, Any] = Field(default_factory=dict, description="extra Zenoh config paths")
    security: str | None = Field(default=None, description="the lab's security directory (twin security init), "
                                 "relative to the scenario: mutual TLS to the lab's router, with access control")
    insecure: bool = Field(default=False, description="allow bus.listen beyond loopback without security "
                           "(anyone who reaches it can read and forge messages)")

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, endpoints: list[str]) -> list[str]:
        bad = not_endpoints(endpoints)
        if bad:
            raise ValueError(f"{bad} are not Zenoh endpoints: {HOW}")
        return endpoints


class JobShop(Spec):
    file: str = Field(max_length=1024, description="a job-shop instance in the standard text format or "
                      "Taillard's, relative to the scenario (or else to the current directory)")
    instance: str | None = Field(default=None, max_length=128, description="which instance of a file that holds "
                                    "several, by the name on its 'instance NAME' line (OR-Library's jobshop1.txt), "
                                    "or FILE-k for the k-th of Taillard's own files (tai15_15-3)")


class SharedCampaign(Spec):
    """One of several campaigns a lab serves at once: its own chemistry, workflow, planner and budget on the
    lab's devices and consumables. A section it leaves out is the lab file's."""

    name: Name = Field(description="the campaign's id: its journal, its samples' ids, `twin ctl --campaign`")
    owner: str = Field(default="", max_length=128, description="who it is for (shown by twin ctl status)")
    priority: int = Field(default=0, ge=-1000, le=1000, description="higher picks free devices first")
    share: float = Field(default=1.0, gt=0, le=1000, description="among campaigns of equal priority, the one "
                         "furthest below its share of the device time used so far picks first")
    start_h: float = Field(default=0.0, ge=0, le=MAX_S / 3600, description="lab hours after the lab starts at "
                           "which it is submitted")
    after: Name | None = Field(default=None, description="submitted when this other campaign has ended (one "
                               "after the other), instead of at start_h")
    chemistry: Chemistry | None = Field(default=None, description="this campaign's chemistry (default: the lab's)")
    workflow: list[WorkflowStep] | None = Field(default=None, description="this campaign's workflow (default: the "
                                                "lab's)")
    campaign: Campaign | None = Field(default=None, description="this campaign's settings (default: the lab's)")


class Scenario(Spec):
    name: Name = Field(description="names the run's journal (runs/<name>-seed<N>-<time>.db): letters, digits, "
                       "'_', '-', '.'")
    description: str = Field(default="", max_length=4096, description="one line about the scenario, for people")
    lab: str = Field(default="lab", pattern=keys.LAB_NAME, description="bus prefix")
    devices: dict[Name, DeviceType] = Field(default_factory=dict, max_length=256, description="the lab: device "
                                            "type -> its driver, instances, steps, durations and faults")
    chemistry: Chemistry = Field(default=Chemistry(), description="the physical model "
                                 "the simulated devices share, the parameter box and the targets")
    workflow: list[WorkflowStep] = Field(default_factory=list, description="the steps of every experiment, in order")
    campaign: Campaign = Field(default=Campaign(), description="budget, planner, scheduler and seed")
    orchestrator: Orchestration = Field(default=Orchestration(), description="deadlines, retries, "
                                        "quarantine and recovery")
    clock: ClockSpec = Field(default=ClockSpec(), description="the lab's clock")
    bus: BusSpec = Field(default=BusSpec(), description="the message bus the devices and the lab share")
    jobshop: JobShop | None = Field(default=None, description="a job-shop instance run as a lab (one device per "
                                    "machine, m0, m1, ..., an experiment per job); `devices:` then changes the "
                                    "machines (m0: {instances: 2})")
    consumables: dict[Name, Consumable] = Field(default_factory=dict, max_length=256, description="reagents, vials, "
                                                "tips: what the lab holds and what its steps use up")
    training: Training = Field(default=Training(), description="`twin train`: what a scheduler is trained to "
                               "minimise and the labs it is trained on")
    campaigns: list[SharedCampaign] = Field(default_factory=list, max_length=64, description="several campaigns "
                                            "sharing this lab's devices (each with its own ledger and journal); "
                                            "empty: the one campaign of this file")

    def _types(self) -> str:
        return ", ".join(self.devices) or "it has none"

    def _parameter_ranges(self) -> dict[str, tuple[float, float]]:
        """Each parameter's lowest low and highest high over the lab's chemistry and its campaigns', and the
        values their workflows' steps give."""
        ranges: dict[str, tuple[float, float]] = {}

        def widen(p: str, low: float, high: float) -> None:
            was = ranges.get(p, (low, high))
            ranges[p] = (min(was[0], low), max(was[1], high))

        for chem in [self.chemistry, *(c.chemistry for c in self.campaigns if c.chemistry is not None)]:
            for p, r in chem.parameters.items():
                widen(p, r.low, r.high)
        for flow in [self.workflow, *(c.workflow for c in self.campaigns if c.workflow is not None)]:
            for ws in flow:
                for p, v in ws.params.items():
                    if isinstance(v, (int, float)) and not isinstance(v, bool):
                        widen(p, float(v), float(v))
        return ranges

    @model_validator(mode="after")
    def _consistent(self, info: ValidationInfo) -> Scenario:
        problems = [f"training.instances.{k}: {k!r} is not a device type of this lab ({self._types()})"
                    for k in self.training.instances if k not in self.devices]
        if not self.devices and self.jobshop is None:
            problems.append("devices: none; a lab needs at least one device type (`twin devices` lists the drivers, "
                            "`twin schema` the fields)")
        steps = {st for dev in self.devices.values() for st in dev.steps}
        lab_only = bool(info.context and info.context.get("lab_only"))  # `twin lab serve`: campaigns come later
        ranges = None if lab_only else self._parameter_ranges()
        for name, c in self.consumables.items():
            problems += usage_problems(name, c, ranges)
            holder = self.devices.get(c.device) if c.device is not None else None
            if c.device is not None and holder is None:
                problems.append(f"consumables.{name}.device: {c.device!r} is not a device type of this lab "
                                f"({self._types()})")
            elif holder is not None:  # a stock per instance is used only by the steps that run on the instances
                problems += [f"consumables.{name}.used_by.{st}: {st!r} does not run on a {c.device} (it runs "
                             f"{', '.join(holder.steps)}), so it can never use a {c.device}'s own {name}"
                             for st in c.used_by if st not in holder.steps]
                continue
            problems += [f"consumables.{name}.used_by.{st}: {st!r} is no device's step ({', '.join(sorted(steps))})"
                         for st in c.used_by if st not in steps]
        for i, rule in enumerate(self.orchestrator.recovery):
            if rule.device is not None and rule.device not in self.devices:
                problems.append(f"orchestrator.recovery.{i}.device: {rule.device!r} is not a device type of this "
                                f"lab ({self._types()})")
            if rule.step is not None and rule.step not in steps:
                problems.append(f"orchestrator.recovery.{i}.step: {rule.step!r} is no device's step "
                                f"({', '.join(sorted(steps))})")
        for i, ws in enumerate(self.workflow):
            dev = self.devices.get(ws.device)
            if dev is None:
                problems.append(f"workflow.{i}.device: {ws.device!r} is not a device type of this lab "
                                f"({self._types()})")
            elif ws.step not in dev.steps:
                problems.append(f"workflow.{i}.step: device type {ws.device!r} does not run {ws.step!r} (it runs {dev.steps})")
        if not self.workflow and self.jobshop is None and not self.campaigns and not lab_only:
            problems.append("workflow: empty; give the steps of an experiment, or a jobshop file, or campaigns: (a "
                            "lab file for `twin lab serve`, which takes its campaigns later, needs none of them: "
                            "`twin validate --serve` checks one)")
        problems += self._instance_clashes() + self._sharing()
        if not self.campaigns and not lab_only:  # a lab of several campaigns: checked with each one's chemistry
            problems += self._plus_params() + self._envelopes()
        if self.bus.security and self.bus.kind != "zenoh":
            problems.append("bus.security: security is for the zenoh bus; the memory bus has no one to keep out")
        if problems:  # one line each, every one naming its own field (the loader lists them)
            raise ValueError("\n".join(problems))
        return self

    def _sharing(self) -> list[str]:
        names = [c.name for c in self.campaigns]
        problems = [f"campaigns.{i}.name: {c.name!r} is the name of campaigns.{names.index(c.name)} too"
                    for i, c in enumerate(self.campaigns) if names.index(c.name) != i]
        for i, c in enumerate(self.campaigns):
            if c.after is not None and (c.after not in names or c.after == c.name):
                problems.append(f"campaigns.{i}.after: {c.after!r} is not another campaign of this lab "
                                f"({', '.join(n for n in names if n != c.name) or 'none'})")
        after = {c.name: c.after for c in self.campaigns}
        for c in self.campaigns:  # a chain of `after` that comes back to where it started never starts
            chain = [c.name]
            while after.get(chain[-1]) in after and len(chain) <= len(after):
                chain.append(after[chain[-1]])
                if chain[-1] == c.name:
                    if c.name == min(chain):  # said once per cycle
                            problems.append(f"campaigns: {' -> '.join(chain)} waits for itself (after)")
                    break
        return problems

    def _instance_clashes(self) -> list[str]:
        owner: dict[str, str] = {}
        problems = []
        for dtype in self.devices:
            for name in self.instance_names(dtype):
                if name in owner:
                    problems.append(f"devices.{dtype}: its instance {name!r} has the name of an instance of "
                                    f"{owner[name]!r}; rename one of the two device types")
                owner[name] = dtype
        return problems

    def _envelopes(self) -> list[str]:
        problems = []
        for dtype, spec in self.devices.items():
            for name, safe in spec.envelope.items():
                box = self.chemistry.parameters.get(name)
                where = f"devices.{dtype}.envelope.{name}"
                given = self._step_given(dtype, name)
                if box is None and not given:
                    problems.append(f"{where}: {name!r} is neither a parameter of chemistry.parameters "
                                    f"({', '.join(self.chemistry.parameters) or 'none'}) nor one a workflow step on "
                                    f"{dtype} gives")
                elif box is not None and (box.high < safe.low or safe.high < box.low):
                    problems.append(f"{where}: [{safe.low:g}, {safe.high:g}] does not overlap the planner's box "
                                    f"[{box.low:g}, {box.high:g}]: no experiment could run")
                for i, value in given:
                    if isinstance(value, (int, float)) and not safe.low <= value <= safe.high:
                        problems.append(f"workflow.{i}.params.{name}: {value:g} is outside {where} [{safe.low:g}, "
                                        f"{safe.high:g}]: every experiment would be refused at this step")
        return problems

    def _step_given(self, dtype: str, name: str) -> list[tuple[int, Any]]:
        """(index, value) of each workflow step on ``dtype`` that gives parameter ``name`` itself."""
        return [(i, ws.params[name]) for i, ws in enumerate(self.workflow) if ws.device == dtype and name in ws.params]

    def _plus_params(self) -> list[str]:
        if self.jobshop is not None:
            return []  # a job shop's operations carry their own durations
        problems = []
        for dtype, spec in self.devices.items():
            p = spec.duration.plus_param
            if not p:
                continue
            box = self.chemistry.parameters.get(p)
            given = self._step_given(dtype, p)
            if box is None and not given:
                problems.append(f"devices.{dtype}.duration.plus_param: {p!r} is neither a parameter of "
                                f"chemistry.parameters ({', '.join(self.chemistry.parameters) or 'none'}) nor one "
                                f"a workflow step on {dtype} gives (params: {{{p}: SECONDS}})")
            elif box is not None and box.low < 0:
                problems.append(f"devices.{dtype}.duration.plus_param: {p!r} can be negative (low {box.low}), "
                                "which would make the step's duration negative: its low must be ≥ 0")
            elif box is not None and box.high > MAX_S:
                problems.append(f"devices.{dtype}.duration.plus_param: {p!r} reaches {box.high:g} lab-s (its "
                                f"high), more than a step may last ({MAX_S:g}, as duration.mean_s): lower its high")
            for i, value in given:  # the step's own value wins over the experiment's
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= MAX_S:
                    problems.append(f"workflow.{i}.params.{p}: {value!r} is what devices.{dtype}.duration."
                                    f"plus_param adds to the step's duration: give it lab seconds, from 0 to "
                                    f"{MAX_S:g} (as duration.mean_s)")
        return problems

    def instance_names(self, device_type: str) -> list[str]:
        return instance_names(device_type, self.devices[device_type].instances)


def instance_names(device_type: str, n: int) -> list[str]:
    """The names of ``n`` instances of a device type: the type's own name for one, else ``type-1`` … ``type-n``."""
    return [f"{device_type}-{i + 1}" for i in range(n)] if n > 1 else [device_type]


def expected_duration(duration: Duration, params: dict[str, Any], setup_s: float, clean_s: float) -> float:
    """A step's mean duration, which the campaign turns into a deadline."""
    extra = float(params.get(duration.plus_param, 0.0)) if duration.plus_param else 0.0
    return duration.mean_s + extra + setup_s + clean_s


def why_runs_vary(s: Scenario) -> str:
    """Why two runs of ``s`` on one seed, scheduled alike, could still differ from each other — chance in its
    durations or faults, experiments proposed from results — or '' for a lab that runs as it was played (a job
    shop): what an offline bound, one run standing for every seed, and a plan played ahead need."""
    if s.campaigns:
        return "it is a lab of several campaigns"
    if s.campaign.planner != "fixed":
        return (f"its experiments are proposed as it runs (campaign.planner: {s.campaign.planner}); only a lab whose "
                "experiments are all known before it starts (a job shop) runs as it was played")
    for name, d in s.devices.items():
        if d.duration.cv > 0:
            return f"devices.{name}.duration.cv is {d.duration.cv:g}: its steps' durations vary from run to run"
        for fault in ("fail_p", "hang_p", "mtbc_h"):
            if getattr(d.faults, fault) > 0:
                return f"devices.{name}.faults.{fault} is {getattr(d.faults, fault):g}: its faults come by chance"
    return ""
