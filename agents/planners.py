"""Baseline experiment planners: random, Latin hypercube, and a fixed list."""

from __future__ import annotations

import random
from typing import Any

from twin import Outcome, Proposal, RouteStep


class RandomPlanner:
    """Uniform draws inside the parameter box: the baseline every planner must beat."""

    plans_routes = False  # every experiment runs the workflow as written

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

    needs_parameters = False  # its proposals carry their own parameters

    def __init__(self, parameters: dict[str, Any], seed: int, proposals: list[dict[str, Any]] | None = None,
                 **_: Any) -> None:
        _check_proposals(proposals)
        self._queue = [
            Proposal(
                p["params"],
                tuple(RouteStep(s["step"], s["device"], s.get("params", {})) for s in p["route"])
                if p.get("route")
                else None,
            )
            for p in proposals
        ]
        self._given, self._next = len(self._queue), 0

    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        out = self._queue[self._next:self._next + n]  # a place in the list: a resume asks again every question
        self._next += len(out)
        return out

    @property
    def why_no_more(self) -> str:
        left = self._next < len(self._queue)
        return "" if left else f"all {self._given} of campaign.planner_options.proposals were proposed"

    @property
    def known_in_advance(self) -> list[tuple[str, Proposal]]:
        """Every experiment it will propose, with the field that gives it: `twin validate` checks them before a run."""
        return [(f"campaign.planner_options.proposals.{i}", p) for i, p in enumerate(self._queue)]


def _check_proposals(proposals: Any) -> None:
    """Refuse proposals not in the form the planner reads, naming the entry and the form."""
    form = ("each proposal is {params: {name: value, ...}}, with optionally route: [{step, device, params}, ...] "
            "(the steps it runs, in order, instead of the workflow)")
    if not isinstance(proposals, list) or not proposals:
        raise ValueError(f"campaign.planner_options.proposals: the fixed planner proposes a list given there, and "
                         f"it is {'missing' if proposals is None else 'empty' if not proposals else 'not a list'}; "
                         f"{form}")
    for i, p in enumerate(proposals):
        where = f"campaign.planner_options.proposals.{i}"
        if not isinstance(p, dict) or not isinstance(p.get("params"), dict):
            keys = f" (it has {', '.join(map(str, p))}: put the parameters under params)" if isinstance(p, dict) else ""
            raise ValueError(f"{where}: {form}{keys}")
        route = p.get("route")
        if route is not None and (not isinstance(route, list) or not all(
                isinstance(st, dict) and {"step", "device"} <= set(st) for st in route)):
            raise ValueError(f"{where}.route: a list of {{step, device}} (and optionally params) for each step")


class LhsPlanner:
    """A Latin-hypercube design over the budget, proposed in order: space-filling, not adaptive."""

    plans_routes = False  # every experiment runs the workflow as written

    def __init__(self, parameters: dict[str, Any], seed: int, budget: int = 30, **_: Any) -> None:
        self._names = list(parameters)
        box = list(parameters.values())
        self._lo = [p.low for p in box]
        self._hi = [p.high for p in box]
        from scipy.stats import qmc  # here: scipy.stats takes ~1 s to import, which labs planning at random never need

        sampler = qmc.LatinHypercube(d=max(1, len(box)), seed=random.Random(f"lhs:{seed}").getrandbits(32))
        self._design = qmc.scale(sampler.random(max(1, budget)), self._lo, self._hi) if box else []
        self._next = 0

    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        rows = self._design[self._next : self._next + n]
        self._next += len(rows)
        return [Proposal({k: float(v) for k, v in zip(self._names, row)}) for row in rows]

    @property
    def why_no_more(self) -> str:
        left = len(self._design) - self._next
        return "" if left else f"its Latin-hypercube design of {len(self._design)} points (the budget) was all proposed"
