"""Monte Carlo tree search for routes, in AiZynthFinder's manner, and random search as a baseline.

A node of the tree is a partial route: the molecules still to make (not in stock) and the reactions chosen so
far. Its actions are the reactions (templates applied backwards) of its first open molecule, each with a prior
from an expansion policy — uniform when unguided, a learned one (``Prior``) otherwise. Selection is PUCT
(AlphaZero's rule); a node reached for the first time is expanded (one expansion: every template on one molecule,
cached) and valued by the share of its route's leaves already in stock; a route whose molecules are all in stock
is solved and worth 1, less 0.05 per reaction beyond the first, so shorter ones win. The search stops at its
budget (expansions, seconds), or ``extra`` iterations after the first route it solves, and returns the shortest
solved route.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from agents.routes.search import Budget, Expander, Reaction, Result, Route, start
from agents.routes.stock import Stock
from agents.routes.templates import Template

Prior = Callable[[str, Sequence[Reaction]], Sequence[float]]  # (molecule, its reactions) -> a weight each


def uniform(molecule: str, reactions: Sequence[Reaction]) -> list[float]:
    return [1.0 / len(reactions)] * len(reactions) if reactions else []


@dataclass(eq=False)
class Node:
    open: tuple[str, ...]  # molecules still to make, the next to expand first
    made_by: dict[str, Reaction]
    visits: int = 0
    value: float = 0.0
    children: list[Node] | None = None
    priors: list[float] = field(default_factory=list)

    @property
    def solved(self) -> bool:
        return not self.open


def _child(node: Node, reaction: Reaction, stock: Stock) -> Node | None:
    """The partial route with ``reaction`` making ``node``'s first open molecule (None if it goes round in a
    circle: a reactant the route is already making)."""
    if any(x in node.made_by or x == reaction.product for x in reaction.reactants):
        return None
    new = [x for x in reaction.reactants if x not in stock and x not in node.open]
    return Node(tuple(node.open[1:]) + tuple(new), {**node.made_by, reaction.product: reaction})


def _estimate(node: Node, stock: Stock) -> float:
    if node.solved:
        return 1.0 - 0.05 * max(0, len(node.made_by) - 1)
    leaves = {x for r in node.made_by.values() for x in r.reactants if x not in node.made_by}
    return 0.5 * sum(x in stock for x in leaves) / max(len(leaves), 1)


def mcts(target: str, templates: tuple[Template, ...], stock: Stock, prior: Prior = uniform, max_depth: int = 6,
         max_expansions: int = 2000, max_seconds: float = 10.0, extra: int = 50, c_puct: float = 1.4,
         seed: int = 0, avoid: frozenset[tuple[str, str]] = frozenset(), shared: dict | None = None) -> Result:
    smiles, done = start(target, stock)
    if done:
        return done
    expand, rng = Expander(templates, avoid, shared), random.Random(seed)
    budget = Budget(expand, max_expansions, max_seconds)
    root = Node((smiles,), {})
    best: Node | None = None
    after = 0
    why = f"the tree was searched to the end: no route within {max_depth} steps from this stock and these templates"
    while not budget.spent():
        if best is not None:
            after += 1
            if after > extra:
                break
        path, node = [root], root
        while node.children:  # select, among the children that are not dead ends (one at least: see below)
            total = math.sqrt(node.visits)
            live = [(c, p) for c, p in zip(node.children, node.priors) if not _dead(c)]
            scores = [(c.value / c.visits if c.visits else 0.0) + c_puct * p * total / (1 + c.visits) for c, p in live]
            top = max(scores)
            node = live[rng.choice([i for i, s in enumerate(scores) if s == top])][0]
            path.append(node)
        if node.children is None and not node.solved and len(node.made_by) < max_depth:  # expand
            reactions = expand(node.open[0])
            pairs = [(c, w) for c, w in zip((_child(node, r, stock) for r in reactions), prior(node.open[0], reactions))
                     if c is not None]
            node.children = [c for c, _ in pairs]
            weight = sum(w for _, w in pairs) or 1.0
            node.priors = [w / weight for _, w in pairs]
        value = _estimate(node, stock)
        if node.solved and (best is None or len(node.made_by) < len(best.made_by)):
            best = node
        if not node.solved and (node.children == [] or len(node.made_by) >= max_depth):
            value = 0.0  # a dead end: nothing makes its next molecule, or the route is as long as allowed
            node.children = []
        for n in path:  # back up
            n.visits += 1
            n.value += value
        # a node whose children are all dead ends is one too; the root one, and the tree is searched to the end
        # (the search went round a finished tree until its budget ran out, and said it had stopped for time)
        for parent in reversed(path[:-1]):
            if not (parent.children and all(_dead(c) for c in parent.children)):
                break
            parent.children = []
        if root.children == []:
            break
    return _result(smiles, best, stock, budget, budget.spent() or why)


def _result(smiles: str, best: Node | None, stock: Stock, budget: Budget, why: str) -> Result:
    if best is None:
        return Result(smiles, None, budget.expand.count, budget.seconds, why)
    return Result(smiles, Route(smiles, dict(best.made_by), stock), budget.expand.count, budget.seconds)


def _dead(node: Node) -> bool:
    return node.children == [] and not node.solved


def random_search(target: str, templates: tuple[Template, ...], stock: Stock, max_depth: int = 6,
                  max_expansions: int = 2000, max_seconds: float = 10.0, extra: int = 50, seed: int = 0,
                  avoid: frozenset[tuple[str, str]] = frozenset()) -> Result:
    """Random rollouts: each picks a random reaction for the next open molecule until the route is solved or
    stuck; the shortest solved route is kept (after ``extra`` more rollouts than the first solution)."""
    smiles, done = start(target, stock)
    if done:
        return done
    expand, rng = Expander(templates, avoid), random.Random(seed)
    budget = Budget(expand, max_expansions, max_seconds)
    best: Node | None = None
    after = 0
    while not budget.spent():
        if best is not None:
            after += 1
            if after > extra:
                break
        node: Node | None = Node((smiles,), {})
        while node is not None and not node.solved and len(node.made_by) < max_depth:
            options = [c for c in (_child(node, r, stock) for r in expand(node.open[0])) if c is not None]
            node = rng.choice(options) if options else None
        if node is not None and node.solved and (best is None or len(node.made_by) < len(best.made_by)):
            best = node
    return _result(smiles, best, stock, budget, budget.spent())
