"""Experiment planners. More (LHS, GP-BO, RL) come with issue [3 of 5]."""

from __future__ import annotations

import random
from typing import Any

from twin.decisions import Outcome, Proposal, RouteStep


class RandomPlanner:
    """Uniform draws inside the parameter box: the baseline every planner must beat."""

    def __init__(self, parameters: dict[str, Any], seed: int, **_: Any) -> None:
        self._box = {name: (p.low, p.high) for name, p in parameters.items()}
        self._rng = random.Random(f"random-planner:{seed}")

    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        return [
            Proposal({name: self._rng.uniform(lo, hi) for name, (lo, hi) in self._box.items()})
            for _ in range(n)
        ]


class FixedPlanner:
    """Proposes a given list in order (a job shop's jobs, a replayed design)."""

    def __init__(self, parameters: dict[str, Any], seed: int, proposals: list[dict[str, Any]], **_: Any) -> None:
        self._queue = [
            Proposal(
                p["params"],
                tuple(RouteStep(s["step"], s["device"], s.get("params", {})) for s in p["route"])
                if p.get("route")
                else None,
            )
            for p in proposals
        ]

    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        out, self._queue = self._queue[:n], self._queue[n:]
        return out
