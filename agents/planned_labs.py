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

from twin import Scenario, SteppedCampaign, SteppedLab, campaign_scenarios, load_plugin, prepare

#: planners that cost next to nothing: run as they are
CHEAP = frozenset({"fixed", "random", "lhs"})
_KEPT = 256  # labs held per process (one per lab and seed drawn)
_PLANNED: OrderedDict[str, Scenario] = OrderedDict()


def planned(lab: Scenario) -> Scenario:
    """``lab`` (prepared with its seed) with its planner's proposals recorded once and replayed; in a lab of several
    campaigns, each campaign's whose planner is costly. As it is if no planner is costly, or it is a job shop (its
    jobs are fixed already). The lab made is kept: every later run of the same lab costs a hash."""
    if lab.jobshop is not None or (not lab.campaigns and lab.campaign.planner in CHEAP):
        return lab  # the common case, and a lab already replayed: no hash
    key = hashlib.sha256(lab.model_dump_json().encode()).hexdigest()
    made = _PLANNED.get(key)
    if made is None:
        made = _PLANNED[key] = _replayed(lab)
        if len(_PLANNED) > _KEPT:
            _PLANNED.popitem(last=False)
    else:
        _PLANNED.move_to_end(key)
    return made


def _replayed(lab: Scenario) -> Scenario:
    runs = campaign_scenarios(lab) if lab.campaigns else {"": lab}
    costly = [name for name, s in runs.items() if s.campaign.planner not in CHEAP]
    if not costly:
        return lab
    recorded = record(lab)
    over: dict[str, Any] = {}
    for i, name in enumerate(runs):
        if name not in costly or not recorded.get(name):  # a planner that proposed nothing: nothing to replay
            continue
        fixed = {"planner": "fixed", "planner_options": {"proposals": recorded[name]}}
        if not lab.campaigns:
            over.update({f"campaign.{k}": v for k, v in fixed.items()})
        else:  # the campaign's whole section, as it runs (its seed included): a section of its own replaces the lab's
            over[f"campaigns.{i}.campaign"] = {**runs[name].campaign.model_dump(exclude_none=True), **fixed}
    return prepare(lab, overrides=over) if over else lab


def record(lab: Scenario) -> dict[str, list[dict[str, Any]]]:
    """What ``lab``'s planners propose in one run of it (each campaign's own scheduler as written, or FIFO where
    that is no plain rule): by campaign ('' for a lab of one), each experiment's parameters, and its route when the
    planner gave one (a route planner's)."""
    from agents.schedulers import RULES

    if lab.campaigns:
        shared = SteppedLab(lab, one_scheduler=False)  # each campaign's own scheduler: runs to its end at once
        try:
            return {name: _proposed(core.experiments, s) for (name, core), s
                    in zip(shared.cores.items(), campaign_scenarios(lab).values())}
        finally:
            shared.close()
    rule = lab.campaign.scheduler if lab.campaign.scheduler in RULES else "fifo"
    decide = load_plugin("schedulers", rule)().decide
    c = SteppedCampaign(lab)
    try:
        while not c.done:
            c.answer(decide(c.view))
        return {"": _proposed(c.core.experiments, lab)}
    finally:
        c.close()


def _proposed(experiments: list[Any], s: Scenario) -> list[dict[str, Any]]:
    workflow = tuple((w.step, w.device, dict(w.params)) for w in s.workflow)
    out = []
    for e in experiments:
        route = tuple((r.step, r.device, dict(r.params)) for r in e.route)
        out.append({"params": dict(e.params)} if route == workflow else
                   {"params": dict(e.params), "route": [{"step": st, "device": d, "params": p} for st, d, p in route]})
    return out
