"""A campaign run one scheduling decision at a time, for a training environment to drive.

The lab is the real one — the campaign core, the scenario's drivers, retries
and faults — on the fast runtime, with its journal in memory. Each time the
core asks for a scheduling decision the run stops and hands the caller the
``LabView``; ``answer`` gives the assignments and runs the lab on to the next
decision point (a device freed, a step ready) or to the end of the campaign.
"""

from __future__ import annotations

import time

from twin.campaign.decisions import Assignment, LabView
from twin.runtime.lab import finish, load_drivers, make_planner, prepare
from twin.campaign.journal import NullJournal
from twin.runtime import FastCampaign
from twin.scenario import Scenario
from twin.campaign.summary import Summary


class SteppedCampaign:
    def __init__(self, scenario: Scenario) -> None:
        self.s = prepare(scenario, clock="virtual", bus="memory")
        self._wall0 = time.perf_counter()
        self._journal = NullJournal()  # a training episode's journal is never read
        self._run = FastCampaign(self.s, load_drivers(self.s), self._journal, make_planner(self.s), None,
                                 alerts=False)
        self.core = self._run.core
        self.summary: Summary | None = None
        self.view: LabView | None = None  # the decision waiting for an answer, if any
        self._next()

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

    def close(self) -> None:
        self._journal.close()

    def _next(self) -> None:
        self.view = self._run.next_decision()
        if self.view is None:
            self.summary = finish(self.core, self._journal, self._wall0, self._run.now)
