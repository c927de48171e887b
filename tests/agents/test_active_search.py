"""campaign.rollout_search: active — the lab is played ahead in rounds, a copy of the policy tuned on it between
rounds; the lab follows the best run, and the policy itself is not changed."""

import logging
import random
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.active_search import ActiveSearch
from agents.label_fit import batch
from agents.lockstep import lockstep
from agents.rl_scheduler import RlScheduler
from agents.rollout_plan import ROUND, plan
from agents.judging import objective
from tests.agents.test_rollout_plan import POLICY, makespan, with_rollouts
from twin import jobshop_as_lab, random_jobshop, read_meta
from twin.runtime.lab import prepare

torch.set_num_threads(1)
PATH = Path(POLICY[3:])


@pytest.fixture(scope="module")
def shop(ft06):
    return jobshop_as_lab(ft06, random_jobshop(8, 5, 1, 99, random.Random("active:1")))


def parameters(net: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in net.parameters()]


def test_the_lab_follows_the_best_run_of_an_active_search_and_the_policy_is_unchanged(shop, tmp_path, capsys):
    greedy = makespan(with_rollouts(shop, 1), tmp_path)
    searched = with_rollouts(shop, 2 * ROUND + 8, **{"campaign.rollout_search": "active"})
    scheduler = RlScheduler(with_rollouts(shop, 1), str(PATH))
    net = scheduler.model.policy.action_net
    before = parameters(net)
    encoding = read_meta(PATH)["signature"]["encoding"]
    first = plan(searched, net, 2 * ROUND + 8, encoding, held=scheduler.encoder.held)
    assert all(torch.equal(a, b) for a, b in zip(before, parameters(net)))  # a copy was tuned, not the policy
    again = plan(searched, net, 2 * ROUND + 8, encoding, held=scheduler.encoder.held)
    assert first.orders == again.orders and first.best == again.best  # the same lab and seed, the same plan
    assert first.search == "active" and first.greedy_h * 3600 == pytest.approx(greedy)  # round one's greedy run
    assert first.best <= first.greedy
    assert makespan(searched, tmp_path) <= first.best_h * 3600 + 1e-6  # the lab keeps to the plan
    assert "active search: the policy tuned on this lab after every 32" in capsys.readouterr().err


def test_a_tuning_moves_the_copy_toward_the_rounds_better_runs(shop):
    """One gradient pass raises the round's runs' log-likelihoods weighted by their advantages (REINFORCE's
    surrogate): the runs better than the mean likelier, the worse ones less likely, taken together."""
    lab = prepare(shop)
    scheduler = RlScheduler(with_rollouts(shop, 1), str(PATH))
    search = ActiveSearch(scheduler.model.policy.action_net, seed=0)
    search.start(12)
    played = lockstep(lab, search.net, 12, (1.0,), read_meta(PATH)["signature"]["encoding"],
                      lambda i, enc, obs, mask, action, _: search.seen(i, enc, obs, mask, action), greedy_first=False,
                      generator=torch.Generator().manual_seed(4))
    scores = np.array([objective(summary, lab) for summary in played])
    assert scores.std() > 0, "the sampled runs all ended alike"
    runs, advantage = search.runs, (scores.mean() - scores) / scores.std()

    def surrogate() -> float:
        total = 0.0
        for samples, a in zip(runs, advantage):
            obs, allowed, taught = batch(samples)
            with torch.no_grad():
                logits = search.net(obs).masked_fill(~allowed, -1e9)
            total += a * float((logits.masked_fill(~taught, -1e9).logsumexp(1) - logits.logsumexp(1)).sum())
        return total

    before = surrogate()
    search.learn(list(scores), greedy_first=False)
    assert surrogate() > before
    assert search.rounds == 1 and search.runs == []


def test_an_active_search_without_rollouts_says_so_and_decides_greedily(shop, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="agents.rl_scheduler"):
        alone = makespan(with_rollouts(shop, 1, **{"campaign.rollout_search": "active"}), tmp_path)
    assert "campaign.rollout_search: active has nothing to search with campaign.rollouts: 1" in caplog.text
    assert alone == makespan(with_rollouts(shop, 1), tmp_path)


def test_a_bench_runs_its_rules_as_they_go_beside_a_policy_played_ahead_by_active_search(shop):
    """The bench runs a rule with campaign.rollouts: 1 (it cannot play ahead); with active search asked for, that
    was refused in the bench's worker, whose ScenarioError then broke the process pool."""
    from twin.tools.scheduler_bench import one

    s = with_rollouts(shop, ROUND + 8, **{"campaign.rollout_search": "active"})
    assert one(s, "mwkr", 0).makespan_s == one(with_rollouts(shop, 1), "mwkr", 0).makespan_s
    assert one(s, POLICY, 0).makespan_s <= one(with_rollouts(shop, 1), POLICY, 0).makespan_s
