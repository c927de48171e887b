"""An in-process planner whose failure ends the campaign gently: a ``propose`` that raises, or answers anything
but a list of ``Proposal``, proposes nothing more; the campaign finishes the experiments already proposed, and
says why (``planner.failed`` in the journal, ``stopped`` in the summary). A plugin's bug costs the rest of the
budget, never an experiment in the lab."""

from __future__ import annotations

import logging
from typing import Any

from twin.campaign.decisions import Outcome, Proposal
from twin.campaign.events import Proposed
from twin.runtime.checked_scheduler import listed

log = logging.getLogger(__name__)


class CheckedPlanner:
    def __init__(self, inner: Any, name: str) -> None:
        self.inner, self.name = inner, name
        self.failed = ""

    def __getattr__(self, attr: str) -> Any:  # the planner's own attributes
        return getattr(self.inner, attr)

    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        return self.answer(n, history, pending).proposals

    def answer(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> Proposed:
        """The planner's answer for the campaign core, or why it can give none."""
        if self.failed:
            return Proposed([], self.failed)
        try:
            return self.checked(self.inner.propose(n, history, pending))
        except Exception as exc:
            return self._fail(f"planner {self.name!r} raised {exc!r}"[:300])

    def checked(self, answer: Any) -> Proposed:
        """A planner's answer (from this process or a worker thread) as the core takes it."""
        proposals = _proposals(answer)
        if proposals is None:
            return self._fail(f"planner {self.name!r} answered {str(answer)[:80]!r}, not a list of "
                              "Proposal(params): return [twin.Proposal({name: value, ...}), ...]")
        return Proposed(proposals)

    def _fail(self, reason: str) -> Proposed:
        self.failed = reason
        log.warning("%s: the campaign proposes nothing more and finishes what is in the lab", reason)
        return Proposed([], reason)


def covered(planner: Any, name: str) -> CheckedPlanner:
    """``planner`` covered, unless it is already."""
    return planner if isinstance(planner, CheckedPlanner) else CheckedPlanner(planner, name)


def _proposals(answer: Any) -> list[Proposal] | None:
    items = listed(answer)
    return items if items is not None and all(isinstance(p, Proposal) for p in items) else None
