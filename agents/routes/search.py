"""Retrosynthesis search over an AND/OR tree: a molecule is solved when it is in stock or one of its reactions
is; a reaction is solved when all its reactants are.

``breadth_first`` expands molecules in order of depth, so the first route it solves is a shortest one (fewest
reactions on the longest branch). Expansions (one molecule: every template applied backwards) are cached per
search and counted against a budget of expansions and of wall time.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

from agents.routes.stock import Stock
from agents.routes.templates import Template, canonical, retro


@dataclass(frozen=True)
class Reaction:
    template: Template
    product: str
    reactants: tuple[str, ...]


@dataclass
class Route:
    """A solved tree: for each molecule made, the reaction that makes it (stock molecules have none)."""

    target: str
    made_by: dict[str, Reaction]
    stock: Stock

    @property
    def steps(self) -> int:
        return len(self.made_by)

    @property
    def depth(self) -> int:
        def depth(m: str) -> int:
            r = self.made_by.get(m)
            return 0 if r is None else 1 + max(depth(x) for x in r.reactants)
        return depth(self.target)

    def order(self) -> list[Reaction]:
        """The reactions in an order the lab can run them (every reactant made before it is used)."""
        out: list[Reaction] = []

        def visit(m: str) -> None:
            r = self.made_by.get(m)
            if r is not None and r not in out:
                for x in r.reactants:
                    visit(x)
                out.append(r)
        visit(self.target)
        return out

    def bought(self) -> list[str]:
        used = {x for r in self.made_by.values() for x in r.reactants} | {self.target}
        return sorted(m for m in used if m not in self.made_by)


@dataclass
class Result:
    target: str
    route: Route | None
    expansions: int
    seconds: float
    why: str = ""  # when there is no route: what stopped the search
    routes: list[Route] = field(default_factory=list)


class Expander:
    """A molecule's reactions (every template backwards), computed once per molecule; ``count`` is the molecules
    this search expanded. ``avoid`` holds (template name, product) pairs never to propose (reactions that
    failed in the lab); ``shared``, a dict kept across searches of the same templates, saves recomputing a
    molecule another search expanded (it still counts as this search's expansion)."""

    def __init__(self, templates: tuple[Template, ...], avoid: frozenset[tuple[str, str]] = frozenset(),
                 shared: dict[str, list[Reaction]] | None = None) -> None:
        self.templates, self.avoid, self.count = templates, avoid, 0
        self.cache: dict[str, list[Reaction]] = {}
        self.shared = shared if shared is not None else {}

    def __call__(self, molecule: str) -> list[Reaction]:
        if molecule not in self.cache:
            self.count += 1
            if molecule not in self.shared:
                self.shared[molecule] = [Reaction(t, molecule, r) for t in self.templates for r in retro(t, molecule)]
            self.cache[molecule] = [r for r in self.shared[molecule] if (r.template.name, molecule) not in self.avoid]
        return self.cache[molecule]


def start(target: str, stock: Stock) -> tuple[str, Result | None]:
    """The target's canonical SMILES, and the search's answer already if it is in stock."""
    smiles = canonical(target)
    if smiles is None:
        raise ValueError(f"not a valid SMILES: {target!r}")
    return smiles, (Result(smiles, Route(smiles, {}, stock), 0, 0.0, "the target is in stock") if smiles in stock
                    else None)


class Budget:
    """A search's budget in expansions and wall seconds; ``spent()`` says which ran out ("" while neither)."""

    def __init__(self, expand: Expander, max_expansions: int, max_seconds: float) -> None:
        self.expand, self.max_expansions, self.max_seconds = expand, max_expansions, max_seconds
        self.t0 = time.perf_counter()

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.t0

    def spent(self) -> str:
        if self.expand.count >= self.max_expansions:
            return f"stopped after {self.max_expansions} expansions"
        if self.seconds > self.max_seconds:
            return f"stopped after {self.max_seconds:g} s"
        return ""


def breadth_first(target: str, templates: tuple[Template, ...], stock: Stock, max_depth: int = 6,
                  max_expansions: int = 2000, max_seconds: float = 10.0,
                  avoid: frozenset[tuple[str, str]] = frozenset()) -> Result:
    """The shortest route to ``target`` (fewest reactions on its longest branch), by expanding molecules in order
    of depth; ``Result.why`` says what stopped it when there is none."""
    smiles, done = start(target, stock)
    if done:
        return done
    expand = Expander(templates, avoid)
    budget = Budget(expand, max_expansions, max_seconds)
    depth_of = {smiles: 0}
    queue = deque([smiles])
    why = f"no route within {max_depth} steps from this stock and these templates"
    while queue:
        if budget.spent():
            why = budget.spent()
            break
        m = queue.popleft()
        if depth_of[m] >= max_depth:
            continue
        for reaction in expand(m):
            for x in reaction.reactants:
                if x not in depth_of and x not in stock:
                    depth_of[x] = depth_of[m] + 1
                    queue.append(x)
        route = _solve(smiles, expand.cache, stock)
        if route is not None:
            return Result(smiles, route, expand.count, budget.seconds)
    return Result(smiles, None, expand.count, budget.seconds, why)


def _solve(target: str, reactions: dict[str, list[Reaction]], stock: Stock) -> Route | None:
    """The best solved tree in what has been expanded: per molecule, the reaction whose deepest reactant is
    shallowest (then the fewest reactions), by fixed-point iteration over the expanded molecules."""
    best: dict[str, tuple[int, int, Reaction | None]] = {}  # molecule -> (depth, steps, reaction)

    def cost(m: str) -> tuple[int, int] | None:
        if m in stock:
            return (0, 0)
        b = best.get(m)
        return (b[0], b[1]) if b else None

    changed = True
    while changed:
        changed = False
        for m, options in reactions.items():
            if m in stock:
                continue
            for r in options:
                parts = [cost(x) for x in r.reactants]
                if any(p is None for p in parts):
                    continue
                c = (1 + max(p[0] for p in parts), 1 + sum(p[1] for p in parts))
                if m not in best or c < best[m][:2]:
                    best[m] = (*c, r)
                    changed = True
    if target not in best:
        return None
    made_by: dict[str, Reaction] = {}

    def take(m: str) -> None:
        if m in stock or m in made_by:
            return
        r = best[m][2]
        made_by[m] = r
        for x in r.reactants:
            take(x)
    take(target)
    return Route(target, made_by, stock)
