"""Train the `rl` planner: PPO in `labtwin/Planning-v0`, evaluated on the scenario's own targets."""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.planning_env import PlanningEnv, signature
from agents.sb3_logging import without_log_dir
from twin import save_policy
from twin import Scenario

# Tuned on quantum_dots (see docs/benchmarks.md): a short horizon wants a short discount.
PPO_SETTINGS = dict(n_steps=256, batch_size=256, n_epochs=10, gamma=0.95, learning_rate=3e-4,
                    policy_kwargs=dict(net_arch=[64, 64]))
EVAL_EPISODES = 30


def evaluate(scenario: Scenario, act: Callable[[np.ndarray, Any], np.ndarray], episodes: int = EVAL_EPISODES,
             seed: int = 10_000) -> dict[str, float]:
    """Success rate, median experiments to target and mean return on the scenario's targets (fixed seeds)."""
    env = PlanningEnv(scenario, random_goals=0.0, seed=seed)
    env.action_space.seed(seed)  # random moves drawn alike in every run: a baseline that repeats
    targets = scenario.chemistry.targets
    met, used, returns = 0, [], []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i, options={"target": targets[i % len(targets)]})
        total = 0.0
        while True:
            obs, reward, terminated, truncated, info = env.step(act(obs, env))
            total += reward
            if terminated or truncated:
                break
        met += terminated
        used.append(info["experiments"])
        returns.append(total)
    return {"success": met / episodes, "experiments": float(statistics.median(used)),
            "return": float(statistics.mean(returns))}


def nothing_scored(scenario: Scenario, episodes: int = 3, seed: int = 10_000) -> str:
    """Why a planner could learn nothing in this lab — no experiment of a few episodes at random measured what the
    targets read, so every reward is the same — or ''."""
    env = PlanningEnv(scenario, random_goals=0.0, seed=seed)
    env.action_space.seed(seed)
    seen: set[str] = set()
    for i in range(episodes):
        _, info = env.reset(seed=seed + i)  # the episode's first experiment, at random
        terminated = truncated = False
        while True:
            seen |= set(env.last_measured.outputs)
            if math.isfinite(info["distance"]):
                return ""
            if terminated or truncated:
                break
            _, _, terminated, truncated, info = env.step(env.action_space.sample())
    reads = sorted({name for t in scenario.chemistry.targets for name in t.outputs})
    last = env.last_measured
    why = (f"the last was {'refused' if last.infeasible else 'failed'}: {last.infeasible or last.failed}"
           if last.infeasible or last.failed else
           f"their steps gave {', '.join(sorted(seen)) or 'no outputs'}")
    return (f"{scenario.name}: none of {env.horizon * episodes} experiments at random measured what the targets "
            f"read ({', '.join(reads)}) as a finite number, so the planner would learn nothing ({why}); check the "
            "targets' output names against the drivers' outputs, and the box against the devices' envelopes "
            "(`twin run` of the scenario says which outputs go unscored)")


def random_moves(obs: np.ndarray, env: PlanningEnv) -> np.ndarray:
    return env.action_space.sample()


def train_planner(scenario: Scenario, steps: int, out: Path, seed: int = 0, envs: int = 4,
                  eval_every: int = 20_000, on_progress: Callable[[int, dict | None], None] | None = None) -> Path:
    """Train, evaluating every ``eval_every`` steps; saves the best evaluated policy to ``out``."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    unlearnable = nothing_scored(scenario)
    if unlearnable:
        raise ValueError(unlearnable)
    torch.set_num_threads(1)
    venv = DummyVecEnv([lambda i=i: PlanningEnv(scenario, seed=seed * 1000 + i) for i in range(envs)])
    model = without_log_dir(PPO("MlpPolicy", venv, seed=seed, verbose=0, device="cpu", **PPO_SETTINGS))
    if on_progress:  # the lab is one it can train on: the bar starts
        on_progress(0, None)
    baseline = evaluate(scenario, random_moves)
    if on_progress:
        on_progress(0, {"policy": "random moves", **baseline})
    sig = signature(list(scenario.chemistry.parameters), list(scenario.chemistry.targets[0].outputs))
    best, done, curve = None, 0, []
    while done < steps:
        chunk = min(eval_every, steps - done)
        model.learn(chunk, reset_num_timesteps=False)
        done += chunk
        result = evaluate(scenario, lambda o, _: model.predict(o, deterministic=False)[0])
        curve.append({"steps": done, **result})
        if best is None or (result["success"], -result["experiments"]) >= (best["success"], -best["experiments"]):
            best = {"steps": done, **result}
            save_policy(model, out, "planner", scenario, sig, steps=done, baseline=baseline, curve=curve)
        if on_progress:
            on_progress(done, {"policy": "ppo", **result})
    return out.with_suffix(".zip")
