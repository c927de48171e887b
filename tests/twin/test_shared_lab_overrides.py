"""The lab-wide `campaign.*` of a lab of several campaigns, as the command line sets it: each campaign with a
`campaign:` of its own replaced the lab's wholesale, so `twin run LAB --scheduler mwkr`, `--set
campaign.max_in_flight=2` and `twin whatif LAB --planners random,gp-bo` changed nothing, and said nothing."""

import json

import pytest
import yaml

from tests.conftest import twin_cli
from tests.twin.shared_labs import LAB
from twin.core.errors import ScenarioError
from twin.runtime.lab import prepare
from twin.scenario.sharing import campaign_scenarios
from twin.tools.whatif import variants


def test_a_lab_wide_campaign_field_reaches_every_campaign_and_one_campaigns_own_still_wins():
    written = campaign_scenarios(prepare(LAB))
    assert {n: s.campaign.scheduler for n, s in written.items()} == {"dots": "oldest-sample", "catalyst": "fifo"}
    for lab in (prepare(LAB, overrides={"campaign.scheduler": "mwkr", "campaign.max_in_flight": 1,
                                        "campaigns.1.campaign.scheduler": "spt"}),
                prepare(prepare(LAB), overrides={"campaign.scheduler": "mwkr", "campaign.max_in_flight": 1,
                                                 "campaigns.1.campaign.scheduler": "spt"})):  # a Scenario, as whatif has
        runs = campaign_scenarios(lab)
        assert {n: s.campaign.scheduler for n, s in runs.items()} == {"dots": "mwkr", "catalyst": "spt"}
        assert all(s.campaign.max_in_flight == 1 for s in runs.values())
        # each campaign's own planner and budget are left as written
        assert [s.campaign.budget for s in runs.values()] == [s.campaign.budget for s in written.values()]
    seeded = campaign_scenarios(prepare(LAB, overrides={"campaign.seed": 5}))
    assert [s.campaign.seed for s in seeded.values()] == [5, 6]  # the lab's seed plus each campaign's place
    with pytest.raises(ScenarioError) as bad:  # a bad value is said once, not again for each campaign
        prepare(LAB, overrides={"campaign.max_in_flight": 0})
    assert bad.value.problems == ["campaign.max_in_flight: Input should be greater than or equal to 1 (got 0)"]


def test_whatif_of_a_lab_compares_what_its_campaigns_run_with(tmp_path):
    lab = prepare(LAB)
    # both campaigns run gp-bo (the lab's own campaign section says random, and nobody runs it): random is a variant
    assert [v.label for v in variants(lab, [], planners=["random", "gp-bo"])] == ["as written",
                                                                                 "campaign.planner=random"]
    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (6, 4)):
        c["campaign"]["budget"] = budget
    small = tmp_path / "lab.yaml"
    small.write_text(yaml.safe_dump(raw))
    res = twin_cli("whatif", small, "--planners", "random,gp-bo", "--seeds", "2", "--json")
    assert res.exit_code == 0, res.output
    rows = {r["variant"]: r for r in json.loads(res.stdout)["variants"]}
    assert list(rows) == ["as written", "campaign.planner=random"]
    assert rows["as written"]["per_campaign"] != rows["campaign.planner=random"]["per_campaign"]
    res = twin_cli("whatif", small, "--schedulers", "fifo", "--seeds", "1", columns=80)
    assert res.exit_code == 0 and "oldest-sample/fifo*" in res.output, res.output  # the two as written
    # a policy for each campaign, asked in the worker's process as for a lab of one (its run refused it: "an agent
    # on the bus serves one campaign", after the other variants had run)
    res = twin_cli("whatif", small, "--schedulers", "rl:agents/policies/flaky_scheduler.zip", "--seeds", "1",
                   "--json")
    assert res.exit_code == 0, res.output
    (rl,) = [r for r in json.loads(res.stdout)["variants"] if r["variant"] != "as written"]
    assert rl["variant"] == "campaign.scheduler=rl:agents/policies/flaky_scheduler.zip" and rl["per_campaign"]


def test_a_bench_of_a_lab_of_several_campaigns_says_what_to_run_instead():
    for what in (["planners"], ["schedulers"], ["schedulers", "--shapes"]):
        res = twin_cli("bench", *what, LAB, "--seeds", "1")
        assert res.exit_code != 0 and "a lab of 2 campaigns (dots, catalyst)" in res.output, res.output
        assert f"twin whatif {LAB} --{what[0]} A,B" in res.output.replace("\n", " ")
