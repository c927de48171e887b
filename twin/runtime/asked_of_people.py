"""What a lab on a live clock asks of the person running it, said on its log as it asks: a step given to people
(``operator.step``), a question on a failed step (``question.asked``) and a stock to reorder (``consumable.low``),
each with the ``twin ctl`` command that answers it and the time left before the campaign goes on without it (or
the stock runs out). In virtual time the scenario's simulated operator answers, and nothing is said."""

from __future__ import annotations

import logging
from typing import Any

from twin.core.printable import shell_word
from twin.core.counts import quantity
from twin.campaign.events import ALERT_LOGGER
from twin.core.clock import LabClock
from twin.scenario import Scenario

log = logging.getLogger(ALERT_LOGGER)
where = logging.getLogger("twin.where")  # where a person reaches the lab: news, not a warning, yet said at start
where.setLevel(logging.INFO)

ASKED = frozenset({"operator.step", "question.asked", "consumable.low"})
NO_CTL = "twin ctl reaches a campaign over Zenoh, and this lab's bus is memory"


def ctl_options(s: Scenario, campaign: str | None, listening: list[str] | None = None) -> str | None:
    """The options of a ``twin ctl`` that reaches this lab (``campaign``: one of a lab's several), as far as the
    scenario knows them, or its bus (``listening``: where it listens, the ports it chose among them); None on a
    memory bus, which nothing outside the process reaches."""
    if s.bus.kind == "memory":
        return None
    where = _reached_at(s, s.bus.listen if listening is None else listening)
    return " ".join([f"--lab {s.lab}", *(["--campaign", campaign] if campaign else []),
                     f"--connect {where}" if where else "--connect ENDPOINT (a port the lab chose: give it --listen "
                     "tcp/127.0.0.1:PORT to know it)",
                     *(["--security", shell_word(s.bus.security)] if s.bus.security else [])])


def _reached_at(s: Scenario, listening: list[str]) -> str:
    """The endpoint another process reaches the lab at: its router, or where it listens with a port known; ''."""
    return next(iter([*s.bus.connect, *(e for e in listening if not e.endswith(":0"))]), "")


def say_where(s: Scenario, listening: list[str], clock: LabClock) -> None:
    """A live lab on Zenoh says once where `twin ctl` and `twin watch` reach it (the port it chose, without
    --listen)."""
    if not clock.is_virtual and s.bus.kind != "memory" and _reached_at(s, listening):
        options = ctl_options(s, None, listening)
        where.info("lab %s is on the bus: twin ctl status %s, twin watch %s", s.lab, options, options)


class AskedOfPeople:
    """A live campaign's: says what it asks of a person (``tell``) with the ``twin ctl`` that reaches it; in
    virtual time nothing (the scenario's simulated operator answers)."""

    def __init__(self, s: Scenario, clock: LabClock, campaign: str | None, listening: list[str] | None = None) -> None:
        self.ctl, self.clock = ctl_options(s, campaign, listening), clock

    def __call__(self, note: Any) -> None:
        if note.kind in ASKED and not self.clock.is_virtual:
            tell(note, self.ctl, self.clock.speed)


def tell(note: Any, ctl: str | None, speed: float) -> None:
    """Say ``note`` if it asks something of a person. ``ctl``: the ``twin ctl`` options that reach this campaign
    (None: nothing can); ``speed``: lab-s per wall second."""
    d = note.detail if isinstance(note.detail, dict) else {}
    if note.kind == "operator.step":
        again = f" (again: {str(d['again'])[:200]})" if d.get("again") else ""
        what = f" — {str(d['instructions'])[:500]}" if d.get("instructions") else ""
        done = f"Done: twin ctl confirm {note.task} {ctl}" if ctl is not None else f"Nobody can say it is done: {NO_CTL}"
        log.warning("operator.step %s: %s on %s waits for a person%s%s. %s%s", note.task, d.get("step", "a step"),
                    note.device, again, what, done, _within(d.get("deadline_s"), speed, "unconfirmed",
                                                            "it times out and is retried"))
    elif note.kind == "question.asked":
        why = "; ".join(str(d[k])[:200] for k in ("fault", "reason") if d.get(k))
        options = ", ".join(str(o) for o in d.get("options", []))
        answer = f"Answer: twin ctl answer {d.get('id')} OPTION {ctl}" if ctl is not None else \
            f"Nobody can answer: {NO_CTL}"
        log.warning("question.asked %s: %s of experiment %s failed on %s (%s): what now? Options %s. %s%s",
                    d.get("id"), d.get("step", "a step"), note.experiment, note.device, why, options, answer,
                    _within(d.get("timeout_s"), speed, "unanswered", f"{d.get('default')} applies"))
    elif note.kind == "consumable.low":
        refill = f"when it is refilled, twin ctl refill {d.get('item')} {ctl}" if ctl is not None else \
            f"nobody can say it is refilled: {NO_CTL}"
        when = _span(d.get("runs_out_in_s"), speed) if d.get("level", 0) > 0 else ""  # none left: its steps say so
        log.warning("consumable.low %s: %s left, below its reorder point (%g)%s: reorder it; %s", d.get("item"),
                    quantity(d.get("level", 0), str(d.get("unit", ""))), d.get("reorder_at", 0),
                    f"; at the rate so far it runs out in {when}" if when else "", refill)


def _within(lab_s: Any, speed: float, unheard: str, then: str) -> str:
    span = _span(lab_s, speed)
    return f"; {unheard} within {span} {then}" if span else ""


def _span(lab_s: Any, speed: float) -> str:
    """``lab_s`` lab seconds, and the wall time they take at ``speed``; '' if unknown."""
    if not isinstance(lab_s, (int, float)) or speed <= 0:
        return ""
    return f"{lab_s:,.0f} lab-s ({lab_s / speed:,.0f} s of wall time)"
