"""An in-process scheduler whose mistakes the fallback rule covers, as it covers an agent's on the bus.

A ``decide`` that raises, answers something other than a list of ``Assignment(task, device)``, or answers pairs of
which none can be carried out (a step that is not ready, a device that is not free or not of the step's type), is
decided that time by ``campaign.fallback_scheduler``; the reason is noted once per change (``scheduler.fallback``) and
the summary counts the decisions it made. The campaign goes on: a plugin's bug costs decisions, not samples.
"""

from __future__ import annotations

import inspect
import time
from typing import Any

from twin.campaign.decisions import Assignment, LabView, unfit
from twin.core import held
from twin.core.errors import PLUGIN_ERRORS
from twin.runtime.remote_scheduler import Fallback


#: what to do about a scheduler whose decision has held the lab long
DECISION_ADVICE = ("A decision must return: give a long search a time limit of its own, or run the scheduler as an "
                   "agent (`twin scheduler serve`), for which the lab does not wait")


class CheckedScheduler:
    def __init__(self, inner: Any, fallback: Fallback, name: str) -> None:
        self.inner, self.fallback, self.name = inner, fallback, name
        self.holder = held.Holder(f"scheduler {name!r}", DECISION_ADVICE)
        held.watch()

    def __getattr__(self, attr: str) -> Any:  # the scheduler's own attributes (serve_on_bus, its policy, ...)
        return getattr(self.inner, attr)

    def decide(self, view: LabView) -> list[Assignment]:
        try:
            held.holding(self.holder, time.perf_counter())
            decided = self.inner.decide(view)
            awaited = dropped_if_awaitable(decided)
            items = None if awaited else assignments(decided)  # a generator's code runs here: covered too
        except PLUGIN_ERRORS as exc:
            return self.fallback.decide(view, "raised", f"scheduler {self.name!r} raised {exc!r}"[:300])
        finally:
            held.released()
        if items is None:
            answered = f"an awaitable ({type(decided).__name__}): decide() must answer at once" if awaited else \
                f"{str(decided)[:80]!r}"
            return self.fallback.decide(view, "invalid", f"scheduler {self.name!r} answered {answered}, not a list of "
                                                         "Assignment(task, device)")
        why = impossible(view, items)
        if why:
            return self.fallback.decide(view, "impossible", f"scheduler {self.name!r} answered nothing that can "
                                                            f"run ({why})")
        self.fallback.recovered(f"scheduler {self.name!r} decides again")
        return items


def impossible(view: LabView, items: list[Assignment]) -> str:
    """Why none of ``items`` can be carried out on ``view`` (the first pair's reason), or '' if one can or there
    are none (a wait). Only what the view settles: the orchestrator checks the rest (an operator's bar, a stock)
    and journals each pair it refuses as ``scheduler.invalid``."""
    first = ""
    for a in items:  # a scan, not dicts: on every decision, and the first pair is nearly always sound
        why = unfit(a, next((r for r in view.ready if r.task == a.task), None),
                    next((f for f in view.free if f.name == a.device), None))
        if not why:
            return ""
        first = first or why
    return first


def assignments(decided: Any) -> list[Assignment] | None:
    """``decided`` as a list of ``Assignment``, or None if it is not a collection of (task, device) pairs of
    names (objects with string ``task`` and ``device``)."""
    items = listed(decided)
    if items is None:
        return None
    out = []
    for a in items:
        task, device = getattr(a, "task", None), getattr(a, "device", None)
        if not isinstance(task, str) or not isinstance(device, str):  # numpy's str_ is a str
            return None
        out.append(a if type(a) is Assignment and type(task) is type(device) is str else Assignment(str(task), str(device)))
    return out


def dropped_if_awaitable(answer: Any) -> bool:
    """Whether a plugin's answer is an awaitable (a coroutine) where one is wanted at once: closed if so, as it
    will never be awaited (no "never awaited" warning at exit)."""
    if not inspect.isawaitable(answer):
        return False
    getattr(answer, "close", lambda: None)()
    return True


def listed(answer: Any) -> list[Any] | None:
    """A plugin's answer as a list, or None if it is not a collection of items (None, a string, a mapping)."""
    if answer is None or isinstance(answer, (str, bytes, dict)):
        return None
    try:
        return list(answer)
    except TypeError:
        return None


def fallbacks(scheduler: Any) -> list[Fallback]:
    """The fallback rules in a chain of wrappers (covered, off the loop, on the bus), outermost first: whose
    decisions a campaign counts and whose changes it journals."""
    out = []
    while scheduler is not None and hasattr(scheduler, "__dict__"):
        own = vars(scheduler)  # not getattr: a covered scheduler hands unknown attributes to the one it covers
        if isinstance(own.get("fallback"), Fallback):
            out.append(own["fallback"])
        scheduler = own.get("inner")
    return out
