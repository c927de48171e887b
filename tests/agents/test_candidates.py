"""The candidate-scoring scheduler (issue [4 of 7], first part): every allowed pair is a candidate in labs of
any size, a short training beats a random policy, and a policy trained on ft06 runs labs far larger."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.candidates import MAX_CANDIDATES, WAIT, CandidateEncoder
from agents.rl_scheduler import RlScheduler
from agents.scheduling_env import SchedulingEnv
from agents.judging import campaign
from agents.train_scheduler import train_scheduler
from tests.agents.test_scheduling import live_and_env
from tests.conftest import qd_lab
from twin import PluginError, jobshop_as_lab, random_jobshop
from twin.campaign.decisions import capable
from twin.runtime.lab import prepare
from twin.scenario import parse

ROOT = Path(__file__).resolve().parents[2]
torch.set_num_threads(1)


def wide_lab(**changes):
    """Six fast synthesisers feeding six slow spectrometers: many ready steps, more instances than a grid held."""
    return parse(qd_lab(**{"devices.synthesiser.instances": 6, "devices.spectrometer.instances": 6,
                           "devices.synthesiser.duration": {"mean_s": 30, "cv": 0.2},
                           "devices.spectrometer.duration": {"mean_s": 400, "cv": 0.2},
                           "campaign.budget": 36, "campaign.max_in_flight": 36, **changes}))


def random_makespans(lab, runs=5):
    """Lab-hours of ``runs`` campaigns of ``lab`` by a policy that picks uniformly among the allowed actions."""
    enc, rng = CandidateEncoder(lab), np.random.default_rng(1)

    def random_decide(view):
        _, mask = enc.encode(view)
        return enc.decode(view, int(rng.choice(np.flatnonzero(mask))))

    return [campaign(lab, 0, random_decide).lab_hours for _ in range(runs)]


@pytest.fixture(scope="module")
def ft06():
    return prepare(ROOT / "scenarios" / "jobshop.yaml", overrides={"training.jobshop_sizes": [], "training.method": "ppo"})


@pytest.fixture(scope="module")
def trained(ft06, tmp_path_factory):
    """A candidate policy trained for a few seconds on ft06 alone."""
    path = tmp_path_factory.mktemp("policy") / "ft06-candidates.zip"
    train_scheduler(ft06, 4096, path, envs=2, eval_every=4096, eval_seeds=(0,))
    return path


def test_every_allowed_pair_is_one_candidate_however_many_steps_and_instances():
    env = SchedulingEnv(wide_lab(), randomise=False, encoding="candidates")
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    most_ready, most_pairs, done, truncated = 0, 0, False, False
    while not done:
        view, mask = env.campaign.view, env.action_masks()
        allowed = {(r.task, f.name) for r in view.ready for f in capable(r, view.free)}
        pairs = [(r.task, name) for r, name in env.encoder.pairs(view)]
        assert len(pairs) == len(set(pairs)) and set(pairs) <= allowed
        if len(allowed) <= MAX_CANDIDATES:
            assert set(pairs) == allowed
        else:  # a very large decision is seen in part: the steps with the most work remaining first
            truncated = True
            assert len(pairs) == MAX_CANDIDATES
            work = {r.task: r.work_remaining_s for r in view.ready}
            kept = min(work[t] for t, _ in pairs)
            assert all(work[t] <= kept for t, _ in allowed - set(pairs))
        assert mask[:len(pairs)].all() and not mask[len(pairs):WAIT].any()
        for i in range(len(pairs)):  # each action starts exactly its pair
            (a,) = env.encoder.decode(view, i)
            assert (a.task, a.device) == pairs[i]
        most_ready, most_pairs = max(most_ready, len(view.ready)), max(most_pairs, len(pairs))
        _, _, done, _, _ = env.step(int(rng.choice(np.flatnonzero(mask))))
    env.close()
    assert most_ready > 10 and most_pairs > 10  # beyond the old grid's 10 slots x 4 instances per step
    assert truncated  # 36 ready syntheses x 6 free synthesisers at the start


def test_a_short_training_beats_a_random_policy(ft06, trained):
    rl = campaign(ft06, 0, RlScheduler(ft06, str(trained)).decide).lab_hours
    randoms = random_makespans(ft06)
    assert rl < min(randoms), (rl, randoms)


def test_a_policy_trained_on_ft06_runs_a_larger_shop_and_uses_every_instance(ft06, trained):
    big = jobshop_as_lab(ft06, random_jobshop(15, 15, 1, 10, __import__("random").Random(3)))
    summary = campaign(big, 0, RlScheduler(big, str(trained)).decide)
    assert summary.done == 15 and summary.abandoned == 0
    lab = wide_lab(**{"campaign.scheduler": "fifo"})
    summary = campaign(lab, 0, RlScheduler(lab, str(trained)).decide)
    assert summary.done == 36
    used = [u for name, u in summary.utilisation.items() if name.startswith("spectrometer")]
    assert len(used) == 6 and min(used) > 0.3, summary.utilisation  # the bottleneck's six, all kept busy


def test_a_policy_knows_the_labs_it_fits_and_warns_or_refuses_outside_them(ft06, trained, caplog):
    assert RlScheduler(ft06, str(trained)).misfit == ""
    flaky = prepare(ROOT / "scenarios" / "flaky_lab.yaml")
    with caplog.at_level("WARNING"):
        warned = RlScheduler(flaky, str(trained)).misfit
    assert "step type(s) ['measure', 'prepare', 'react'] never seen" in warned and warned in caplog.text
    assert "3 device types (trained on 6)" in warned
    assert "2 instances of one type (trained on at most 1)" in warned
    with pytest.raises(PluginError, match=r"trained on labs unlike 'flaky_lab'.*policy_fit: refuse"):
        RlScheduler(prepare(flaky, overrides={"campaign.policy_fit": "refuse"}), str(trained))
    bigger = jobshop_as_lab(ft06, random_jobshop(10, 8, 1, 10, __import__("random").Random(0)))
    assert "8 device types (trained on 6)" in RlScheduler(bigger, str(trained)).misfit


def test_a_policy_of_an_older_encoding_is_refused_with_what_to_do(ft06, trained, tmp_path):
    old = tmp_path / "old.zip"
    old.write_bytes(trained.read_bytes())
    meta = json.loads(trained.with_suffix(".json").read_text())
    meta["signature"]["encoding"] = "candidates-v1"
    old.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(PluginError, match=r"old.zip reads labs as candidates-v1.*retrain it with `twin train"):
        RlScheduler(ft06, str(old))


def test_the_live_agent_over_zenoh_dispatches_what_the_env_does(ft06, trained, tmp_path):
    live, in_env, summary = live_and_env(ft06, trained, tmp_path)
    assert live == in_env and len(live) == 36
    assert summary.scheduler_fallbacks == 0


@pytest.mark.parametrize("policy, scenario", [("agents/policies/flaky_scheduler.zip", "flaky_lab.yaml"),
                                              ("agents/policies/jobshop_scheduler.zip", "jobshop.yaml"),
                                              ("tests/data/jobshop_scheduler_v2.zip", "jobshop.yaml")])
def test_a_greedy_decision_is_the_one_sb3_predict_takes(policy, scenario):
    """The rl scheduler scores candidates with the policy's own network and takes the most probable under the
    mask, as SB3's predict(deterministic=True) does — every decision of a campaign, policies of v3, v4 and v2."""
    lab = prepare(ROOT / "scenarios" / scenario)
    rl = RlScheduler(lab, str(ROOT / policy))
    views = []

    def decide(view):
        views.append(view)
        return rl.decide(view)

    campaign(lab, 0, decide)
    assert len(views) > 30
    for view in views:
        obs, mask = rl.encoder.encode(view)
        action, _ = rl.model.predict(obs, action_masks=mask, deterministic=True)
        assert rl.decide(view) == rl.encoder.decode(view, int(action))
