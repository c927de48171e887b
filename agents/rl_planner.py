"""`rl`: a PPO policy trained in `labtwin/Planning-v0`, proposing experiments in a live campaign.

Per unmet target the planner keeps a chain, as in training: it moves from the
best experiment for that target so far, seeing where the chain's last attempt
went and what it gave. The first ``n_init`` experiments are a Latin
hypercube. While a chain's last proposal is still in the lab (an asynchronous
batch), or when the deterministic move would repeat a pending or tried point,
the planner samples the policy instead, so a batch never proposes a duplicate.
A failed synthesis leaves the chain's last attempt unanswered, and the next
move is sampled from the best point: an alternative, not a repeat.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.box import UnitBox
from agents.planners import LhsPlanner
from agents.planning_env import move, observation, signature
from twin import load_policy
from twin import Outcome, Proposal
from twin import PluginError
from twin import score

SAME = 1e-4  # two points closer than this in the unit box are the same experiment


class RlPlanner:
    plans_routes = False  # every experiment runs the workflow as written

    def __init__(self, parameters: dict[str, Any], seed: int, targets: list[Any] = (), policy: str | None = None,
                 n_init: int = 3, horizon: int = 30, **_: Any) -> None:
        if not policy:
            raise PluginError("the rl planner needs a trained policy: train one with "
                              "`twin train SCENARIO --agent planner --out P.zip`, then name it rl:P.zip (--planner, "
                              "--planners, campaign.planner) or give campaign.planner_options.policy")
        torch.set_num_threads(1)
        self.box = UnitBox(parameters)
        self.targets = list(targets)
        conditions = list(self.targets[0].outputs) if self.targets else []
        self.model = load_policy(Path(policy), "planner", signature(self.box.names, conditions))
        self.design = LhsPlanner(parameters, seed, budget=n_init)
        self.n_init, self.horizon = n_init, horizon
        self.rng = np.random.default_rng(seed)
        self._chains: dict[str, list[tuple[float, ...]]] = {t.name: [] for t in self.targets}
        self._turn = 0
        torch.manual_seed(seed)

    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        done = [h for h in history if h.outputs]
        if len(history) < self.n_init:
            return self.design.propose(n, history, pending)
        unmet = [t for t in self.targets if not any(score(h.outputs, t) == 0 for h in done)] or self.targets
        taken = [self.box.unit(p) for p in pending] + [self.box.unit(h.params) for h in history]
        results = {self._key(h.params): h for h in history}
        out = []
        for _ in range(n):
            target = unmet[self._turn % len(unmet)]
            self._turn += 1
            u = self._next(target, done, results, taken)
            taken.append(u)
            params = self.box.params(u)
            self._chains[target.name].append(self._key(params))
            out.append(Proposal(params))
        return out

    def _next(self, target: Any, done: list[Outcome], results: dict, taken: list[np.ndarray]) -> np.ndarray:
        if not done:
            return self.rng.random(self.box.dims)
        best = min(done, key=lambda h: score(h.outputs, target))
        best_point = (self.box.unit(best.params), best.outputs)
        chain = self._chains[target.name]
        last = results.get(chain[-1]) if chain else None
        answered = last is not None and last.outputs
        last_point = (self.box.unit(last.params), last.outputs) if answered else best_point
        obs = observation(self.box, target, best_point, last_point, min(len(chain) / self.horizon, 1.0))
        deterministic = answered
        for _ in range(16):
            action, _ = self.model.predict(obs, deterministic=deterministic)
            u = move(best_point[0], action)
            if all(np.max(np.abs(u - t)) > SAME for t in taken):
                return u
            deterministic = False
        return self.rng.random(self.box.dims)

    def _key(self, params: dict[str, Any]) -> tuple[float, ...]:
        return tuple(round(float(params[n]), 9) for n in self.box.names)
