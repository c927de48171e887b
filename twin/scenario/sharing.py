"""A lab that serves several campaigns: each campaign's scenario is the lab file with the campaign's sections.

The lab file gives the devices, consumables, clock, bus and orchestrator; a campaign (``campaigns:`` in the lab
file, or a campaign file given to ``twin submit``) gives its own chemistry, workflow and campaign section, and
takes the lab's for any it leaves out. A campaign that gives no seed of its own runs on the lab's seed plus its
place in the list, so two campaigns of the same chemistry do not propose the same experiments.
"""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

from twin.core.errors import ScenarioError
from twin.scenario.loading import parse, problems_of
from twin.scenario.model import Scenario, SharedCampaign

_OWN = ("chemistry", "workflow", "campaign")


def campaign_scenario(lab: Scenario, c: SharedCampaign, index: int, source: str = "<lab>",
                      named: str = "") -> Scenario:
    """The scenario campaign ``c`` (the ``index``-th of the lab) runs: the lab's, with ``c``'s own sections.
    Its problems name ``named`` (a campaign submitted later, which is no entry of the lab's file), else its place in
    ``source``."""
    data = lab.model_dump(exclude={"campaigns"})
    own = c.model_dump(include=set(_OWN), exclude_none=True)
    data.update(own)
    params = {*data["chemistry"]["parameters"], *(p for w in data["workflow"] for p in w.get("params", {}))}
    for item in data["consumables"].values():  # an amount per a parameter this campaign has not is never taken
        for use in item["used_by"].values():
            if isinstance(use, dict):
                use["per"] = {p: amount for p, amount in use["per"].items() if p in params}
    used = {w["device"] for w in data["workflow"]}
    for dtype, spec in data["devices"].items():
        if used and dtype not in used:  # never sent this campaign's steps: its chemistry need not fit them
            spec["duration"]["plus_param"] = None
            spec["envelope"] = {}
    seeded = c.campaign is not None and "seed" in c.campaign.model_fields_set
    data["campaign"]["seed"] = data["campaign"]["seed"] if seeded else (lab.campaign.seed + index) % 2**63
    return parse(data, named or f"{source}: campaigns.{index} ({c.name})")


def campaign_scenarios(lab: Scenario, source: str = "<lab>") -> dict[str, Scenario]:
    """Every campaign's scenario, by name; a ScenarioError names the campaign and the field."""
    return {c.name: campaign_scenario(lab, c, i, source) for i, c in enumerate(lab.campaigns)}


def parse_campaign(raw: Any, source: str = "<campaign>") -> SharedCampaign:
    if not isinstance(raw, dict):
        raise ScenarioError(source, ["a campaign file is a mapping: name, and any of owner, priority, share, "
                                     "chemistry, workflow, campaign"])
    try:
        return SharedCampaign.model_validate(raw)
    except ValidationError as exc:
        problems = problems_of(exc, raw, SharedCampaign)
        lab_only = sorted(k for k in ("lab", "devices", "bus", "clock", "orchestrator", "campaigns") if k in raw)
        if lab_only:  # a whole scenario (twin run's file) sent as a campaign: say so once, then the fields
            problems.insert(0, f"this is a lab's scenario ({', '.join(lab_only)}), not a campaign for a lab: a "
                               "campaign file keeps only name, and any of owner, priority, share, chemistry, "
                               "workflow, campaign (the lab has the devices); copy those into a file of their own")
        raise ScenarioError(source, problems) from None
