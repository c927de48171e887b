"""Where vectorised environments pay off: MaskablePPO steps per second on the scheduling env.

    python bench/bench_training.py [scenarios/jobshop.yaml] [steps]

Same algorithm and settings as `twin train`; only the vectorisation differs.
Baseline: one environment in this process.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.tables import table  # noqa: E402
from agents.scheduling_env import SchedulingEnv  # noqa: E402
from agents.sb3_logging import without_log_dir  # noqa: E402
from agents.train_scheduler import PPO_SETTINGS  # noqa: E402
from twin.runtime.lab import prepare  # noqa: E402


def rate(scenario, kind: str, n: int, steps: int) -> float:
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    make = [lambda: SchedulingEnv(scenario, encoding="slots") for _ in range(n)]  # the figures in docs
    venv = DummyVecEnv(make) if kind == "dummy" else SubprocVecEnv(make, start_method="fork")
    venv.seed(0)
    model = without_log_dir(MaskablePPO("MlpPolicy", venv, seed=0, verbose=0, device="cpu", **PPO_SETTINGS))
    model.learn(PPO_SETTINGS["n_steps"] * n)  # warm up
    t = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    elapsed = time.perf_counter() - t
    venv.close()
    return steps / elapsed


def main() -> None:
    torch.set_num_threads(1)
    path = sys.argv[1] if len(sys.argv) > 1 else "scenarios/jobshop.yaml"
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 16_384
    scenario = prepare(ROOT / path)
    base = rate(scenario, "dummy", 1, steps)
    rows = [["1 env, in process (baseline)", f"{base:,.0f}", "1.00"]]
    for kind, n in (("dummy", 4), ("subproc", 2), ("subproc", 4)):
        r = rate(scenario, kind, n, steps)
        rows.append([f"{n} envs, {'in process (DummyVecEnv)' if kind == 'dummy' else 'own processes (SubprocVecEnv)'}",
                     f"{r:,.0f}", f"{r / base:.2f}"])
    table(f"MaskablePPO on labtwin/Scheduling-v0 ({scenario.name}), {steps:,} steps, 2 cores",
          ["vectorisation", "steps/s", "÷ baseline"], rows)


if __name__ == "__main__":
    main()
