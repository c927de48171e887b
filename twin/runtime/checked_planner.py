"""An in-process planner whose failure ends the campaign gently: a ``propose`` that raises, or answers anything
but a list of ``Proposal``, proposes nothing more; the campaign finishes the experiments already proposed, and
says why (``planner.failed`` in the journal, ``stopped`` in the summary). A plugin's bug costs the rest of the
budget, never an experiment in the lab."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from twin.campaign.decisions import Outcome, Proposal, RouteStep
from twin.campaign.events import Proposed
from twin.campaign.replay import PlannerAsk
from twin.core import held
from twin.core.errors import PLUGIN_ERRORS
from twin.core.messages import plain_value
from twin.runtime.checked_scheduler import dropped_if_awaitable, listed

log = logging.getLogger(__name__)
#: what to do about a planner whose call has held the lab long
PROPOSAL_ADVICE = ("A proposal must return: give a long search or fit a time limit of its own (on a scaled or wall "
                   "clock the lab asks the planner off its loop, and goes on without a late answer: "
                   "campaign.planner_deadline_s)")


class CheckedPlanner:
    def __init__(self, inner: Any, name: str) -> None:
        self.inner, self.name = inner, name
        self.failed = ""
        self.said_extra = False  # more proposals than asked for: said once
        self.holder = held.Holder(f"planner {name!r}", PROPOSAL_ADVICE)
        held.watch()

    def answer(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> Proposed:
        """The planner's answer for the campaign core, or why it can give none."""
        if self.failed:
            return Proposed([], self.failed)
        try:
            held.holding(self.holder, time.perf_counter())
            try:
                answer = self.inner.propose(n, history, pending)
            finally:
                held.released()
            return self._at_most(n, self._checked(answer))
        except PLUGIN_ERRORS as exc:
            return self._fail(f"planner {self.name!r} raised {exc!r}"[:300])

    def _checked(self, answer: Any) -> Proposed:
        if dropped_if_awaitable(answer):
            return self._fail(f"planner {self.name!r} answered an awaitable ({type(answer).__name__}): propose() "
                              "must answer at once, a list of Proposal(params)")
        proposals = _proposals(answer)
        if proposals is None:
            return self._fail(f"planner {self.name!r} answered {str(answer)[:80]!r}, not a list of "
                              "Proposal(params): return [twin.Proposal({name: value, ...}), ...]")
        for i, p in enumerate(proposals):
            wrong = _malformed(p)
            if wrong:
                return self._fail(f"planner {self.name!r} answered a malformed proposal (item {i}): {wrong}")
        return Proposed([_plain_values(p) for p in proposals], why="" if proposals else self._why_no_more())

    def _at_most(self, n: int, answer: Proposed) -> Proposed:
        """The first ``n`` of more proposals than were asked for, said once: a planner that answers a whole batch
        each time may think the rest are queued; it is asked again when something finishes."""
        if len(answer.proposals) <= n:
            return answer
        if not self.said_extra:
            self.said_extra = True
            log.warning("planner %r proposed %d experiments where %d were asked for: the first %d run, the rest are "
                        "dropped (it is asked again as experiments finish; said once)", self.name,
                        len(answer.proposals), n, n)
        return replace(answer, proposals=answer.proposals[:n])

    def _why_no_more(self) -> str:
        """The planner's own word on why it proposes nothing (its optional ``why_no_more``), if it is text."""
        try:
            why = getattr(self.inner, "why_no_more", "")
        except PLUGIN_ERRORS:  # a property that raises says nothing
            return ""
        return " ".join(why.split())[:300] if isinstance(why, str) else ""

    def _fail(self, reason: str) -> Proposed:
        self.failed = reason
        log.warning("%s: the campaign proposes nothing more and finishes what is in the lab", reason)
        return Proposed([], reason)


def covered(planner: Any, name: str) -> CheckedPlanner:
    """``planner`` covered, unless it is already."""
    return planner if isinstance(planner, CheckedPlanner) else CheckedPlanner(planner, name)


#: Wall seconds a resumed campaign spends asking its planner again the questions it had answered, at most
CATCH_UP_S = 30.0


def caught_up(planner: Any, name: str, asks: Sequence[PlannerAsk], history: Sequence[Outcome]) -> CheckedPlanner:
    """``planner`` (covered) asked again, in order, the questions a killed live campaign's planner had answered
    (``history``: the rebuilt core's), its answers dropped: a planner that keeps state (the fixed list's place in it,
    random's and lhs's draws, GP-BO's design and fitted kernel) goes on where it was, where a new one would propose its
    first experiments again. For ``CATCH_UP_S`` at most: GP-BO asked again 400 questions would refit for many minutes,
    and what it proposes follows from the history it is given. A virtual-time resume re-runs the whole campaign,
    planner included, and needs none of this."""
    checked = covered(planner, name)
    started = time.perf_counter()
    for i, ask in enumerate(asks):
        if time.perf_counter() - started > CATCH_UP_S:
            log.warning("planner %r was asked again %d of the %d questions it had answered before the campaign "
                        "stopped, in %g s, and not the rest: it goes on from the history it is given (a planner whose "
                        "proposals follow from it, as GP-BO's do, proposes as it would have; one that keeps a place "
                        "in a list of its own may propose an experiment again)", name, i, len(asks), CATCH_UP_S)
            break
        checked.answer(ask.n, list(history[:ask.known]), list(ask.pending))
    return checked


def _malformed(p: Proposal) -> str:
    """What is wrong with the shape of a proposal ('' if nothing): its values are the core's to judge."""
    if not isinstance(p.params, dict) or not all(isinstance(k, str) for k in p.params):
        return f"params is {str(p.params)[:60]!r}, not a mapping of parameter names to values"
    if p.route is None:
        return ""
    steps = listed(p.route)
    if steps is None:
        return f"route is {str(p.route)[:60]!r}, not a list of RouteStep(step, device_type)"
    for j, r in enumerate(steps):
        if not (isinstance(r, RouteStep) and isinstance(r.step, str) and isinstance(r.device, str)
                and isinstance(r.params, dict)):
            return f"route item {j} is {str(r)[:60]!r}, not a RouteStep(step, device_type, params={{}})"
    return ""


def _plain_values(p: Proposal) -> Proposal:
    """``p`` with numpy's (or torch's) scalars as Python numbers: a GP library's float32 was "not a number" to the
    core, and every experiment proposed so was abandoned."""
    route = None if p.route is None else tuple(replace(r, params=_plain(r.params)) for r in p.route)
    return replace(p, params=_plain(p.params), route=route, cost=_number(p.cost))


def _plain(params: dict[str, Any]) -> dict[str, Any]:
    return {k: _number(v) for k, v in params.items()}


def _number(v: Any) -> Any:
    return plain_value(v) if getattr(v, "shape", None) == () else v  # a scalar, as a message would carry it


def _proposals(answer: Any) -> list[Proposal] | None:
    items = listed(answer)
    return items if items is not None and all(isinstance(p, Proposal) for p in items) else None
