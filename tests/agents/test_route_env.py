"""labtwin/SynthesisRoute-v0 and the route trainer: masks that say what applies, rewards for short cheap
routes, a known route replayed to its reward, and a short training whose prior beats a uniform one."""

from __future__ import annotations

import json
import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from agents.routes import stock as stock_file
from agents.routes import templates as template_file
from agents.routes.env import ENV_ID, SynthesisRouteEnv
from agents.routes.policy import load_prior
from agents.routes.targets import target_set
from twin import load_scenario

TEMPLATES, STOCK = template_file.load(), stock_file.load()
TARGETS = target_set(TEMPLATES, STOCK, 12, depths=range(1, 3))


@pytest.fixture(scope="module")
def env():
    return SynthesisRouteEnv(TEMPLATES, STOCK, [t.smiles for t in TARGETS], seed=0)


def test_the_env_is_registered_and_passes_gymnasiums_checks():
    made = gym.make(ENV_ID, templates=TEMPLATES, stock=STOCK, targets=[TARGETS[0].smiles])
    check_env(made.unwrapped, skip_render_check=True)
    made.close()


def test_a_known_route_replayed_reaches_stock_with_the_reward_for_its_length_and_cost(env):
    for target in TARGETS:
        env.reset(options={"target": target.smiles})
        index = {t.name: i for i, t in enumerate(TEMPLATES)}
        total, info = 0.0, {}
        for name, _, product in reversed(target.route):  # the last reaction first, as retrosynthesis goes
            if not env.open:
                break
            assert env.open[0] == product
            mask = env.action_masks()
            assert mask[index[name]]
            _, reward, done, _, info = env.step(index[name])
            total += reward
            if done:
                break
        if not info.get("solved"):
            continue  # the env's first disconnection for that template differs from the one the target was made by
        eur = sum(STOCK.get(x).eur_per_g or 0.0 for x in info["bought"])
        assert total == pytest.approx(1 - 0.1 * (info["reactions"] - 1) - 0.05 * math.log10(1 + eur))
        return
    pytest.fail("no known route replayed to stock")


def test_masked_actions_always_apply_and_an_unmasked_one_loses(env):
    env.reset(seed=3)
    mask = env.action_masks()
    assert mask.any() and not mask.all()
    _, reward, done, _, info = env.step(int(np.flatnonzero(~mask)[0]))
    assert done and reward == -1.0 and "does not apply" in info["why"]
    rng = np.random.default_rng(0)
    for episode in range(10):
        env.reset(seed=episode)
        while True:
            action = int(rng.choice(np.flatnonzero(env.action_masks())))
            _, reward, done, _, info = env.step(action)
            assert "does not apply" not in info["why"]
            if done:
                assert (reward > 0) == info["solved"] and info["reactions"] <= env.max_steps
                break


def test_a_target_in_stock_or_unreadable_is_refused(env):
    with pytest.raises(ValueError, match="in stock"):
        env.reset(options={"target": "CC(=O)O"})
    with pytest.raises(ValueError, match="SMILES"):
        env.reset(options={"target": "C1CC(("})


def test_a_short_training_gives_a_prior_that_needs_fewer_expansions_than_a_uniform_one(tmp_path):
    from agents.routes.train_rl import train_route

    torch.set_num_threads(1)
    seen = []
    out = train_route(load_scenario("scenarios/aspirin.yaml"), 128, tmp_path / "prior", envs=1, eval_every=128,
                      targets=100, eval_targets=4, eval_mcts=4, eval_expansions=60,
                      on_progress=lambda d, r: r and seen.append((d, r)))
    meta = json.loads(out.with_suffix(".json").read_text())
    assert [d for d, _ in seen] == [0, 0, 128] and seen[-1][1]["policy"] == "maskable-ppo"
    assert meta["kind"] == "route-prior" and meta["method"] == "imitation + MaskablePPO"
    best = max(meta["curve"], key=lambda c: (c["mcts_solved"], c["greedy_solved"], -c["expansions"]))
    assert best["mcts_solved"] >= meta["baseline"]["mcts_solved"]
    assert best["expansions"] < meta["baseline"]["expansions"]
    prior = load_prior(out.with_suffix(""), TEMPLATES)  # what MCTS and the route planner load
    assert prior.ranked(TARGETS[0].smiles)
