"""A scenario's ``training`` section: what a scheduler is trained to minimise and the labs it is trained on."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from twin.scenario.spec import IntRange, Range, Spec


class RewardWeights(Spec):
    """What a scheduler is trained to minimise, per episode: weighted lab time, degraded samples, abandoned
    experiments (a policy that trades one for another says so in its training curve and the bench)."""

    time: float = Field(default=1.0, ge=0, le=1000, description="per typical step duration of lab time")
    degraded: float = Field(default=0.5, ge=0, le=1000, description="per sample that waited past its stability")
    abandoned: float = Field(default=2.0, ge=0, le=1000, description="per experiment abandoned")


class RandomLabs(Spec):
    """Whole labs drawn at random for training a scheduler (``twin.scenario.random_labs``): each has its own device types,
    instance counts and workflow, its devices copied from this scenario's (durations, faults) and scaled."""

    share: float = Field(default=0.5, ge=0, le=1, description="the fraction of training labs drawn this way; "
                         "the rest come from the scenario's own devices and the ranges above")
    device_types: IntRange = Field(default=(2, 5), description="[min, max] device types in a lab")
    instances: IntRange = Field(default=(1, 6), description="[min, max] instances of each type")
    duration_scale: Range = Field(default=(0.5, 2.0), description="multiplies each type's mean duration, so "
                                  "bottlenecks move from type to type")
    revisit_p: float = Field(default=0.3, ge=0, le=1, description="probability that the workflow visits one type "
                             "a second time (re-entrant: measure before and after)")

    @model_validator(mode="after")
    def _ordered(self) -> RandomLabs:
        (a, b), (c, d), (e, f) = self.device_types, self.instances, self.duration_scale
        bad = [f"{k}: [{lo}, {hi}] must be low ≤ high, both > 0" for k, (lo, hi) in
               {"device_types": (a, b), "instances": (c, d), "duration_scale": (e, f)}.items() if not 0 < lo <= hi]
        if b > 16 or d > 64:
            bad.append("at most 16 device types and 64 instances of each")
        if bad:
            raise ValueError("random_labs: " + "; ".join(bad))
        return self


class Training(Spec):
    """Domain randomisation for training a scheduler: each episode draws a lab from these ranges."""

    weights: RewardWeights = Field(default=RewardWeights(), description="what the scheduler is trained to "
                                   "minimise: lab time, degraded samples, abandoned experiments")
    method: Literal["ppo", "imitate"] = Field(
        default="imitate", description="how `twin train --agent scheduler` learns: imitate (DAgger from a teacher; "
        "it matches the teacher within minutes) or ppo (from the reward alone, any lab of one campaign; it needs "
        "far more steps to catch up with the rules)")
    teacher: Literal["auto", "cp-sat", "best-rule", "self", "self-pg"] = Field(
        default="auto", description="method imitate: cp-sat (its schedules of random shops; job shops with "
        "jobshop_sizes), best-rule (in each lab drawn from these ranges, the dispatching rule that does best there), "
        "self (the policy's own best of `samples` rollouts of each lab) or self-pg (a policy gradient: every one of "
        "`samples` sampled rollouts of each lab reinforced by how much better than their mean it ended); self and "
        "self-pg start from a policy (--init); auto: cp-sat for a job shop with jobshop_sizes; for a lab of the shapes "
        "the shipped general policy (agents/policies/flaky_scheduler.zip) was trained on, self from it, unless it "
        "does worse than the best rule at the start; else self for a lab of several campaigns (with --init), and "
        "best-rule for any other lab")
    samples: int = Field(default=16, ge=2, le=256, description="teacher self: rollouts of each lab (one greedy, the "
                         "rest sampled), the best of which is imitated; self-pg: sampled rollouts of each lab")
    teacher_seeds: int = Field(default=1, ge=1, le=16, description="teacher best-rule: each lab drawn is run this "
                               "many times by every rule, its faults drawn anew each time, and the rules compared on "
                               "the mean")
    teacher_margin: float = Field(default=0.0, ge=0, le=1, description="teacher best-rule: another rule teaches a "
                                  "lab only where it beats the scenario's best rule as written by more than this share "
                                  "of the objective (0.02: 2 %), so that rules a seed's noise apart do not take turns "
                                  "teaching labs alike")
    teacher_default: str | None = Field(default=None, description="teacher best-rule with teacher_margin: the rule "
                                        "that teaches unless another beats it by the margin; by default the best rule "
                                        "on the scenario as written (the one training is judged against)")

    duration_scale: Range = Field(default=(1.0, 1.0), description="multiplies every mean duration")
    fault_scale: Range = Field(default=(1.0, 1.0), description="multiplies fail/hang probabilities and crash rates")
    type_scale: Range = Field(default=(1.0, 1.0), description="each device type's durations and faults are also "
                              "multiplied by draws of their own from this range: one stage slower or flakier than "
                              "the rest (a bottleneck, a flaky stage)")
    stability_scale: Range = Field(default=(1.0, 1.0), description="multiplies how long samples keep "
                                   "(chemistry.stability_s)")
    bottleneck_share: float = Field(default=0.0, ge=0, le=1, description="the share of the scenario's own labs drawn "
                                    "in which one device type of the workflow, at random, is made the bottleneck: its "
                                    "steps made long enough that it takes a quarter more lab time per experiment than "
                                    "any other, and up to half as long again (as `twin bench schedulers --shapes` "
                                    "makes its bottleneck shapes)")
    instances: dict[str, IntRange] = Field(default_factory=dict, description="device type -> [min, max] instances")
    operation_s: Range | None = Field(
        default=None, description="job shops: draw every operation's duration from [low, high] lab-s")
    shuffle_routes: bool = Field(default=False, description="job shops: draw each job's machine order afresh")
    jobshop_sizes: list[IntRange] = Field(
        default_factory=list, description="job shops: draw a random instance of one of these [jobs, machines] sizes")
    random_labs: RandomLabs | None = Field(
        default=None, description="also train on whole labs drawn at random (other device types, counts and "
        "workflows), so the policy is not tied to this lab's shape")

    @model_validator(mode="after")
    def _ordered(self) -> Training:
        ranges = {"duration_scale": self.duration_scale, "fault_scale": self.fault_scale,
                  "type_scale": self.type_scale, "stability_scale": self.stability_scale,
                  **({"operation_s": self.operation_s} if self.operation_s else {}),
                  **{f"instances.{k}": v for k, v in self.instances.items()}}
        bad = [f"{k}: [{lo}, {hi}] must be low ≤ high, both > 0" for k, (lo, hi) in ranges.items() if not 0 < lo <= hi]
        if bad:
            raise ValueError("; ".join(bad))
        return self
