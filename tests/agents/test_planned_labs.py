"""A training lab's planner run once and replayed: GP-BO's fits were ~80 % of teaching a scheduler on a GP-BO lab
(20,000 steps of a lab of mine took over 10 minutes, the README says ~40 s)."""

from tests.conftest import qd_lab
from agents import planned_labs
from agents.planned_labs import planned, record
from agents.judging import campaign
from twin import SteppedCampaign, load_plugin, prepare


def gp_lab(**changes):
    return prepare(qd_lab(**{"campaign.planner": "gp-bo", "campaign.planner_options": {"n_init": 3},
                             "campaign.budget": 10, "campaign.scheduler": "spt", **changes}), seed=4)


def experiments(lab, rule):
    c = SteppedCampaign(lab)
    decide = load_plugin("schedulers", rule)().decide
    while not c.done:
        c.answer(decide(c.view))
    return [e.params for e in c.core.experiments], c.summary


def test_the_lab_replays_what_its_planner_proposed_under_its_own_scheduler():
    lab = gp_lab()
    live, summary = experiments(lab, "spt")
    replay = planned(lab)
    assert replay.campaign.planner == "fixed" and lab.campaign.planner == "gp-bo"
    assert [p["params"] for p in replay.campaign.planner_options["proposals"]] == live
    again, replayed = experiments(replay, "spt")  # the same experiments, and the same campaign
    assert again == live and replayed.lab_hours == summary.lab_hours and replayed.done == summary.done
    other, _ = experiments(replay, "mwkr")  # another rule: the same experiments, whatever order results come in
    assert other == live


def test_a_lab_is_recorded_once_per_seed_and_a_cheap_planners_lab_runs_as_it_is(monkeypatch):
    calls = []
    monkeypatch.setattr(planned_labs, "record", lambda lab: calls.append(lab) or record(lab))
    monkeypatch.setattr(planned_labs, "_PLANNED", type(planned_labs._PLANNED)())
    lab = gp_lab(**{"campaign.budget": 6})
    for _ in range(3):
        campaign(lab, 4, load_plugin("schedulers", "fifo")().decide)  # the trainer's campaigns of one lab and seed
    assert len(calls) == 1
    campaign(lab, 5, load_plugin("schedulers", "fifo")().decide)  # another seed is another lab
    assert len(calls) == 2
    cheap = prepare(qd_lab(**{"campaign.planner": "random"}))
    assert planned(cheap) is cheap and len(calls) == 2


def test_in_a_lab_of_several_campaigns_each_campaigns_planner_is_replayed_its_own_settings_kept():
    from tests.twin.shared_labs import LAB
    from twin import SteppedLab, campaign_scenarios

    lab = prepare(LAB, seed=2, overrides={"campaigns.0.campaign.budget": 5, "campaigns.1.campaign.budget": 4})
    live = SteppedLab(lab, one_scheduler=False)  # each campaign's own scheduler, as the recording runs it
    proposed = {name: [e.params for e in core.experiments] for name, core in live.cores.items()}
    live.close()
    written, replayed = campaign_scenarios(lab), campaign_scenarios(planned(lab))
    for name, s in replayed.items():
        assert s.campaign.planner == "fixed" and written[name].campaign.planner == "gp-bo"
        assert [p["params"] for p in s.campaign.planner_options["proposals"]] == proposed[name]
        assert s.campaign.model_dump(exclude={"planner", "planner_options"}) == \
            written[name].campaign.model_dump(exclude={"planner", "planner_options"})  # seed, budget, scheduler kept
    again = SteppedLab(planned(lab), one_scheduler=False)
    assert {name: [e.params for e in core.experiments] for name, core in again.cores.items()} == proposed
    assert again.summary.lab_hours == live.summary.lab_hours
    again.close()
