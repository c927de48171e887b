"""What a scheduler in training is judged by: whole campaigns of a lab scheduled by a ``decide`` and their
objective, the dispatching rules on the same labs, held-out labs drawn from its ``training`` ranges, and CP-SAT's
reference for the curve (``agents.train_scheduler.Judge`` keeps the best policy by them)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any

from agents.lab_scheduling import lab_objective
from agents.planned_labs import planned
from agents.scheduling_env import randomised
from agents.schedulers import rules_for
from twin import Assignment, LabSummary, LabView, Scenario, SteppedCampaign, SteppedLab, load_plugin, prepare
from twin import time_scale, weighted_objective

EVAL_SEEDS = tuple(range(100_000, 100_005))
HELD_OUT_SEED = -1_000_000  # reset() draws seeds in [0, 2**31): negative ones are never trained on
TURNS = "turns"  # a lab of several campaigns without one scheduler: each campaign's own, in turns


def campaign(scenario: Scenario, seed: int, decide: Callable[[LabView], list[Assignment]] | None) -> Any:
    """One whole campaign, scheduled by ``decide``; its summary. A lab of several campaigns: every campaign,
    ``decide`` the lab's one scheduler (None: each campaign's own, in turns); a ``LabSummary``."""
    lab = planned(prepare(scenario, seed=seed))
    c: Any = SteppedLab(lab, one_scheduler=decide is not None) if lab.campaigns else SteppedCampaign(lab)
    try:
        while not c.done:
            assert decide is not None
            c.answer(decide(c.view))
        return c.summary
    finally:
        c.close()


def objective(summary: Any, scenario: Scenario) -> float:
    """What the environment's reward sums to (negated): lab time in typical steps, degraded samples and
    abandoned experiments, weighted by ``training.weights``; a lab of several campaigns, their weighted mean
    (``agents.lab_scheduling.lab_objective``)."""
    if isinstance(summary, LabSummary):
        return lab_objective(summary, scenario, time_scale(scenario))
    return weighted_objective(scenario, summary.lab_hours * 3600, summary.degraded_samples, summary.abandoned)


def count(summary: Any, what: str) -> int:
    """``what`` (degraded_samples, abandoned) of a campaign's summary, or summed over a lab's campaigns."""
    if isinstance(summary, LabSummary):
        return sum(getattr(c, what) for c in summary.campaigns.values())
    return getattr(summary, what)


def score(summaries: list[Any], scenario: Scenario | None = None) -> dict[str, float]:
    out = {"makespan h": statistics.mean(s.lab_hours for s in summaries),
           "degraded": statistics.mean(count(s, "degraded_samples") for s in summaries),
           "abandoned": statistics.mean(count(s, "abandoned") for s in summaries)}
    if scenario is not None:
        out["objective"] = statistics.mean(objective(s, scenario) for s in summaries)
    return out


def baselines(scenario: Scenario) -> dict[str, Callable[[LabView], list[Assignment]] | None]:
    """What a policy is judged against: every dispatching rule (in a lab of several campaigns, as its one
    scheduler, with ``fair-share``), and there also the campaigns' own schedulers in turns."""
    out: dict[str, Any] = {rule: load_plugin("schedulers", rule)().decide for rule in rules_for(scenario)}
    if scenario.campaigns:
        out[TURNS] = None
    return out


def evaluate_rules(scenario: Scenario, seeds=EVAL_SEEDS) -> dict[str, dict[str, float]]:
    return {rule: score([campaign(scenario, seed, decide) for seed in seeds], scenario)
            for rule, decide in baselines(scenario).items()}


def held_out_labs(scenario: Scenario, n: int) -> list[Scenario]:
    """Labs drawn from the scenario's ``training`` ranges with seeds the training draws never use (a lab of
    several campaigns: always, its campaigns' priorities and shares drawn)."""
    t = scenario.training
    varied = any(r != (1.0, 1.0) for r in (t.duration_scale, t.fault_scale, t.type_scale, t.stability_scale))
    if not (t.jobshop_sizes or t.instances or t.operation_s or t.random_labs or varied or scenario.campaigns):
        return []
    return [prepare(randomised(scenario, HELD_OUT_SEED + i), seed=0) for i in range(n)]


def solver_reference(scenario: Scenario, seeds, held_out: list[Scenario]) -> dict[str, Any]:
    """What CP-SAT does on the labs a policy is judged on, for the curve (the score stays rule-relative): a job
    shop's plan (lab-h, the scenario and each held-out shop; CP-SAT's offline solve, 1 s each), or, in a lab whose
    work is not all known, the online ``cp-sat`` scheduler's objective on the scenario as written with the first of
    ``seeds`` (up to 0.2 s a decision: one campaign of a 40-experiment lab took a minute, five of them five
    minutes before training began), compared with the policy's run of that seed."""
    from agents.cpsat_scheduler import CpSatScheduler

    if scenario.campaigns:
        return {}  # CP-SAT schedules one campaign's steps
    if scenario.jobshop is not None:
        return {"plans": [CpSatScheduler.offline_bound(lab, 1.0) / 3600 for lab in [scenario, *held_out]]}
    online = CpSatScheduler(scenario, time_limit_s=ONLINE_DECISION_S)
    started = time.perf_counter()

    def decide(view: LabView) -> list[Assignment]:
        if time.perf_counter() - started > REFERENCE_MAX_S:
            raise _OutOfTime
        return online.decide(view)

    try:
        return {"online": objective(campaign(scenario, seeds[0], decide), scenario)}
    except _OutOfTime:  # minutes of CP-SAT for a number on the curve (a wide lab's took five): the rules suffice
        return {"online_out_of_time": REFERENCE_MAX_S}


#: The online CP-SAT reference: its time limit a decision, and the wall seconds its whole campaign is given
ONLINE_DECISION_S, REFERENCE_MAX_S = 0.2, 90.0


class _OutOfTime(Exception):
    """The online CP-SAT reference's campaign took longer than ``REFERENCE_MAX_S``."""


def reference_note(scenario: Scenario, held_out: list[Scenario]) -> str | None:
    """What ``solver_reference`` is about to do, for a user watching a training start (None: nothing)."""
    if scenario.campaigns:
        return None
    if scenario.jobshop is not None:
        return f"the reference: CP-SAT plans the shop and {len(held_out)} held-out ones (1 s each) …"
    return (f"the reference: CP-SAT schedules the lab as written once, online (up to {ONLINE_DECISION_S:g} s for "
            f"each of about {scenario.campaign.budget * len(scenario.workflow)} decisions, {REFERENCE_MAX_S:.0f} s "
            "at most) …")


def reference_outcome(solver: dict) -> str | None:
    """What became of an online reference that ran out of time (None: it did not)."""
    if "online_out_of_time" not in solver:
        return None
    return (f"the reference: none — CP-SAT online did not finish the lab in {solver['online_out_of_time']:.0f} s; "
            "the rules are the reference (compare it after: twin bench schedulers SCENARIO --schedulers "
            "mwkr,cp-sat,rl:POLICY)")
