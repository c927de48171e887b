"""Targets with a known route: made by running templates forwards from the stock, so a route of known length
exists (the shortest may be shorter still). Training and held-out targets come from disjoint seed ranges."""

from __future__ import annotations

import random
from dataclasses import dataclass
from functools import lru_cache

from rdkit import Chem

from agents.routes.stock import Stock
from agents.routes.templates import Template, _mol, _products

HELD_OUT_SEED = 1_000_000  # held-out targets are drawn from seeds at or above this; training ones below
MAX_HEAVY_ATOMS = 45


@dataclass(frozen=True)
class Target:
    smiles: str
    steps: int  # the length of the route it was made by: an upper bound on the shortest
    route: tuple[tuple[str, tuple[str, ...], str], ...]  # (template name, reactants, product), in order
    seed: int


@lru_cache(maxsize=4)
def _slots(templates: tuple[Template, ...], stock: Stock) -> dict[str, list[list[str]]]:
    """Per template, per reactant slot, the stock molecules that fit it."""
    mols = {s: Chem.MolFromSmiles(s) for s in stock.items}
    out = {}
    for t in templates:
        out[t.name] = [[s for s, m in mols.items() if m.HasSubstructMatch(q)] for q in t.forward.GetReactants()]
    return out


def _fits(template: Template, slot: int, smiles: str) -> bool:
    return _mol(smiles).HasSubstructMatch(template.forward.GetReactantTemplate(slot))


def make_target(templates: tuple[Template, ...], stock: Stock, steps: int, seed: int,
                tries: int = 200) -> Target | None:
    """A molecule made from the stock by ``steps`` reactions in a chain (each uses the last one's product and
    stock), or None if ``tries`` draws found no such chain."""
    rng = random.Random(f"route-target:{seed}")
    slots = _slots(templates, stock)
    route: list[tuple[str, tuple[str, ...], str]] = []
    current: str | None = None
    seen: set[str] = set()
    for _ in range(steps):
        for _ in range(tries):
            t = rng.choice(templates)
            choices = slots[t.name]
            if current is None:
                if any(not c for c in choices):
                    continue
                reactants = [rng.choice(c) for c in choices]
            else:
                places = [i for i in range(t.arity) if _fits(t, i, current)]
                if not places:
                    continue
                place = rng.choice(places)
                if any(not c for i, c in enumerate(choices) if i != place):
                    continue
                reactants = [current if i == place else rng.choice(c) for i, c in enumerate(choices)]
            outcomes = {o[0] for o in _products(t.forward, tuple(_mol(r) for r in reactants))}
            outcomes = sorted(o for o in outcomes if o not in stock and o not in seen and o not in reactants
                              and _mol(o).GetNumHeavyAtoms() <= MAX_HEAVY_ATOMS)
            if outcomes:
                current = rng.choice(outcomes)
                seen.add(current)
                route.append((t.name, tuple(reactants), current))
                break
        else:
            return None
    return Target(current, steps, tuple(route), seed) if current else None


def target_set(templates: tuple[Template, ...], stock: Stock, count: int, depths: range = range(1, 7),
               held_out: bool = False) -> list[Target]:
    """``count`` targets, depths in turn; held-out ones from seeds training never draws."""
    out, seed = [], HELD_OUT_SEED if held_out else 0
    while len(out) < count:
        target = make_target(templates, stock, depths[len(out) % len(depths)], seed)
        seed += 1
        if target is not None and all(target.smiles != t.smiles for t in out):
            out.append(target)
    return out


#: Real drugs and intermediates the shipped stock and templates reach: (name, SMILES, steps of the shortest route).
NAMED = (
    ("aspirin", "CC(=O)Oc1ccccc1C(=O)O", 1),
    ("paracetamol", "CC(=O)Nc1ccc(O)cc1", 1),
    ("phenacetin", "CCOc1ccc(NC(C)=O)cc1", 1),
    ("benzocaine", "CCOC(=O)c1ccc(N)cc1", 1),
    ("procaine", "CCN(CC)CCOC(=O)c1ccc(N)cc1", 1),
    ("DEET", "CCN(CC)C(=O)c1cccc(C)c1", 1),
    ("methyl salicylate", "COC(=O)c1ccccc1O", 1),
    ("lidocaine", "CCN(CC)CC(=O)Nc1c(C)cccc1C", 2),
)


def held_out(count: int = 100) -> list[dict]:
    """Benchmark targets (entry point ``labtwin.route_targets``: held-out): ``count`` held-out forward-made
    targets of the shipped templates and stock, depths 1–6 in turn; ``steps`` is their known route's length."""
    from agents.routes import stock as stock_file
    from agents.routes import templates as template_file

    return [{"name": f"held-out {t.seed}", "smiles": t.smiles, "steps": t.steps}
            for t in target_set(template_file.load(), stock_file.load(), count, held_out=True)]


def named(count: int = len(NAMED)) -> list[dict]:
    """Benchmark targets (``labtwin.route_targets``: drugs): the named drugs, with their shortest routes' lengths."""
    return [{"name": n, "smiles": s, "steps": k} for n, s, k in NAMED[:count]]
