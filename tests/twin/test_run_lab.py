"""A lab of several campaigns from Python: `twin.run` of one failed deep in the drivers ("chemistry.model: none
given"), the lab's own sections being only the campaigns' defaults; `twin.run_lab` runs it as `twin run` does."""

import pytest

import twin
from tests.twin.shared_labs import LAB, assert_accounted

SMALL = {"campaigns.0.campaign.budget": 4, "campaigns.1.campaign.budget": 3}


def test_run_names_run_lab_for_a_lab_of_several_campaigns_and_run_lab_runs_it(tmp_path):
    with pytest.raises(twin.TwinError, match=r"a lab of 2 campaigns \(dots, catalyst\): twin.run runs one campaign; "
                                             r"twin.run_lab runs the lab"):
        twin.run(LAB, journal=tmp_path / "j.db", overrides=SMALL)
    assert not (tmp_path / "j.db").exists()
    out = twin.run_lab(LAB, journals=tmp_path / "lab", seed=3, overrides={**SMALL, "campaign.planner": "random"})
    assert_accounted(out)
    assert {n: c.done + c.abandoned for n, c in out.campaigns.items()} == {"dots": 4, "catalyst": 3}
    assert sorted(p.name for p in (tmp_path / "lab").glob("*.db")) == ["catalyst.db", "dots.db"]
    with pytest.raises(twin.TwinError, match="no campaigns: list"):
        twin.run_lab(twin.campaign_scenarios(twin.prepare(LAB))["dots"], journals=tmp_path / "one")


def test_a_policy_given_to_each_campaign_of_a_lab_is_refused_naming_the_lab_scheduler(tmp_path):
    policy = "rl:agents/policies/flaky_scheduler.zip"
    with pytest.raises(twin.ClockError, match=r"their scheduler \(rl:agents/policies/flaky_scheduler.zip\) is an "
                                              r"agent on the bus.*--set orchestrator.lab_scheduler=rl:agents/policies"):
        twin.run_lab(LAB, journals=tmp_path / "lab", overrides={**SMALL, "campaign.scheduler": policy})
