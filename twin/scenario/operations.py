"""How a lab is operated when things go wrong or run out: the orchestrator's deadlines and retries, the
operator's recovery of a failed step, and the consumables its steps use (the ``orchestrator`` and
``consumables`` sections of a scenario)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from twin.scenario.spec import MAX_S, MAX_VALUE, Label, Name, Spec


class Retry(Spec):
    max_attempts: int = Field(default=3, ge=1, le=100, description="attempts of one step before its experiment is "
                              "abandoned (or an operator is asked: orchestrator.recovery)")
    max_delay_s: float = Field(default=24 * 3600, gt=0, le=1e8, description="stop retrying a step this long after its "
                              "first failure (lab seconds; time queued before it is not counted)")
    backoff_s: float = Field(default=60, ge=0, le=MAX_S, description="lab seconds before the first retry; doubled "
                             "for each one after")
    backoff_max_s: float = Field(default=3600, ge=0, le=MAX_S, description="the longest wait before a retry")
    jitter: float = Field(default=0.5, ge=0, le=1, description="each wait is drawn within ± this share of it")


RecoveryOption = Literal["retry", "another_device", "skip", "alternative", "abandon"]


def _every_option() -> list[RecoveryOption]:
    return ["retry", "another_device", "skip", "alternative", "abandon"]


class SimulatedOperator(Spec):
    """Virtual time: the operator a what-if assumes — who answers after ``after_s`` lab seconds with ``answer``."""

    after_s: float = Field(ge=0, le=MAX_S, description="lab seconds before the simulated operator answers")
    answer: RecoveryOption = Field(description="the option the simulated operator chooses")


class Recovery(Spec):
    """Ask the operator what to do with a failed step instead of abandoning its experiment: when the step's
    automatic retries are spent, or at once for a fault in ``faults``. The answer is one of ``options``
    (`twin ctl answer`); ``default`` applies after ``timeout_s`` lab seconds without one."""

    step: str | None = Field(default=None, description="the step type it covers (default: every step)")
    device: str | None = Field(default=None, description="the device type it covers (default: every type)")
    faults: list[Literal["failed", "timed_out", "device_lost", "driver_error"]] = Field(
        default_factory=list, description="faults that ask at once, before any automatic retry")
    options: list[RecoveryOption] = Field(default_factory=_every_option, min_length=1,
                                          description="retry (fresh attempts), another_device (fresh attempts, "
                                          "never on the devices that failed it; offered only where the type has "
                                          "another instance), skip (the step: the experiment goes on without its "
                                          "outputs), alternative (abandon the experiment and have the planner "
                                          "propose one in its place, beyond the budget), abandon (the "
                                          "experiment)")
    default: RecoveryOption = Field(default="abandon", description="what happens when nobody answers in time")
    timeout_s: float = Field(default=3600, gt=0, le=MAX_S, description="lab seconds to wait for an answer")
    simulate: SimulatedOperator | None = Field(default=None, description="virtual time: a simulated operator's "
                                               "delay and answer")

    @model_validator(mode="after")
    def _answerable(self) -> Recovery:
        if len(set(self.options)) != len(self.options):
            raise ValueError(f"options {self.options}: each at most once")
        if self.default not in self.options:
            raise ValueError(f"default {self.default!r} is not one of the options {self.options}")
        if self.simulate is not None and self.simulate.answer not in self.options:
            raise ValueError(f"simulate.answer {self.simulate.answer!r} is not one of the options {self.options}")
        return self


class Usage(Spec):
    """How much of an item one step uses: ``fixed`` plus, for each experiment parameter in ``per``, that much per
    unit of the parameter (never below 0)."""

    fixed: float = Field(default=0.0, ge=0, le=MAX_VALUE, description="used by every step")
    per: dict[Label, float] = Field(default_factory=dict, max_length=64, description="a parameter of the "
                                    "chemistry, or one a workflow step gives -> used per unit of it (below 0 only "
                                    "where fixed covers it)")


def usage_problems(item: str, stock: Consumable, ranges: dict[str, tuple[float, float]] | None) -> list[str]:
    """What is wrong with the amounts ``stock`` takes per parameter: a parameter no chemistry of the file has (its
    amount would never be taken), or amounts that make a step use less than nothing somewhere in the parameters'
    ranges. ``ranges``: each parameter's lowest low and highest high over the file's chemistries; None when the
    campaigns come later (`twin lab serve`), and nothing can be checked yet."""
    if ranges is None:
        return []
    problems, known = [], ", ".join(sorted(ranges)) or "it has none"
    for step, use in stock.used_by.items():
        if not isinstance(use, Usage):
            continue
        field = f"consumables.{item}.used_by.{step}"
        unknown = [p for p in use.per if p not in ranges]
        problems += [f"{field}.per.{p}: {p!r} is no parameter of the chemistry nor of a workflow step ({known}), so "
                     f"this amount would never be taken" for p in unknown]
        ends = {p: (ranges[p][0] if coef > 0 else ranges[p][1]) for p, coef in use.per.items() if p not in unknown}
        least = use.fixed + sum(use.per[p] * v for p, v in ends.items())
        if least < 0:
            at = ", ".join(f"{p} = {v:g}" for p, v in ends.items())
            problems.append(f"{field}: at {at} a step would use {least:g} {stock.unit} (fixed {use.fixed:g} plus "
                            f"per unit of each), less than nothing; raise fixed to at least {use.fixed - least:g}, "
                            f"or correct the sign of an amount in per")
    return problems


class SimulatedRefill(Spec):
    """Virtual time: the operator refills the item (to its starting level) this long after it runs short."""

    after_s: float = Field(ge=0, le=MAX_S, description="lab seconds after the item runs short")


class Consumable(Spec):
    unit: str = Field(default="units", max_length=32, description="what the levels count: mL, g, vials, tips, ...")
    level: float = Field(gt=0, le=MAX_VALUE, description="the starting level (a refill without an amount fills to it)")
    reorder_at: float = Field(default=0.0, ge=0, le=MAX_VALUE, description="below this, a consumable.low note says "
                              "when it will run out at the rate so far")
    used_by: dict[Label, float | Usage] = Field(min_length=1, max_length=64, description="step type -> what one step "
                                                "uses: an amount, or {fixed, per: {parameter: amount per unit}}")
    simulate_refill: SimulatedRefill | None = Field(default=None, description="virtual time: a simulated operator's "
                                                    "refill")
    device: Name | None = Field(default=None, description="a device type whose every instance holds its own stock "
                                "of the item (its own level, refills and notes, as 'ITEM@INSTANCE'); none: one "
                                "stock for the whole lab")


class Orchestration(Spec):
    timeout_factor: float = Field(default=2.0, ge=1, le=1000, description="an attempt's deadline is this times the "
                                  "step's expected lab seconds (set-up and clean-up included), plus timeout_slack_s")
    timeout_slack_s: float = Field(default=300, ge=0, le=MAX_S, description="lab seconds added to every deadline")
    retry: Retry = Field(default=Retry(), description="how a failed step is tried again")
    quarantine_after: int = Field(default=3, ge=1, le=1000, description="consecutive failures")
    probe_after_s: float = Field(default=3600, ge=0, le=MAX_S, description="lab seconds a quarantined device rests "
                                 "before it is given work again (its next failure quarantines it again)")
    startup_s: float = Field(default=60, ge=0, le=MAX_S, description="lab seconds to wait for devices")
    orphan_grace_s: float = Field(default=300, ge=0, le=MAX_S, description="lab seconds a device goes on with a "
                                  "step after the orchestrator has left the bus, before it stops it in a safe state")
    cancel_grace_s: float = Field(default=60, ge=0, le=MAX_S, description="lab seconds a timed-out device has to "
                                  "answer the cancel before it is given work again")
    recovery: list[Recovery] = Field(default_factory=list, max_length=64, description="failed steps to ask an "
                                     "operator about (the first rule that covers a step applies)")
    lab_scheduler: str | None = Field(default=None, max_length=4096, description="a lab of several campaigns: one "
                                      "scheduler (a rule, or rl:POLICY) choosing among every campaign's ready steps "
                                      "at once, priorities first (virtual time); none: each campaign's own "
                                      "scheduler, the campaigns in turns")
