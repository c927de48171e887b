"""Train the RL scheduler: MaskablePPO in `labtwin/Scheduling-v0`, evaluated against every rule.

Evaluation runs whole campaigns of the scenario as written (no randomisation)
on fixed seeds the training never uses, for the policy and for each
dispatching rule, and reports the mean makespan (lab-hours), degraded and
abandoned samples; the policy is kept when it beats its best evaluation so far.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from agents.scheduling_env import SchedulingEnv, randomised
from agents.rl_scheduler import RlScheduler
from agents.candidates import signature as candidate_signature
from agents.candidates import widen
from agents.scheduling_features import signature, time_scale
from agents.schedulers import RULES
from twin import load_plugin
from twin import Assignment, LabView
from twin import prepare
from twin import save_policy
from twin import Scenario
from twin import SteppedCampaign

EVAL_SEEDS = tuple(range(100_000, 100_005))
CANDIDATE_SETTINGS = dict(n_steps=1024, batch_size=512, n_epochs=8, gamma=0.995, gae_lambda=0.95, learning_rate=1e-4,
                          ent_coef=0.01)
HELD_OUT_SEED = -1_000_000  # reset() draws seeds in [0, 2**31): negative ones are never trained on
PPO_SETTINGS = dict(n_steps=512, batch_size=256, n_epochs=10, gamma=0.995, gae_lambda=0.95, learning_rate=3e-4,
                    ent_coef=0.01, policy_kwargs=dict(net_arch=[128, 128]))


def campaign(scenario: Scenario, seed: int, decide: Callable[[LabView], list[Assignment]]) -> Any:
    """One whole campaign, scheduled by ``decide``; its summary."""
    c = SteppedCampaign(prepare(scenario, seed=seed))
    try:
        while not c.done:
            c.answer(decide(c.view))
        return c.summary
    finally:
        c.close()


def objective(summary: Any, scenario: Scenario) -> float:
    """What the environment's reward sums to (negated): lab time in typical steps, degraded samples and
    abandoned experiments, weighted by ``training.weights``."""
    w = scenario.training.weights
    return (w.time * summary.lab_hours * 3600 / time_scale(scenario) + w.degraded * summary.degraded_samples
            + w.abandoned * summary.abandoned)


def score(summaries: list[Any], scenario: Scenario | None = None) -> dict[str, float]:
    out = {"makespan h": statistics.mean(s.lab_hours for s in summaries),
           "degraded": statistics.mean(s.degraded_samples for s in summaries),
           "abandoned": statistics.mean(s.abandoned for s in summaries)}
    if scenario is not None:
        out["objective"] = statistics.mean(objective(s, scenario) for s in summaries)
    return out


def evaluate_rules(scenario: Scenario, seeds=EVAL_SEEDS) -> dict[str, dict[str, float]]:
    return {rule: score([campaign(scenario, seed, load_plugin("schedulers", rule)().decide) for seed in seeds],
                        scenario) for rule in RULES}


def held_out_labs(scenario: Scenario, n: int) -> list[Scenario]:
    """Labs drawn from the scenario's ``training`` ranges with seeds the training draws never use."""
    t = scenario.training
    if not (t.jobshop_sizes or t.instances or t.operation_s or t.duration_scale != (1.0, 1.0)):
        return []
    return [prepare(randomised(scenario, HELD_OUT_SEED + i), seed=0) for i in range(n)]


def train_scheduler(scenario: Scenario, steps: int, out: Path, seed: int = 0, envs: int = 2,
                    eval_every: int = 20_000, on_progress: Callable[[int, dict | None], None] | None = None,
                    eval_seeds=EVAL_SEEDS, encoding: str = "candidates", held_out_count: int = 6) -> Path:
    """``encoding``: ``candidates`` (the candidate-scoring policy) or ``slots`` (an MLP over the fixed grid,
    the baseline).
    The policy kept is the best by its objective (what the reward sums to: makespan, degraded samples and
    abandoned experiments, weighted by ``training.weights``) relative to the best rule's, averaged over the
    scenario as written and ``held_out_count`` labs drawn from its ``training`` ranges with seeds training
    never uses. The curve reports makespan against the best rule too, so a trade is visible."""
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    torch.set_num_threads(1)
    venv = DummyVecEnv([lambda: SchedulingEnv(scenario, encoding=encoding) for _ in range(envs)])
    venv.seed(seed)
    if encoding == "candidates":
        from stable_baselines3.common.vec_env import VecNormalize

        from agents.candidate_policy import CandidatePolicy

        # labs of 36 and of 300 operations in one training: returns differ tenfold, so rewards are scaled by
        # a running estimate of the returns' spread (training only: the policy never sees rewards)
        venv = VecNormalize(venv, norm_obs=False, norm_reward=True, gamma=CANDIDATE_SETTINGS["gamma"])
        model = MaskablePPO(CandidatePolicy, venv, seed=seed, verbose=0, device="cpu", **CANDIDATE_SETTINGS)
        sign = candidate_signature(scenario)
    else:
        model = MaskablePPO("MlpPolicy", venv, seed=seed, verbose=0, device="cpu", **PPO_SETTINGS)
        sign = signature(scenario)
    rules = evaluate_rules(scenario, eval_seeds)
    best_rule = min(rules, key=lambda r: rules[r]["objective"])
    held_out = held_out_labs(scenario, held_out_count)
    rule_spans = [min(objective(campaign(lab, 0, load_plugin("schedulers", r)().decide), lab) for r in RULES)
                  for lab in held_out]
    if on_progress:
        on_progress(0, {"policy": f"best rule: {best_rule}", **rules[best_rule]})
    best, done, curve = None, 0, []
    try:
        while done < steps:
            chunk = min(eval_every, steps - done)
            model.learn(chunk, reset_num_timesteps=False)
            done += chunk
            decide = RlScheduler.from_model(model, scenario, encoding).decide
            result = score([campaign(scenario, s, decide) for s in eval_seeds], scenario)
            result["vs best rule"] = result["makespan h"] / rules[best_rule]["makespan h"]
            ratios = [result["objective"] / rules[best_rule]["objective"]]
            result["objective vs best rule"] = ratios[0]
            if held_out:  # labs it never trained on: each against the best rule there
                ratios += [objective(campaign(lab, 0, RlScheduler.from_model(model, lab, encoding).decide), lab) / ref
                           for lab, ref in zip(held_out, rule_spans)]
                result["held-out vs best rule"] = statistics.mean(ratios[1:])
            result["score"] = statistics.mean(ratios)
            curve.append({"steps": done, **result})
            if best is None or result["score"] <= best:
                best = result["score"]
                fits = None
                for env in venv.unwrapped.envs:
                    fits = widen(fits, env.fits) if env.fits else fits
                save_policy(model, out, "scheduler", scenario, sign, steps=done, rules=rules, fits=fits,
                            best_rule=best_rule, curve=curve)
            if on_progress:  # after saving: what the user reads is on disk
                on_progress(done, {"policy": "maskable-ppo", **result})
    finally:
        venv.close()  # stops the campaigns in the environments, also on Ctrl-C
    return out.with_suffix(".zip")


def train_slot_scheduler(scenario: Scenario, steps: int, out: Path, **kwargs: Any) -> Path:
    """`twin train --agent scheduler-slots`: the fixed-grid policy, kept as a baseline."""
    return train_scheduler(scenario, steps, out, encoding="slots", **kwargs)
