"""training.teacher: self-pg — every sampled run of a lab is learnt from, weighted by how much better than the runs'
mean it ended (REINFORCE with the runs' mean as the baseline)."""

import copy
import json
import random

import numpy as np
import pytest
import torch

from agents.imitation import _reinforced, _scorer, sampled_runs
from agents.label_fit import batch, fit
from agents.judging import objective
from agents.train_scheduler import train_scheduler
from tests.agents.test_self_labelling import AS_SHIPPED, SHIPPED, replay
from twin import jobshop_as_lab, random_jobshop
from twin.runtime.lab import prepare

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def shop(ft06):
    return prepare(jobshop_as_lab(ft06, random_jobshop(8, 5, 1, 50, random.Random(5))), seed=0)


def test_every_sampled_run_is_labelled_and_weighted_by_its_advantage(shop, state):
    samples, info = _reinforced(shop, _scorer(state, 3), 6, 3, AS_SHIPPED)
    runs = sampled_runs(shop, _scorer(state, 3), 6, (1.0,), AS_SHIPPED, greedy_first=False,
                        generator=torch.Generator().manual_seed(3))  # the same draws
    scores = np.array([objective(summary, shop) for _, summary in runs])
    assert scores.std() > 0, "the sampled runs all ended alike"
    expected = [(scores.mean() - s) / scores.std() for s in scores]
    at = 0
    for (labelled, summary), advantage in zip(runs, expected):
        mine = samples[at:at + len(labelled)]
        at += len(labelled)
        assert all(s.weight == pytest.approx(advantage) for s in mine)
        assert replay(shop, mine) == pytest.approx(summary.lab_hours * 3600)  # the labels are that run's choices
    assert at == len(samples)
    assert info["sampled ÷ best"] == pytest.approx(scores.mean() / scores.min())


def test_a_positive_weight_makes_a_choice_likelier_and_a_negative_one_less_likely(shop, state):
    samples, _ = _reinforced(shop, _scorer(state, 3), 4, 3, AS_SHIPPED)

    def p_taught(net, sample) -> float:
        obs, allowed, taught = batch([sample])
        with torch.no_grad():
            probs = torch.softmax(net(obs).masked_fill(~allowed, -1e9), 1)
        return float(probs[taught].sum())

    sample = next(s for s in samples if 0.05 < p_taught(_scorer(state, 0), s) < 0.95)  # a choice it hesitated over
    before = p_taught(_scorer(state, 0), sample)
    for weight, moved in ((1.0, lambda p: p > before), (-1.0, lambda p: p < before)):
        net = _scorer(copy.deepcopy(state), 0)
        one = copy.copy(sample)
        one.weight = weight
        fit(net, [one, copy.copy(one)], 1, torch.optim.SGD(net.parameters(), lr=0.05))
        assert moved(p_taught(net, sample)), (weight, before, p_taught(net, sample))


def test_self_pg_starts_from_a_policy_and_its_training_says_what_it_did(ft06, tmp_path, rollouts_in_process):
    pg = prepare(ft06, overrides={"training.teacher": "self-pg", "training.jobshop_sizes": [[6, 6]],
                                  "training.samples": 4})
    with pytest.raises(ValueError, match="training.teacher 'self-pg' improves a policy on its own rollouts, so it "
                                         "starts from one: pass --init POLICY.zip"):
        train_scheduler(pg, 100, tmp_path / "x.zip")
    out, seen = tmp_path / "tuned.zip", []
    train_scheduler(pg, 600, out, envs=2, eval_every=300, eval_seeds=(0,), held_out_count=2, init=SHIPPED,
                    on_progress=lambda done, result: seen.append(result) if result and "objective" in result else None)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["teacher"] == "self-pg" and meta["init"] == str(SHIPPED)
    assert [r["policy"].split(" (")[0] for r in seen[1:]][:2] == ["start", "policy gradient"]
    assert all(r["sampled ÷ best"] >= 1 for r in seen[2:])
