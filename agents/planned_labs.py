"""A training lab whose planner's proposals are made once and replayed, so that a slow planner is not run again for
every rule, rollout and evaluation of the same lab.

Teaching a scheduler runs each drawn lab many times over (each rule to find the teacher, then the rollouts), and
the evaluations run the same seeds at every check. With GP-BO planning, its fits were ~80 % of the time: a lab of
yours with GP-BO trained at ~30 steps/s where one with a random planner trains at hundreds. So the first run of a
lab (its scheduler as written, or FIFO if that is no plain rule) records the experiments its planner proposed, and
every run of that lab proposes the same ones, in the same order (the ``fixed`` planner); a target is met by the
same experiment, so a campaign that stops on its target still stops. What is lost is the planner answering the
order results came in, which is the planner's part, not the scheduler's.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import Any

from twin import Scenario, SteppedCampaign, load_plugin, prepare

#: planners that cost next to nothing: run as they are
CHEAP = frozenset({"fixed", "random", "lhs"})
_KEPT = 512  # recordings held per process (one per lab and seed drawn; a few KB each)
_RECORDED: OrderedDict[str, list[dict[str, Any]]] = OrderedDict()


def planned(lab: Scenario) -> Scenario:
    """``lab`` (prepared with its seed) with its planner's proposals recorded once and replayed; as it is if its
    planner is cheap, or it is a job shop (its jobs are fixed already) or a lab of several campaigns."""
    if lab.campaigns or lab.jobshop is not None or lab.campaign.planner in CHEAP:
        return lab
    key = hashlib.sha256(lab.model_dump_json().encode()).hexdigest()
    proposals = _RECORDED.get(key)
    if proposals is None:
        proposals = _RECORDED[key] = record(lab)
        if len(_RECORDED) > _KEPT:
            _RECORDED.popitem(last=False)
    else:
        _RECORDED.move_to_end(key)
    if not proposals:  # the planner proposed nothing: nothing to replay
        return lab
    return prepare(lab, overrides={"campaign.planner": "fixed", "campaign.planner_options": {"proposals": proposals}})


def record(lab: Scenario) -> list[dict[str, Any]]:
    """What ``lab``'s planner proposes in one campaign of it: each experiment's parameters, and its route when the
    planner gave one (a route planner's)."""
    from agents.schedulers import RULES

    rule = lab.campaign.scheduler if lab.campaign.scheduler in RULES else "fifo"
    decide = load_plugin("schedulers", rule)().decide
    c = SteppedCampaign(lab)
    try:
        while not c.done:
            c.answer(decide(c.view))
        workflow = tuple((w.step, w.device, dict(w.params)) for w in lab.workflow)
        out = []
        for e in c.core.experiments:
            route = tuple((s.step, s.device, dict(s.params)) for s in e.route)
            out.append({"params": dict(e.params)} if route == workflow else
                       {"params": dict(e.params), "route": [{"step": s, "device": d, "params": p} for s, d, p in route]})
        return out
    finally:
        c.close()
