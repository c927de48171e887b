"""Consumables: reagents, vials and tips a lab holds and its steps use up.

The scenario's ``consumables`` section gives each item a unit, a starting level, a reorder point and what each
step type uses (a fixed amount plus amounts per experiment parameter). The core takes a step's amounts when it
dispatches the step — never more than is left, so a level is never negative. A step that needs more than is left
is not dispatched: it waits (``consumable.depleted``, once per item until it is refilled, and `twin ctl pending`
lists it), the rest of the lab goes on, and ``twin ctl refill ITEM`` (or, in virtual time, the scenario's
simulated refill) brings it back. Crossing the reorder point is a ``consumable.low`` note with the level and
when, at the rate so far, the item runs out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from twin.campaign.events import CancelTimer, Status, TimerKey, TimerKind
from twin.campaign.ledger import Task

EPS = 1e-9
CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


@dataclass(slots=True)
class Stock:
    name: str
    unit: str
    full: float
    reorder_at: float
    level: float
    used: float = 0.0
    depleted: bool = False  # a step waits for it: one depletion at a time, until a refill
    low: bool = False  # below the reorder point (said once per crossing)
    uses: dict[str, Any] = field(default_factory=dict)  # step type -> amount (number, or {fixed, per})


def amount(use: Any, params: dict[str, Any]) -> float:
    """How much one step uses: a number, or ``fixed`` plus ``per`` parameter × its value (never below 0)."""
    if isinstance(use, (int, float)):
        return max(0.0, float(use))
    total = float(use.fixed)
    for name, coef in use.per.items():
        value = params.get(name)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            total += coef * float(value)
    return max(0.0, total)


class Stocks:
    def __init__(self, spec: dict[str, Any]) -> None:
        self.items = {name: Stock(name, c.unit, c.level, c.reorder_at, c.level, uses=dict(c.used_by))
                      for name, c in spec.items()}

    def __bool__(self) -> bool:
        return bool(self.items)

    def needs(self, step: str, params: dict[str, Any]) -> dict[str, float]:
        out = {}
        for stock in self.items.values():
            use = stock.uses.get(step)
            if use is not None:
                n = amount(use, params)
                if n > 0:
                    out[stock.name] = n
        return out

    def short(self, needs: dict[str, float]) -> list[str]:
        """The items of ``needs`` there is not enough of."""
        return [name for name, n in needs.items() if self.items[name].level + EPS < n]

    def take(self, needs: dict[str, float]) -> list[Stock]:
        """Take ``needs`` (all there: check ``short`` first); returns the items that fell below their reorder point."""
        crossed = []
        for name, n in needs.items():
            stock = self.items[name]
            stock.level = max(0.0, stock.level - n)
            stock.used += n
            if not stock.low and stock.level < stock.reorder_at:
                stock.low = True
                crossed.append(stock)
        return crossed

    def refill(self, name: str, amount_: float | None) -> Stock:
        stock = self.items[name]
        stock.level = stock.full if amount_ is None else stock.level + amount_
        stock.depleted = False
        stock.low = stock.level < stock.reorder_at
        return stock

    def runs_out_in_s(self, stock: Stock, elapsed_s: float) -> float | None:
        """Lab seconds until ``stock`` runs out at the rate it was used so far (None: not used yet)."""
        if stock.used <= 0 or elapsed_s <= 0:
            return None
        return round(stock.level / (stock.used / elapsed_s), 1)

    def levels(self) -> dict[str, float]:
        return {name: round(s.level, 6) for name, s in self.items.items()}


# -- the core's side -------------------------------------------------------------------
def take(core: CampaignCore, task: Task) -> dict[str, Any]:
    """Take what ``task`` uses as it is dispatched; the dispatch note's ``used`` and ``left``."""
    needs = core._needs(task)
    if not needs:
        return {}
    for stock in core.stocks.take(needs):
        core._note("consumable.low", detail={"item": stock.name, "level": round(stock.level, 6), "unit": stock.unit,
                                             "reorder_at": stock.reorder_at,
                                             "runs_out_in_s": core.stocks.runs_out_in_s(stock, core.elapsed_s)})
    return {"used": needs, "left": {k: round(core.stocks.items[k].level, 6) for k in needs}}


def starve(core: CampaignCore, task: Task, short: list[str]) -> None:
    """``task`` waits for ``short`` to be refilled: the first step to find an item short says so, once per
    depletion. A step that needs more than the item's starting level could never run: its experiment is refused
    as infeasible, with what it needs."""
    needs = core._needs(task)
    beyond = [n for n in short if needs[n] > core.stocks.items[n].full + EPS]
    if beyond:
        core.counts.infeasible += 1
        core.experiments[task.experiment.id].infeasible = True
        core._finish(task.experiment, Status.ABANDONED, "infeasible: " + "; ".join(
            f"step {task.step.step!r} needs {needs[n]:g} {core.stocks.items[n].unit} of {n}, more than the lab "
            f"holds (consumables.{n}.level: {core.stocks.items[n].full:g})" for n in beyond))
        return
    core.starved[task.id] = task
    for name in short:
        stock = core.stocks.items[name]
        if stock.depleted:
            continue
        stock.depleted = True
        core._note("consumable.depleted", task.experiment.id, task.id,
                   detail={"item": name, "level": round(stock.level, 6), "unit": stock.unit,
                           "needed": round(needs[name], 6)})
        sim = core.s.consumables[name].simulate_refill
        if sim is not None and core.s.clock.mode == "virtual":
            core._timer(TimerKey(TimerKind.REFILL, name), sim.after_s)


def refill(core: CampaignCore, item: str, amount_: float | None, who: str) -> None:
    """Refill ``item``; the steps that waited for it go back in the queue (one still short waits on, and says so)."""
    stock = core.stocks.refill(item, amount_)
    core._out.append(CancelTimer(TimerKey(TimerKind.REFILL, item)))
    core._note("consumable.refilled", detail={"item": item, "amount": amount_, "level": round(stock.level, 6),
                                              "unit": stock.unit, "who": who})
    requeue(core)


def requeue(core: CampaignCore) -> None:
    """The steps that waited for a consumable go back in the queue (after a refill, here or by another campaign
    of a shared lab)."""
    waiting, core.starved = list(core.starved.values()), {}
    for task in waiting:
        if task.experiment.id in core.active:
            core._make_ready(task.experiment, task)  # starved again, with a new note, if still short
    core._wake = True


def stalled(core: CampaignCore) -> str:
    """In virtual time, why nothing can happen any more but a refill nobody will make ('' if something can):
    every experiment in the lab waits for a consumable, and no simulated refill is due."""
    if core.s.clock.mode != "virtual" or core.ready or core._retrying or core.questions:
        return ""
    if any(d.attempt is not None or d.cancelling is not None for d in core.devices.values()):
        return ""
    waiting = {t.experiment.id for t in core.starved.values()}
    if any(e not in waiting for e in core.active):
        return ""
    short = sorted({n for t in core.starved.values() for n in core.stocks.short(core._needs(t))})
    if any(core.s.consumables[n].simulate_refill is not None for n in short):
        return ""
    return (f"every experiment waits for a refill of {', '.join(short)}, and in virtual time nobody refills "
            f"(consumables.<item>.simulate_refill gives a simulated operator)")
