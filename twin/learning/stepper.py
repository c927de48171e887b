"""A campaign run one scheduling decision at a time, for a training environment to drive.

The lab is the real one — the campaign core, the scenario's drivers, retries
and faults — on the fast runtime, with its journal in memory. Each time the
core asks for a scheduling decision the run stops and hands the caller the
``LabView``; ``answer`` gives the assignments and runs the lab on to the next
decision point (a device freed, a step ready) or to the end of the campaign.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from twin.campaign.decisions import Assignment, LabView
from twin.runtime.fast_lab import FastLab, SeatParts
from twin.runtime.lab import finish, load_drivers, make_planner, make_scheduler, prepare
from twin.campaign.journal import NullJournal
from twin.runtime import FastCampaign
from twin.runtime.shared_run import lab_summaries, lab_summary, shared_drivers
from twin.scenario import Scenario
from twin.scenario.sharing import campaign_scenarios
from twin.campaign.summary import LabSummary, Summary


class _Stepped:
    """What both steppers share: ``_run`` (a fast runtime with ``next_decision``, ``answer`` and ``now``) and
    ``_next``, which takes its next question or, at the end, makes ``summary``."""

    _run: Any
    summary: Any
    view: LabView | None

    @property
    def done(self) -> bool:
        return self.summary is not None

    @property
    def now(self) -> float:
        return self._run.now

    def answer(self, assignments: list[Assignment]) -> None:
        """Answer the waiting decision and run the lab to the next one (or the end)."""
        if self.view is None:
            raise RuntimeError("no decision is waiting: the campaign is over")
        self._run.answer(assignments)
        self._next()

    def _next(self) -> None:
        raise NotImplementedError


class SteppedCampaign(_Stepped):
    def __init__(self, scenario: Scenario) -> None:
        self.s = prepare(scenario, clock="virtual", bus="memory")
        self._wall0 = time.perf_counter()
        self._journal = NullJournal()  # a training episode's journal is never read
        self._run = FastCampaign(self.s, load_drivers(self.s), self._journal, make_planner(self.s), None,
                                 alerts=False)
        self.core = self._run.core
        self.summary: Summary | None = None
        self.view = None  # the decision waiting for an answer, if any
        self._next()

    def close(self) -> None:
        self._journal.close()

    def _next(self) -> None:
        self.view = self._run.next_decision()
        if self.view is None:
            self.summary = finish(self.core, self._journal, self._wall0, self._run.now)


class SteppedLab(_Stepped):
    """A lab of several campaigns (a scenario with ``campaigns:``) run one decision of its one scheduler at a time:
    every campaign's ready steps in one ``LabView`` (tasks ``campaign/task``, ``LabView.campaigns``), as
    ``orchestrator.lab_scheduler`` sees them, whether or not the lab file sets one; each campaign's planner as its
    file says, journals in memory. The same interface as ``SteppedCampaign``; ``summary`` is a ``LabSummary``.
    ``one_scheduler=False``: each campaign's own scheduler decides, the campaigns in turns, and the lab runs to its
    end at once (the baseline a lab's one scheduler is judged against)."""

    def __init__(self, lab: Scenario, one_scheduler: bool = True) -> None:
        self.s = prepare(lab, clock="virtual", bus="memory")
        if not self.s.campaigns:
            raise ValueError(f"{self.s.name}: a stepped lab has several campaigns (campaigns:); a lab of one is a "
                             "SteppedCampaign")
        self._wall0 = time.perf_counter()
        scenarios = campaign_scenarios(self.s, self.s.name)
        drivers, per_device = shared_drivers(scenarios)
        self._parts: dict[str, SeatParts] = {n: (NullJournal(), make_planner(cs), make_scheduler(cs))
                                             for n, cs in scenarios.items()}
        self._run = FastLab(self.s, scenarios, drivers, per_device, self._parts, alerts=False,
                            one_scheduler=one_scheduler)
        self.summary: LabSummary | None = None
        self.view = None
        self._next()

    @property
    def cores(self) -> dict[str, Any]:
        """Each campaign's core (its ledger: ``experiments``), by campaign."""
        return self._run.shared.cores

    def close(self) -> None:
        for journal, _, _ in self._parts.values():
            journal.close()

    def _next(self) -> None:
        self.view = self._run.next_decision()
        if self.view is None:
            shared = self._run.shared
            summaries = lab_summaries(shared, self._parts, self._wall0, self.now)
            self.summary = lab_summary(self.s, shared, summaries, Path("(memory)"), time.perf_counter() - self._wall0)


def stepped(scenario: Scenario) -> SteppedCampaign | SteppedLab:
    """``scenario`` one scheduling decision at a time: a lab of several campaigns by its one scheduler's questions."""
    return SteppedLab(scenario) if scenario.campaigns else SteppedCampaign(scenario)
