"""A route as a campaign: the planner (``campaign.planner: route``) that runs a synthesis in the lab.

It searches a route to ``molecule`` and proposes its reactions as experiments — each one react, purify, LC-MS
(the scenario's ``workflow``) — as soon as what they take is at hand: bought (the stock) or made by an earlier
reaction (an intermediate lot, whose amount and purity LC-MS measured). Reactions that do not depend on each
other run at once, as far as ``campaign.max_in_flight`` allows. Scales are worked back from the amount
wanted (the target's ``target_mg`` minimum) through each step's expected yield, with a margin.

A reaction that fails ``max_failures`` times — abandoned by the orchestrator after its retries, no product
found, or a yield under ``min_yield_pct`` — is avoided from then on: the planner searches again for an
alternative route (the intermediates made so far count as stock) and goes on with it. When no route is left it
proposes nothing and the campaign ends, with the reason in the log.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from rdkit import Chem
from rdkit.Chem import Descriptors

from agents.routes.plan import inputs, search
from agents.routes.search import Reaction, Route
from agents.routes.stock import Item, Stock
from agents.routes.templates import canonical
from twin import Outcome, Proposal

log = logging.getLogger(__name__)

DEFAULT_MG = 100.0
EQUIVALENTS = 1.2  # bought reagents are used in a slight excess
RECOVERY = 0.835  # a purification's mean recovery (devices.models.synthesis.RECOVERY)


@lru_cache(maxsize=4096)
def molar_mass(smiles: str) -> float:
    """g/mol (RDKit's average molecular weight), to turn the milligrams LC-MS reports into mmol."""
    return Descriptors.MolWt(Chem.MolFromSmiles(smiles))


@dataclass
class Lot:
    smiles: str
    mg: float  # product content LC-MS measured
    purity: float  # 0-1
    made_at_s: float

    @property
    def mmol(self) -> float:
        return self.mg / molar_mass(self.smiles)


class RoutePlanner:
    needs_parameters = False  # a reaction's parameters are the route's, not a box's

    def __init__(self, parameters: dict[str, Any], seed: int, targets: list[Any] = (), molecule: str = "",
                 method: str = "mcts", stock: str | None = None, templates: str | None = None,
                 prior: str | None = None, seconds: float = 10.0, amount_mg: float | None = None,
                 max_failures: int = 2, min_yield_pct: float = 10.0, margin: float = 1.3, **_: Any) -> None:
        target = canonical(molecule) if isinstance(molecule, str) and molecule else None
        if target is None:
            raise ValueError(f"campaign.planner_options.molecule: {molecule!r} is not a SMILES RDKit can read; "
                             "give the molecule to make, e.g. molecule: 'CC(=O)Oc1ccccc1C(=O)O'")
        self.target, self.method, self.prior, self.seconds = target, method, prior, float(seconds)
        for option, value in (("templates", templates), ("stock", stock)):
            try:  # a file that cannot be used is named with the option that named it
                inputs(**{option: value})
            except ValueError as exc:
                raise ValueError(f"campaign.planner_options.{option}: {exc}") from None
        self.templates, self.stock = inputs(stock, templates)
        self.amount_mg = float(amount_mg or _wanted_mg(targets) or DEFAULT_MG)
        self.max_failures, self.min_yield_pct, self.margin = int(max_failures), float(min_yield_pct), float(margin)
        self.seed = seed
        self.inventory: list[Lot] = []
        self.failures: Counter[tuple[str, str]] = Counter()
        self.avoid: set[tuple[str, str]] = set()
        self.route: Route | None = None
        self.routes = 0  # routes planned so far (the first, then each alternative)
        self.why_no_more = ""  # why there is no route, once there is none (the campaign's summary says it)
        self.made = False  # a batch of the target met the targets
        self._seen = 0
        self._announce = False

    # -- the planner protocol -----------------------------------------------------
    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        for outcome in history[self._seen:]:
            self._learn(outcome)
        self._seen = len(history)
        if self.made or self.why_no_more:
            return []
        if self.route is None and not self._plan():
            return []
        out = self._next(n, {p.get("product") for p in pending})
        if not out and not pending and self._plan():  # stuck (an intermediate used up): plan from what is at hand
            out = self._next(n, set())
        return out

    def _next(self, n: int, running: set[str]) -> list[Proposal]:
        out: list[Proposal] = []
        for reaction in self.route.order():
            if len(out) >= n:
                break
            if reaction.product in running or not self._needed(reaction.product, running):
                continue
            lots = self._take(reaction)
            if lots is None:
                continue
            out.append(self._proposal(reaction, lots))
            running.add(reaction.product)
        return out

    # -- what happened ---------------------------------------------------------------
    def _learn(self, o: Outcome) -> None:
        p = o.params
        if "reaction" not in p:
            return
        key = (p["template"], p["product"])
        out = o.outputs or {}
        if o.outputs is None or not out.get("identity") or float(out.get("yield_pct", 0)) < self.min_yield_pct:
            self.failures[key] += 1
            what = o.reason or ("no product found" if not out.get("identity") else
                                f"yield {out.get('yield_pct')} % < {self.min_yield_pct:g} %")
            log.warning("route %d step %s (%s) failed (%d of %d): %s", p.get("route"), p.get("step"),
                        p["template"], self.failures[key], self.max_failures, what)
            if self.failures[key] >= self.max_failures and key not in self.avoid:
                self.avoid.add(key)
                self.route = None  # search again, around it
            return
        if p.get("final"):
            self.made = self.made or o.score == 0
            return
        self.inventory.append(Lot(p["product"], float(out.get("product_mg", 0.0)),
                                  float(out.get("purity_pct", 100.0)) / 100, float(out.get("made_at_s", 0.0))))

    def _plan(self) -> bool:
        made = {lot.smiles for lot in self.inventory if lot.smiles != self.target}
        stock = Stock({**self.stock.items, **{m: Item(m, "made in the lab", 0.0) for m in made}}, self.stock.source)
        result = search(self.method, self.target, self.templates, stock, self.prior, self.seconds,
                        frozenset(self.avoid))
        if result.route is None or not result.route.made_by:
            avoiding = f" avoiding {sorted(t for t, _ in self.avoid)}" if self.avoid else ""
            self.why_no_more = f"no route to {self.target}{avoiding}: {result.why or 'in stock'}"
            log.warning("%s; the campaign ends", self.why_no_more)
            return False
        self.route, self._announce = result.route, True
        self.routes += 1
        log.info("route %d to %s: %s", self.routes, self.target,
                 "; ".join(r.template.name for r in self.route.order()))
        return True

    # -- what to run next -----------------------------------------------------------------
    def _consumer(self, molecule: str) -> Reaction | None:
        return next((r for r in self.route.made_by.values() if molecule in r.reactants), None)

    def _needed(self, molecule: str, running: set[str]) -> bool:
        """Whether a reaction making ``molecule`` should run now: the target until a batch meets the targets; an
        intermediate while what it feeds is needed, is not running, and lacks half of the amount it takes."""
        if molecule == self.target:
            return True
        consumer = self._consumer(molecule)
        if consumer is None or consumer.product in running or not self._needed(consumer.product, running):
            return False
        return self._available(molecule) < 0.5 * self._scale(consumer)

    def _available(self, molecule: str) -> float:
        return sum(lot.mmol for lot in self.inventory if lot.smiles == molecule)

    def _scale(self, reaction: Reaction) -> float:
        """mmol of the limiting reagent to make what is wanted of the reaction's product, with the margin."""
        if reaction.product == self.target:
            want = self.amount_mg / molar_mass(self.target)
        else:
            want = self._scale(self._consumer(reaction.product))
        lo, hi = reaction.template.yield_pct
        return want * self.margin / ((lo + hi) / 200 * RECOVERY)

    def _take(self, reaction: Reaction) -> list[Lot] | None:
        """The intermediate lots the reaction takes (removed from the inventory), or None if one is missing."""
        made = [x for x in reaction.reactants if x not in self.stock]
        if any(self._available(x) <= 0 for x in made):
            return None
        taken = [lot for lot in self.inventory if lot.smiles in made]
        self.inventory = [lot for lot in self.inventory if lot.smiles not in made]
        return taken

    def _proposal(self, reaction: Reaction, lots: list[Lot]) -> Proposal:
        t = reaction.template
        order = self.route.order()
        scale = self._scale(reaction)
        for x in {lot.smiles for lot in lots}:  # at most what the intermediates allow
            scale = min(scale, sum(lot.mmol for lot in lots if lot.smiles == x))
        bought = [x for x in reaction.reactants if x in self.stock]
        price = sum(scale * EQUIVALENTS * molar_mass(x) / 1000 * (self.stock.get(x).eur_per_g or 0.0) for x in bought)
        params: dict[str, Any] = {
            "reaction": ".".join(reaction.reactants) + ">>" + reaction.product, "product": reaction.product,
            "template": t.name, "class": t.reaction_class, "route": self.routes, "step": order.index(reaction) + 1,
            "steps": len(order), "scale_mmol": round(scale, 4), "yield_pct": list(t.yield_pct), "hours": list(t.hours),
            "reaction_s": 1800 * (t.hours[0] + t.hours[1]), "reagents_eur": round(price, 2),
            "lots": [{"smiles": lot.smiles, "mg": round(lot.mg, 2), "purity": round(lot.purity, 4),
                      "made_at_s": lot.made_at_s} for lot in lots],
            "final": reaction.product == self.target,
        }
        if self._announce:  # the whole route, once per route, for the viewer and the journal
            params["plan"] = [".".join(r.reactants) + ">>" + r.product for r in order]
            self._announce = False
        return Proposal(params, cost=params["reagents_eur"])


def _wanted_mg(targets: list[Any]) -> float | None:
    for t in targets or ():
        cond = getattr(t, "outputs", {}).get("target_mg")
        if cond is not None and cond.min is not None:
            return float(cond.min)
    return None
