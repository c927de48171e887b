"""The RL scheduler of a lab of several campaigns (issue [7 of 7]): it sees whose step each candidate is, a lab is
stepped one decision of its one scheduler at a time, and a policy of the earlier encoding still decides as it did."""

from pathlib import Path

import numpy as np
import pytest
import torch

from agents.candidates import FEATURES, MAX_CANDIDATES, WIDTHS, CandidateEncoder, trained_encoding
from agents.rl_scheduler import RlScheduler
from agents.train_scheduler import initial_state
from twin import load_plugin, prepare
from twin.campaign.decisions import CampaignState, DeviceState, FreeDevice, LabView, ReadyStep
from twin.learning.stepper import SteppedLab
from twin.runtime.shared_run import run_shared

ROOT = Path(__file__).resolve().parents[2]
LAB = ROOT / "scenarios" / "shared_lab.yaml"
SHIPPED = ROOT / "agents" / "policies" / "flaky_scheduler.zip"
EARLIER = ROOT / "tests" / "data" / "jobshop_scheduler_v2.zip"  # a policy of an earlier encoding, candidates-v2
torch.set_num_threads(1)
CONTENDED = {"campaigns.1.priority": 0, "devices.spectrometer.duration.mean_s": 1500,  # both queue at one device
             "campaigns.0.campaign.budget": 16, "campaigns.1.campaign.budget": 12}


def columns(view: LabView, lab) -> dict[str, tuple]:
    """The campaign columns of each candidate, by task."""
    enc = CandidateEncoder(lab)
    obs, _ = enc.encode(view)
    rows = obs[:MAX_CANDIDATES * FEATURES].reshape(MAX_CANDIDATES, FEATURES)
    return {r.task: tuple(float(x) for x in row[WIDTHS["candidates-v2"]:]) for (r, _), row in zip(enc.encoded, rows)}


def step(task, campaign, dtype="spectrometer", expected=100.0, then=()):
    return ReadyStep(task, 0, "measure", dtype, 0.0, None, expected, expected + sum(s for _, s in then),
                     then=then, campaign=campaign)


def test_each_candidate_says_whose_step_it_is():
    lab = prepare(LAB)
    view = LabView(
        50.0, (step("a/t1", "a"), step("a/t2", "a", then=(("reactor", 300.0),)), step("b/t1", "b", expected=200.0)),
        (FreeDevice("spectrometer", "spectrometer"),),
        (DeviceState("spectrometer", "spectrometer", True, True, None, 3, 0, 40.0),),
        finished=5, budget=100, campaigns=(CampaignState("a", 2, 0.25, 0.5, 4, 40), CampaignState("b", 0, 0.75, 0.5, 1, 60)))
    got = columns(view, lab)
    # a: top priority, has had 0.5 of the device time against 0.25 due, 4 of 40 done, 1 rival step, whose
    # 200 s of the 400 s queued for the spectrometer
    assert got["a/t1"] == pytest.approx((1.0, 0.25, 0.1, 0.1, 0.5), abs=1e-6)
    assert got["a/t2"] == got["a/t1"]
    assert got["b/t1"] == pytest.approx((0.0, -0.25, 1 / 60, 0.2, 0.5), abs=1e-6)
    alone = LabView(50.0, (step("t1", ""),), view.free, view.devices, finished=5, budget=100)
    assert columns(alone, lab)["t1"] == pytest.approx((1.0, 0.0, 0.05, 0.0, 0.0), abs=1e-6)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_lab_stepped_decision_by_decision_is_the_lab_run_with_that_scheduler(tmp_path, seed):
    lab = prepare(LAB, seed=seed, overrides=CONTENDED)
    stepped, mwkr, views = SteppedLab(lab), load_plugin("schedulers", "mwkr")(), []
    try:
        while not stepped.done:
            views.append(stepped.view)
            stepped.answer(mwkr.decide(stepped.view))
    finally:
        stepped.close()
    ran = run_shared(prepare(LAB, seed=seed, overrides={**CONTENDED, "orchestrator.lab_scheduler": "mwkr"}),
                     tmp_path, handle_signals=False)
    assert stepped.summary.ended_h == pytest.approx(ran.ended_h)
    assert {n: c.done for n, c in stepped.summary.campaigns.items()} == {n: c.done for n, c in ran.campaigns.items()}
    assert any({r.campaign for r in v.ready} == {"dots", "catalyst"} for v in views), "no question had both's steps"
    assert all(r.task.startswith(r.campaign + "/") for v in views for r in v.ready)
    assert all({c.name for c in v.campaigns} <= {"dots", "catalyst"} and
               sum(c.share for c in v.campaigns) == pytest.approx(1.0) for v in views)


def test_a_policy_of_the_earlier_encoding_decides_as_before_and_widened_the_same():
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.candidate_policy import CandidatePolicy
    from agents.scheduling_env import SchedulingEnv

    lab = prepare(LAB, seed=1, overrides=CONTENDED)
    old = RlScheduler(lab, str(EARLIER))
    assert not old.sees_campaigns and old.encoder.width == WIDTHS["candidates-v2"]
    old.encoder.held = None  # the network widened, compared as it reads: not held inside its file's range
    host = DummyVecEnv([lambda: SchedulingEnv(lab, randomise=False)])
    model = MaskablePPO(CandidatePolicy, host, device="cpu")
    host.close()
    model.policy.load_state_dict(initial_state(EARLIER, lab, "candidates"))
    widened = RlScheduler.from_model(model, lab, trained_encoding("candidates-v2"))  # v3: v2's columns and five
    assert widened.encoder.width == FEATURES
    stepped, decisions = SteppedLab(lab), 0
    try:
        while not stepped.done:
            chosen = old.decide(stepped.view)
            assert widened.decide(stepped.view) == chosen
            stepped.answer(chosen)
            decisions += 1
    finally:
        stepped.close()
    assert decisions > 20
    obs = torch.as_tensor(widened.encoder.encode(stepped.view if stepped.view else _last(lab, old))[0]).unsqueeze(0)
    before = model.policy.action_net(obs)
    model.policy.action_net.sets.embed[0].weight.data[:, -5:] += 1.0  # the campaign columns now count
    assert not torch.allclose(model.policy.action_net(obs), before), "the campaign columns are not read"


def _last(lab, scheduler) -> LabView:
    """A question of the lab to its one scheduler with both campaigns' steps in it."""
    stepped = SteppedLab(lab)
    try:
        while {r.campaign for r in stepped.view.ready} != {"dots", "catalyst"}:
            stepped.answer(scheduler.decide(stepped.view))
        return stepped.view
    finally:
        stepped.close()


BUSY = ROOT / "scenarios" / "busy_lab.yaml"


def test_a_campaigns_weight_doubles_per_lower_priority_and_follows_its_share():
    from agents.lab_scheduling import weights

    lab = prepare(BUSY, overrides={"campaigns.0.priority": 2, "campaigns.1.priority": 1, "campaigns.2.priority": 0,
                                   "campaigns.2.share": 0.5})
    assert weights(lab) == {"dots": 4.0, "catalyst": 4.0, "bandgap": 0.5}  # catalyst: share 2


def test_a_lab_is_trained_from_a_policy_by_its_own_best_runs_and_says_so_when_it_cannot_be(tmp_path, caplog):
    from agents.imitation import self_task
    from agents.train_scheduler import train_scheduler
    from twin import read_meta

    lab = prepare(BUSY, overrides={"training.samples": 4})
    with pytest.raises(ValueError, match=r"busy_lab: .*own best runs.*--init P.zip"):
        train_scheduler(prepare(BUSY, overrides={"training.teacher": "self"}), 100, tmp_path / "p.zip")
    with pytest.raises(ValueError, match=r"here candidates, ppo, "):
        train_scheduler(prepare(BUSY, overrides={"training.method": "ppo"}), 100, tmp_path / "p.zip", init=SHIPPED)
    # a worker's labels: variants of the lab, whose questions hold several campaigns' steps
    state = initial_state(SHIPPED, lab, "candidates", part="action_net")
    labelled = []
    for seed in (1, 2):
        samples, info = self_task((lab, seed, ("self",), state, 0.0, "candidates-v3"))
        labelled += samples
        assert info["greedy ÷ best"] >= 1.0 and {"prepare", "react", "synthesise", "measure"} <= set(info["shape"]["steps"])
    top, rivals = np.concatenate([s.rows[:, -5] for s in labelled]), np.concatenate([s.rows[:, -2] for s in labelled])
    assert (top == 0).any() and (top == 1).any(), "no label had candidates of a campaign below the top priority"
    assert (rivals > 0).any(), "no label had two campaigns' steps queued for one device type"
    out = train_scheduler(lab, 300, tmp_path / "lab.zip", envs=1, eval_every=300, init=SHIPPED, held_out_count=2,
                          eval_seeds=(0, 1))
    meta = read_meta(out)
    assert meta["signature"]["encoding"] == "candidates-v3" and meta["method"] == "imitate"  # SHIPPED's own
    assert "reads labs as candidates-v3: the policy trained from it keeps those columns" in caplog.text
    assert "turns" in meta["rules"] and meta["lineage"][-1]["steps"] == read_meta(SHIPPED)["steps"]
    ran = run_shared(prepare(BUSY, seed=3, overrides={"orchestrator.lab_scheduler": f"rl:{out}"}), tmp_path / "j",
                     handle_signals=False)
    assert all(c.done + c.abandoned == c.proposed > 0 for c in ran.campaigns.values())


def test_a_lab_whose_rule_learnt_does_worse_than_the_shipped_policy_keeps_that_policy(tmp_path):
    """busy_lab says nothing of its teacher: its training starts from the shipped policy, which scores about 1.08 ×
    the turns there (1.076–1.085 on this machine's CPUs: torch's float kernels differ), so the best rule is learnt
    instead — and a short training of it ends at 1.42: the policy left at --out is the best one evaluated, the
    shipped one, not the last training's."""
    from agents.train_scheduler import FALL_BACK_ABOVE, GENERAL_POLICY, train_scheduler
    from twin import read_meta

    said: list[str] = []
    out = train_scheduler(prepare(BUSY, overrides={"training.samples": 4}), 300, tmp_path / "p.zip", envs=1,
                          eval_every=300, eval_seeds=(0,), held_out_count=2,
                          on_progress=lambda done, result: said.append((result or {}).get("policy", "")))
    meta = read_meta(out)
    assert (meta["teacher"], meta["init"]) == ("self", str(GENERAL_POLICY))
    assert [c["steps"] for c in meta["curve"]] == [0] and meta["curve"][0]["score"] > FALL_BACK_ABOVE
    learnt = next(i for i, s in enumerate(said) if "learning the best rule instead, from scratch" in s)
    assert any(s.startswith("best-rule teacher") for s in said[learnt:])  # it was learnt, and did worse
    began = meta["curve"][0]["score"]
    assert said[-1] == f"kept the shipped general policy: its start ({began:.3f}) did better than the rule learnt", said


def test_fair_share_serves_the_top_priority_then_the_campaign_furthest_below_its_share():
    fair = load_plugin("schedulers", "fair-share")()
    free = (FreeDevice("spectrometer", "spectrometer"),)
    ready = (step("a/t1", "a"), step("b/t1", "b"), step("c/t1", "c"))

    def given(*states):
        return fair.decide(LabView(0.0, ready, free, campaigns=states))[0].task

    a, c = CampaignState("a", 0, 0.5, 0.6, 0, 9), CampaignState("c", 0, 0.2, 0.25, 0, 9)
    assert given(a, CampaignState("b", 0, 0.3, 0.1, 0, 9), c) == "b/t1"  # 0.2 below its share
    assert given(a, CampaignState("b", 0, 0.3, 0.5, 0, 9), c) == "c/t1"  # 0.05 above it; a 0.1, b 0.2
    assert given(a, CampaignState("b", 0, 0.3, 0.1, 0, 9), CampaignState("c", 1, 0.2, 0.3, 0, 9)) == "c/t1"


def test_the_gym_environment_refuses_a_lab_of_several_campaigns_with_what_to_use():
    from agents.scheduling_env import SchedulingEnv

    with pytest.raises(ValueError, match=r"busy_lab: a lab of several campaigns.*twin train.*SteppedLab"):
        SchedulingEnv(prepare(BUSY)).reset(seed=0)


def test_the_planning_environment_refuses_a_lab_of_several_campaigns_and_takes_one_of_them():
    """It said "the rl planner needs targets on the same outputs; got []": the lab's own chemistry is empty."""
    from agents.planning_env import PlanningEnv
    from twin import campaign_scenarios

    with pytest.raises(ValueError, match=r"a lab of several campaigns \(dots, catalyst\).*campaign_scenarios"):
        PlanningEnv(prepare(LAB))
    env = PlanningEnv(campaign_scenarios(prepare(LAB))["dots"])
    try:
        obs, _ = env.reset(seed=0)
        assert obs.shape == env.observation_space.shape
    finally:
        env.close()


def test_each_campaigns_samples_age_by_its_own_stability_also_one_submitted_later():
    lab = prepare(LAB)
    made = ReadyStep("x/t", 0, "measure", "spectrometer", 0.0, 100.0, 60.0, 60.0, campaign="x")
    other = ReadyStep("y/t", 0, "measure", "spectrometer", 0.0, 100.0, 60.0, 60.0, campaign="y")
    view = LabView(1900.0, (made, other), (FreeDevice("spectrometer", "spectrometer"),),
                   campaigns=(CampaignState("x", 0, 0.5, 0.5, 0, 9, 3600.0), CampaignState("y", 0, 0.5, 0.5, 0, 9)))
    enc = CandidateEncoder(lab)  # "x" and "y" are in no lab file: as if submitted to a served lab
    obs, _ = enc.encode(view)
    rows = {r.task: row for (r, _), row in zip(enc.encoded, obs[:MAX_CANDIDATES * FEATURES].reshape(-1, FEATURES))}
    assert rows["x/t"][5] == pytest.approx(1800 / 3600)  # age ÷ its stability
    assert rows["y/t"][5] == 0.0  # its samples keep for ever


def test_a_lab_policy_for_other_steps_is_refused_before_a_journal_is_made(tmp_path):
    """The lab's one scheduler is judged on every step its devices run (campaigns may be submitted later)."""
    from twin import PluginError

    furnace = {"driver": "synthesiser", "instances": 1, "steps": ["anneal"], "duration": {"mean_s": 600}}
    lab = prepare(BUSY, overrides={"devices.furnace": furnace, "campaign.policy_fit": "refuse",
                                   "orchestrator.lab_scheduler": "rl:agents/policies/lab_scheduler.zip"})
    with pytest.raises(PluginError, match=r"step type\(s\) \['anneal'\] never seen.*4 device types"):
        run_shared(lab, tmp_path / "j", handle_signals=False)
    assert not (tmp_path / "j").exists() or not list((tmp_path / "j").iterdir())


def test_the_planning_environment_says_what_targets_it_needs():
    """'the rl planner needs targets on the same outputs; got []' for a lab without targets."""
    from agents.planning_env import target_shape

    none = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides={"chemistry.targets": []})
    with pytest.raises(ValueError, match=r"flaky_lab: the rl planner .* it has none: give chemistry.targets"):
        target_shape(none)
    mixed = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides={"chemistry.targets": [
        {"name": "a", "outputs": {"yield": {"min": 90}}}, {"name": "b", "outputs": {"selectivity": {"min": 95}}}]})
    with pytest.raises(ValueError, match=r"these ask for selectivity / yield: train one planner per kind of target"):
        target_shape(mixed)
