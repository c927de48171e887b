"""The lab's objective as a scenario weighs it (``training.weights``): what schedulers are trained on and judged by.

Lab time counts in the scenario's typical step (``time_scale``), so a lab of hours and a job shop of seconds
weigh a degraded sample or an abandoned experiment alike: ``time`` × lab time ÷ the typical step +
``degraded`` × samples that waited past their stability + ``abandoned`` × experiments given up.
"""

from __future__ import annotations

import statistics

from twin.scenario.model import Scenario, expected_duration
from twin.scenario.sharing import campaign_scenarios


def time_scale(s: Scenario) -> float:
    """The scenario's typical step duration (lab seconds): the unit of every time feature (a lab of several
    campaigns: the mean of theirs; a lab with no steps yet: 1)."""
    return typical_step(s) or 1.0


def typical_step(s: Scenario) -> float | None:
    """The mean expected duration of the scenario's steps (lab seconds), or None for a lab that has none yet (a
    lab file served for campaigns to come)."""
    if s.campaigns:
        return statistics.mean(time_scale(c) for c in campaign_scenarios(s, s.name).values())
    durations = []
    for p in s.campaign.planner_options.get("proposals", []):  # fixed routes (a job shop's): each step on its device
        for step in p.get("route") or []:
            d = s.devices.get(step.get("device"))
            try:
                durations.append(expected_duration(d.duration, {**p.get("params", {}), **step.get("params", {})},
                                                   d.setup_s, d.clean_s))
            except (AttributeError, TypeError, ValueError):  # a step the planner's checks refuse, by name
                continue
    if not durations:
        mid = {k: (p.low + p.high) / 2 for k, p in s.chemistry.parameters.items()}
        for w in s.workflow:
            d = s.devices[w.device]
            durations.append(expected_duration(d.duration, {**mid, **w.params}, d.setup_s, d.clean_s))
    return max(statistics.mean(durations), 1e-6) if durations else None


def weighted_objective(s: Scenario, lab_s: float, degraded: float, abandoned: float, unit_s: float | None = None) -> float:
    """One campaign's objective: ``lab_s`` lab seconds, ``degraded`` samples, ``abandoned`` experiments."""
    w = s.training.weights
    return (w.time * lab_s / (unit_s or time_scale(s)) + w.degraded * degraded + w.abandoned * abandoned)
