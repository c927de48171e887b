"""Consumables: reagents, vials and tips a lab holds and its steps use up.

The scenario's ``consumables`` section gives each item a unit, a starting level, a reorder point and what each
step type uses (a fixed amount plus amounts per experiment parameter); an item may be held by each instance of a
device type (``device``: a stock per instance, ``ITEM@INSTANCE``, used by the steps that run on it; a step goes
only to an instance with enough of its own). The core takes a step's amounts when it
dispatches the step — never more than is left, so a level is never negative — and gives them back if its device
refuses it (it never ran). A step that needs more than is left
is not dispatched: it waits (``consumable.depleted``, once per item until it is refilled, and `twin ctl pending`
lists it), the rest of the lab goes on, and ``twin ctl refill ITEM`` (or, in virtual time, the scenario's
simulated refill) brings it back. Crossing the reorder point is a ``consumable.low`` note with the level and
when, at the rate so far, the item runs out.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from twin.core.counts import quantity
from twin.campaign.events import Status, TimerKey, TimerKind
from twin.campaign.ledger import Attempt, Task

EPS = 1e-9
CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


@dataclass(slots=True)
class Stock:
    name: str  # the item's name; a stock of one instance's own: ITEM@INSTANCE
    unit: str
    full: float
    reorder_at: float
    level: float
    used: float = 0.0
    depleted: bool = False  # a step found it short: one depletion at a time, until a refill
    out_since: float | None = None  # lab time it was found short, until the refill
    out_s: float = 0.0  # lab seconds it was out before the last refill
    low: bool = False  # below the reorder point (said once per crossing)
    uses: dict[str, Any] = field(default_factory=dict)  # step type -> amount (number, or {fixed, per})
    item: str = ""  # the scenario's name of the item
    holder: str | None = None  # the instance whose own stock this is (None: the lab's)

    def out_hours(self, now: float) -> float:
        """Lab hours it has been out (found short, not yet refilled) up to ``now``."""
        return (self.out_s + (now - self.out_since if self.out_since is not None else 0.0)) / 3600


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
    """The lab's stocks: one per item, or — for an item a device type holds (``consumables.ITEM.device``) — one
    per instance of that type, named ``ITEM@INSTANCE``. ``needs`` are by item; which stock a step draws on
    depends on the instance it runs on."""

    def __init__(self, spec: dict[str, Any], instances: Callable[[str], list[str]]) -> None:
        """``instances``: a device type's instance names (``Scenario.instance_names``)."""
        self.items: dict[str, Stock] = {}
        self.holder_type: dict[str, str] = {}  # item -> the device type whose instances each hold a stock of it
        self.of: dict[str, list[str]] = {}  # item -> its stocks' names
        for name, c in spec.items():
            holders: list[str | None] = [None]
            if c.device is not None:
                self.holder_type[name] = c.device
                holders = list(instances(c.device))
            for holder in holders:
                stock = Stock(name if holder is None else f"{name}@{holder}", c.unit, c.level, c.reorder_at, c.level,
                              uses=dict(c.used_by), item=name, holder=holder)
                self.items[stock.name] = stock
                self.of.setdefault(name, []).append(stock.name)

    def __bool__(self) -> bool:
        return bool(self.items)

    @property
    def per_device(self) -> bool:
        return bool(self.holder_type)

    def needs(self, step: str, params: dict[str, Any], device_type: str | None = None) -> dict[str, float]:
        """What one ``step`` uses, by item (an item a device type holds: only when the step runs on that type)."""
        out = {}
        for item, names in self.of.items():
            holder = self.holder_type.get(item)
            if holder is not None and device_type is not None and holder != device_type:
                continue
            use = self.items[names[0]].uses.get(step)
            if use is not None:
                n = amount(use, params)
                if n > 0:
                    out[item] = n
        return out

    def stock(self, item: str, device: str) -> Stock:
        """The stock of ``item`` a step on instance ``device`` draws on."""
        return self.items[item] if item not in self.holder_type else self.items[f"{item}@{device}"]

    def short(self, needs: dict[str, float], device: str | None = None,
              barred: frozenset[str] = frozenset()) -> list[str]:
        """The stocks there is not enough of for a step with ``needs`` on instance ``device``; without a device:
        the lab's stocks short, and of an item each instance holds, the stocks of every instance the step may go
        to (not ``barred``) — only when none of them has enough (the step can run nowhere)."""
        out = []
        for item, n in needs.items():
            if item not in self.holder_type or device is not None:
                stock = self.items[item] if device is None else self.stock(item, device)
                if stock.level + EPS < n:
                    out.append(stock.name)
                continue
            names = [k for k in self.of[item] if self.items[k].holder not in barred] or self.of[item]
            if all(self.items[k].level + EPS < n for k in names):
                out += names
        return out

    def dry(self, needs: dict[str, float]) -> list[Stock]:
        """The instances' own stocks too short for ``needs`` (a step must go to another instance)."""
        return [self.items[k] for item, n in needs.items() if item in self.holder_type
                for k in self.of[item] if self.items[k].level + EPS < n]

    def take(self, needs: dict[str, float], device: str) -> list[Stock]:
        """Take ``needs`` for a step on ``device`` (all there: check ``short`` first); returns the stocks that fell
        below their reorder point."""
        crossed = []
        for item, n in needs.items():
            stock = self.stock(item, device)
            stock.level = max(0.0, stock.level - n)
            stock.used += n
            if not stock.low and stock.level < stock.reorder_at:
                stock.low = True
                crossed.append(stock)
        return crossed

    def give_back(self, needs: dict[str, float], device: str) -> list[Stock]:
        """What ``take`` took for a step on ``device`` that never ran, back in stock (never above a full stock);
        the reorder point's note is not said again for it."""
        out = []
        for item, n in needs.items():
            stock = self.stock(item, device)
            stock.level = min(stock.full, stock.level + n)
            stock.used = max(0.0, stock.used - n)
            out.append(stock)
        return out

    def refill(self, name: str, amount_: float | None, now: float) -> list[Stock]:
        """Refill stock ``name``, or every instance's stock of item ``name``, at lab time ``now``."""
        out = []
        for key in ([name] if name in self.items else self.of[name]):
            stock = self.items[key]
            stock.level = stock.full if amount_ is None else stock.level + amount_
            stock.depleted = False
            stock.out_s = stock.out_hours(now) * 3600
            stock.out_since = None
            stock.low = stock.level < stock.reorder_at
            out.append(stock)
        return out

    def known(self, name: str) -> bool:
        return name in self.items or name in self.of

    def runs_out_in_s(self, stock: Stock, elapsed_s: float) -> float | None:
        """Lab seconds until ``stock`` runs out at the rate it was used so far (None: not used yet)."""
        if stock.used <= 0 or elapsed_s <= 0:
            return None
        return round(stock.level / (stock.used / elapsed_s), 1)

    def levels(self) -> dict[str, float]:
        return {name: round(s.level, 6) for name, s in self.items.items()}


# -- the core's side -------------------------------------------------------------------
def take(core: CampaignCore, task: Task, device: str) -> dict[str, Any]:
    """Take what ``task`` uses as it is dispatched to ``device``; the dispatch note's ``used`` and ``left``, by
    stock."""
    needs = core._needs(task)
    if not needs:
        return {}
    for stock in core.stocks.take(needs, device):
        core._note("consumable.low", detail={"item": stock.name, "level": round(stock.level, 6), "unit": stock.unit,
                                             "reorder_at": stock.reorder_at,
                                             "runs_out_in_s": core.stocks.runs_out_in_s(stock, core.elapsed_s)})
    stocks = {item: core.stocks.stock(item, device) for item in needs}
    return {"used": {stocks[k].name: n for k, n in needs.items()},
            "left": {st.name: round(st.level, 6) for st in stocks.values()}}


def give_back(core: CampaignCore, att: Attempt) -> None:
    """A step its device refused ("not now", or infeasible) never ran: what its dispatch took goes back
    (``consumable.returned``), and the steps that waited for it are looked at again. A device answering "not now"
    while it warmed up had used up the campaign's vials with its answers. A refusal that says the step had begun
    (``began``: a step a stop cancelled, sent again when the campaign resumes) keeps what it used."""
    needs = core._needs(att.task)
    if not needs:
        return
    for stock, n in zip(core.stocks.give_back(needs, att.device), needs.values()):
        core._note("consumable.returned", att.task.experiment.id, att.task.id, att.n, att.device,
                   detail={"item": stock.name, "amount": round(n, 6), "level": round(stock.level, 6),
                           "unit": stock.unit})
    if core.starved:
        requeue(core)


def starve(core: CampaignCore, task: Task, short: list[str]) -> None:
    """``task`` waits for the stocks ``short`` to be refilled: the first step to find one short says so, once
    per depletion. A step that needs more than the item's starting level could never run: its experiment is
    refused as infeasible, with what it needs."""
    needs = core._needs(task)
    items = core.stocks.items
    beyond = sorted({items[k].item for k in short if needs[items[k].item] > items[k].full + EPS})
    if beyond:
        core.counts.infeasible += 1
        core.experiments[task.experiment.id].infeasible = True
        core._finish(task.experiment, Status.ABANDONED, "infeasible: " + "; ".join(
            f"step {task.step.step!r} needs {quantity(needs[n], items[core.stocks.of[n][0]].unit)} of {n}, more than "
            f"{'a ' + core.stocks.holder_type[n] if n in core.stocks.holder_type else 'the lab'} holds "
            f"(consumables.{n}.level: {items[core.stocks.of[n][0]].full:g})" for n in beyond))
        return
    core.starved[task.id] = task
    _depleted(core, task, short, needs)


def dried(core: CampaignCore, task: Task, needs: dict[str, float]) -> None:
    """``task`` is ready, and some instances' own stock of what it uses is short (it goes to another): the first
    step to find one short says so, once per depletion."""
    _depleted(core, task, [st.name for st in core.stocks.dry(needs)], needs)


def _depleted(core: CampaignCore, task: Task, short: list[str], needs: dict[str, float]) -> None:
    for name in short:
        stock = core.stocks.items[name]
        if stock.depleted:
            continue
        stock.depleted = True
        stock.out_since = core.now
        core._note("consumable.depleted", task.experiment.id, task.id,
                   detail={"item": name, "level": round(stock.level, 6), "unit": stock.unit,
                           "needed": round(needs[stock.item], 6), "stocks": len(core.stocks.of[stock.item])})
        sim = core.s.consumables[stock.item].simulate_refill
        if sim is not None and core.s.clock.mode == "virtual":
            core._timer(TimerKey(TimerKind.REFILL, name), sim.after_s)


def refill(core: CampaignCore, item: str, amount_: float | None, who: str) -> None:
    """Refill ``item`` (a stock, or every instance's stock of an item each holds); the steps that waited for it
    go back in the queue (one still short waits on, and says so)."""
    for stock in core.stocks.refill(item, amount_, core.now):
        core.cancel_timer(TimerKey(TimerKind.REFILL, stock.name))
        core._note("consumable.refilled", detail={"item": stock.name, "amount": amount_,
                                                  "level": round(stock.level, 6), "unit": stock.unit, "who": who})
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
    short = sorted({n for t in core.starved.values() for n in core.stocks.short(core._needs(t), barred=t.barred)})
    if any(core.s.consumables[core.stocks.items[n].item].simulate_refill is not None for n in short):
        return ""
    return (f"every experiment waits for a refill of {', '.join(short)}, and in virtual time nobody refills "
            f"(consumables.<item>.simulate_refill gives a simulated operator)")
