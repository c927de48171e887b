"""Train the reactor's PPO controller (`twin train SCENARIO --agent controller|controller-residual`)."""

from __future__ import annotations

import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from devices.models import catalyst, thermal
from devices.reactor_control import SIGNATURE, PolicyController, ReactorControlEnv, tracking
from twin import save_policy
from twin import Scenario

EVAL_SETPOINTS_K = (400.0, 430.0, 450.0, 480.0, 510.0)
HOLD_S, DT_S = 3600.0, 10.0
PPO_SETTINGS = dict(n_steps=720, batch_size=360, n_epochs=10, gamma=0.98, learning_rate=3e-4,
                    policy_kwargs=dict(net_arch=[64, 64]))


def reactor_gains(scenario: Scenario) -> dict[str, float]:
    """The PID gains of the scenario's reactor (the base a residual policy corrects)."""
    for spec in scenario.devices.values():
        if spec.driver == "reactor":
            o = spec.options
            return {"kp": float(o.get("kp", 6.0)), "ki": float(o.get("ki", 0.04)), "kd": float(o.get("kd", 0.0))}
    raise ValueError(f"{scenario.name} has no device type whose driver is 'reactor' (its device types: "
                     f"{', '.join(scenario.devices) or 'none'}): --agent controller trains a reactor's heater loop; "
                     "train it in a lab with one, e.g. scenarios/catalyst.yaml")


def compare(controllers: dict[str, Callable[[float], Any]], setpoints=EVAL_SETPOINTS_K,
            plant: thermal.Plant = thermal.NOMINAL) -> dict[str, dict[str, float]]:
    """Per controller, tracking metrics and the catalyst's yield/selectivity at each set-point, and their means."""
    out = {}
    for name, make in controllers.items():
        rows = {}
        for sp in setpoints:
            trace = thermal.simulate(sp, HOLD_S, DT_S, controller=make(sp), plant=plant)
            rows[sp] = {**tracking(trace, sp, DT_S), **{k: 100 * v for k, v in catalyst.run(trace, DT_S).items()}}
        rows["mean"] = {k: statistics.mean(r[k] for r in rows.values()) for k in next(iter(rows.values()))}
        out[name] = rows
    return out


def episode_return(model: Any, mode: str, gains: dict[str, float], setpoints=EVAL_SETPOINTS_K) -> float:
    env = ReactorControlEnv(mode, gains, DT_S, HOLD_S)
    total = 0.0
    for sp in setpoints:
        obs, _ = env.reset(options={"setpoint": sp})
        done = False
        while not done:
            action = model.predict(obs, deterministic=True)[0] if model else np.zeros(1, np.float32)
            obs, r, term, trunc, _ = env.step(action)
            total += r
            done = term or trunc
    return total / len(setpoints)


def train_controller(scenario: Scenario, steps: int, out: Path, seed: int = 0, envs: int = 4,
                     eval_every: int = 20_000, on_progress: Callable[[int, dict | None], None] | None = None,
                     mode: str = "pure") -> Path:
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.vec_env import DummyVecEnv

    torch.set_num_threads(1)
    gains = reactor_gains(scenario)
    if on_progress:  # the lab is one it can train on: the bar starts
        on_progress(0, None)
    venv = DummyVecEnv([lambda: ReactorControlEnv(mode, gains, DT_S, HOLD_S) for _ in range(envs)])
    venv.seed(seed)
    settings = dict(PPO_SETTINGS)
    if mode == "residual":  # start close to the PID: a unit-variance correction of ±RESIDUAL_K is mostly noise
        settings["policy_kwargs"] = {**settings["policy_kwargs"], "log_std_init": -1.5}
    model = PPO("MlpPolicy", venv, seed=seed, verbose=0, device="cpu", **settings)
    model.set_logger(Logger(folder=None, output_formats=[]))  # SB3's own makes an empty /tmp/SB3-<time> per learn()

    def measured(policy: Any, label: str) -> dict[str, Any]:
        make = (lambda sp: thermal.Pid(**gains)) if policy is None else (
            lambda sp: PolicyController(policy, sp, mode, thermal.Pid(**gains)))
        m = compare({label: make})[label]["mean"]
        return {"policy": label, "return": episode_return(policy, mode if policy else "residual", gains),
                "time to target s": m["time_to_target_s"], "overshoot K": m["overshoot_k"], "rms K": m["rms_k"]}

    if on_progress:
        on_progress(0, measured(None, "pid"))
    best, done = None, 0
    while done < steps:
        chunk = min(eval_every, steps - done)
        model.learn(chunk, reset_num_timesteps=False)
        done += chunk
        result = measured(model, f"ppo-{mode}")
        if best is None or result["return"] >= best:
            best = result["return"]
            save_policy(model, out, "controller", scenario, SIGNATURE, mode=mode, steps=done, evaluation=result)
        if on_progress:
            on_progress(done, result)
    return out.with_suffix(".zip")


def train_residual_controller(scenario: Scenario, steps: int, out: Path, **kw: Any) -> Path:
    return train_controller(scenario, steps, out, mode="residual", **kw)
