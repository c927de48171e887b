"""The RL scheduler of a lab of several campaigns (``orchestrator.lab_scheduler: rl:POLICY``): what it reads its
labs with, what it is trained to lower, and the labs it is trained on.

- It reads a question of the lab with the lab file (``agents.candidates``): the campaigns' mean typical step as
  its unit of time, each campaign's sample stability for its own steps, every campaign's step types in the fit
  check.
- Its objective is the campaigns' objectives (as ``agents.train_scheduler.objective`` weighs one: each campaign's
  lab time from its start to its end, degraded samples and abandoned experiments), averaged with **weights**: a
  campaign's ``share``, doubled for each lower priority among the lab's campaigns — so a top-priority campaign
  finished an hour later costs its lab more than a low-priority one.
- It trains on **variants** of the lab: the ``training`` ranges applied to its devices, and each campaign's
  priority (0 or 1) and share (½–2) drawn afresh, so what the campaign columns say varies as it will in labs the
  policy has not seen.
"""

from __future__ import annotations

import random
from typing import Any

from twin import LabSummary, Scenario, weighted_objective


def weights(lab: Scenario) -> dict[str, float]:
    """Each campaign's weight in its lab's objective: its share × 2 per lower priority among the campaigns."""
    below = {c.name: len({d.priority for d in lab.campaigns if d.priority < c.priority}) for c in lab.campaigns}
    return {c.name: c.share * 2.0 ** below[c.name] for c in lab.campaigns}


def lab_objective(summary: LabSummary, lab: Scenario, unit_s: float) -> float:
    """The weighted mean over the campaigns that ran of their objectives, as ``agents.train_scheduler.objective``
    weighs one campaign (``training.weights`` of the lab file; lab time from each campaign's start to its end in
    units of ``unit_s``, the lab's typical step)."""
    w = weights(lab)
    ran = [n for n in summary.campaigns if n in w]
    if not ran:
        return 0.0
    total = sum(w[n] * weighted_objective(lab, c.lab_hours * 3600, c.degraded_samples, c.abandoned, unit_s)
                for n, c in ((n, summary.campaigns[n]) for n in ran))
    return total / sum(w[n] for n in ran)


def variant(lab: Scenario, over: dict[str, Any], rng: random.Random) -> dict[str, Any]:
    """``over`` (the devices' training draws) with each campaign's priority and share drawn too."""
    out = dict(over)
    for i, _ in enumerate(lab.campaigns):
        out[f"campaigns.{i}.priority"] = rng.choice((0, 0, 1))
        out[f"campaigns.{i}.share"] = round(2.0 ** rng.uniform(-1.0, 1.0), 3)
    return out

