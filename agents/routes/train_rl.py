"""``twin train SCENARIO --agent route``: the expansion prior, taught by imitation and then by MaskablePPO in
``labtwin/SynthesisRoute-v0``; written as a route prior (``P.pt`` + ``P.json``) that MCTS, ``twin route
--prior P`` and the route planner (``planner_options.prior``) use as they are.

1. Imitation: the scorer learns every step of the known routes of ``targets`` training targets (made forwards
   from the scenario's stock and templates; seeds the held-out set never uses).
2. Reinforcement: MaskablePPO, its actor the same network (fingerprint → 256 ReLU → one logit per template,
   copied in), plays the route game on the same training targets: reward for reaching stock in few reactions
   and cheaply, −1 for a dead end.
3. Every ``eval_every`` steps (and before any PPO step) it is judged on held-out targets: the share its greedy
   choices solve, and MCTS guided by it (a budget of ``EVAL_EXPANSIONS`` expansions, so the judgement does not
   depend on the machine's speed): solved and mean expansions. The best by (MCTS solved, greedy solved, fewer
   expansions) is kept.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from agents.routes.env import SynthesisRouteEnv
from agents.routes.mcts import mcts, uniform
from agents.routes.plan import inputs
from agents.routes.policy import (HIDDEN, LearnedPrior, TemplateScorer, examples, fingerprint, load_prior, save_prior,
                                  train_prior)
from agents.routes.search import Expander
from agents.routes.targets import target_set
from agents.sb3_logging import without_log_dir
from twin import Scenario

EVAL_TARGETS = 30
EVAL_MCTS = 12
EVAL_EXPANSIONS = 150
PPO_SETTINGS = dict(n_steps=128, batch_size=128, n_epochs=4, learning_rate=1e-4, gamma=1.0, ent_coef=0.0)


def scorer_into_policy(scorer: TemplateScorer, policy) -> None:
    policy.mlp_extractor.policy_net[0].load_state_dict(scorer.net[0].state_dict())
    policy.action_net.load_state_dict(scorer.net[3].state_dict())


def policy_to_scorer_of(prior: LearnedPrior, templates) -> TemplateScorer:
    """A loaded prior's network, its outputs in the order of ``templates`` (a prior may score more)."""
    scorer = TemplateScorer(len(templates))
    rows = torch.as_tensor([prior.index[t.name] for t in templates])
    scorer.net[0].load_state_dict(prior.scorer.net[0].state_dict())
    last = prior.scorer.net[3]
    scorer.net[3].load_state_dict({"weight": last.weight[rows].clone(), "bias": last.bias[rows].clone()})
    return scorer.eval()


def policy_to_scorer(policy, templates: int) -> TemplateScorer:
    scorer = TemplateScorer(templates)
    scorer.net[0].load_state_dict(policy.mlp_extractor.policy_net[0].state_dict())
    scorer.net[3].load_state_dict(policy.action_net.state_dict())
    return scorer.eval()


def evaluate(scorer: TemplateScorer, templates, stock, held: list[str], expander: Expander,
             eval_mcts: int = EVAL_MCTS, expansions: int = EVAL_EXPANSIONS) -> dict[str, float]:
    """Greedy solved share on ``held``; MCTS guided by the scorer on the first ``eval_mcts``: solved, expansions."""
    prior = LearnedPrior(scorer, [t.name for t in templates])
    env = SynthesisRouteEnv(templates, stock, held, expander=expander)
    solved = 0
    for target in held:
        env.reset(options={"target": target})
        while True:
            mask = env.action_masks()
            with torch.no_grad():
                logits = scorer(torch.as_tensor(fingerprint(env.open[0])).unsqueeze(0))[0].numpy()
            _, _, done, _, info = env.step(int(np.argmax(np.where(mask, logits, -np.inf))))
            if done:
                solved += info["solved"]
                break
    runs = [mcts(t, templates, stock, prior=prior, max_expansions=expansions, max_seconds=1e9,
                 shared=expander.shared) for t in held[:eval_mcts]]
    return {"greedy_solved": solved / len(held), "mcts_solved": statistics.mean(r.route is not None for r in runs),
            "expansions": statistics.mean(r.expansions for r in runs)}


def uniform_baseline(templates, stock, held: list[str], expander: Expander, eval_mcts: int = EVAL_MCTS,
                     expansions: int = EVAL_EXPANSIONS) -> dict[str, float]:
    runs = [mcts(t, templates, stock, prior=uniform, max_expansions=expansions, max_seconds=1e9,
                 shared=expander.shared) for t in held[:eval_mcts]]
    return {"mcts_solved": statistics.mean(r.route is not None for r in runs),
            "expansions": statistics.mean(r.expansions for r in runs)}


def train_route(scenario: Scenario, steps: int, out: Path, seed: int = 0, envs: int = 4, eval_every: int = 20_000,
                on_progress: Callable[[int, dict | None], None] | None = None, targets: int = 2000,
                eval_targets: int = EVAL_TARGETS, eval_mcts: int = EVAL_MCTS,
                eval_expansions: int = EVAL_EXPANSIONS, init: Path | None = None) -> Path:
    """Imitation (or the prior ``init``), then MaskablePPO for ``steps`` environment steps; the best judged
    prior is saved at ``out``."""
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    torch.set_num_threads(1)
    options = scenario.campaign.planner_options
    templates, stock = inputs(options.get("stock"), options.get("templates"))
    if on_progress:  # the stock and templates are read: the bar starts
        on_progress(0, None)
    train = target_set(templates, stock, targets)
    held = [t.smiles for t in target_set(templates, stock, eval_targets, held_out=True)]
    names = len(templates)
    if init is not None:
        start = load_prior(Path(init).with_suffix(""), templates)
        scorer = policy_to_scorer_of(start, templates)
    else:
        scorer = train_prior(templates, examples(train), epochs=20, seed=seed)
    eval_expander = Expander(templates)  # its cache is shared by every judging search (counts stay per search)
    judged = dict(eval_mcts=eval_mcts, expansions=eval_expansions)
    baseline = uniform_baseline(templates, stock, held, eval_expander, **judged)
    if on_progress:
        on_progress(0, {"policy": "mcts uniform", **baseline})
    first = evaluate(scorer, templates, stock, held, eval_expander, **judged)
    if on_progress:
        on_progress(0, {"policy": "start" if init is not None else "imitation", **first})
    out = Path(out).with_suffix(".pt")
    curve = [{"steps": 0, **first}]
    meta = dict(method=("from " + str(init) if init is not None else "imitation") + " + MaskablePPO",
                scenario=scenario.name, targets=targets, baseline=baseline,
                command=f"twin train SCENARIO --agent route --steps {steps} --envs {envs} --eval-every {eval_every} "
                        f"--seed {seed}{f' --init {init}' if init is not None else ''} --out {out.with_suffix('')}")
    best = (first["mcts_solved"], first["greedy_solved"], -first["expansions"])
    save_prior(scorer, templates, out, steps=0, curve=curve, **meta)

    expander = Expander(templates)  # one cache for every environment: molecules recur across episodes
    smiles = [t.smiles for t in train]
    venv = DummyVecEnv([lambda i=i: SynthesisRouteEnv(templates, stock, smiles, seed=seed * 1000 + i,
                                                      expander=expander) for i in range(envs)])
    model = MaskablePPO("MlpPolicy", venv, seed=seed, verbose=0, device="cpu",
                        policy_kwargs=dict(net_arch=dict(pi=[HIDDEN], vf=[64]), activation_fn=nn.ReLU),
                        **PPO_SETTINGS)
    without_log_dir(model)
    scorer_into_policy(scorer, model.policy)
    done = 0
    while done < steps:
        chunk = min(eval_every, steps - done)
        model.learn(chunk, reset_num_timesteps=False)
        done += chunk
        now = policy_to_scorer(model.policy, names)
        result = evaluate(now, templates, stock, held, eval_expander, **judged)
        curve.append({"steps": done, **result})
        key = (result["mcts_solved"], result["greedy_solved"], -result["expansions"])
        if key >= best:
            best = key
            save_prior(now, templates, out, steps=done, curve=curve, **meta)
        if on_progress:
            on_progress(done, {"policy": "maskable-ppo", **result})
    return out
