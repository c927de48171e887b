"""A campaign run one scheduling decision at a time, for a training environment to drive.

The lab is the real one — device actors, the orchestrator, retries, faults —
on the memory bus and a virtual clock, with its journal in memory. Its
scheduler is this object: each time the orchestrator asks for a decision, the
loop stops and hands the caller the ``LabView``; ``decide`` answers and runs
the lab on to the next decision point (a device freed, a step ready) or to
the end of the campaign.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

from twin.clock import LabClock
from twin.decisions import Assignment, LabView
from twin.lab import prepare, run_async
from twin.scenario import Scenario
from twin.summary import Summary

log = logging.getLogger(__name__)


class SteppedCampaign:
    def __init__(self, scenario: Scenario) -> None:
        self.s = prepare(scenario, clock="virtual", bus="memory")
        self.clock = LabClock("virtual")
        self.loop = self.clock.new_loop()
        self.orch: Any = None
        self.view: LabView | None = None  # the decision waiting for an answer, if any
        self.summary: Summary | None = None
        self._answer: asyncio.Future | None = None
        self._paused: asyncio.Future | None = None
        self._task = self.loop.create_task(
            run_async(self.s, self.clock, ":memory:", scheduler=self, on_start=self._started, handle_signals=False))
        self._task.add_done_callback(lambda _: self._pause())
        self._run()

    # -- the scheduler the orchestrator sees ---------------------------------------
    def decide(self, view: LabView) -> asyncio.Future:
        self.view = view
        self._answer = self.loop.create_future()
        self._pause()
        return self._answer

    # -- the caller's side ----------------------------------------------------------
    @property
    def done(self) -> bool:
        return self._task.done()

    def answer(self, assignments: list[Assignment]) -> None:
        """Answer the waiting decision and run the lab to the next one (or the end)."""
        if self._answer is None:
            raise RuntimeError("no decision is waiting: the campaign is over")
        answer, self._answer, self.view = self._answer, None, None
        answer.set_result(assignments)
        self._run()

    def close(self) -> None:
        if not self.loop.is_closed():
            if not self._task.done():
                self._task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    self.loop.run_until_complete(self._task)
            self.loop.close()

    @property
    def now(self) -> float:
        return self.clock.now() if not self.loop.is_closed() else 0.0

    def _started(self, orch: Any) -> None:
        self.orch = orch

    def _pause(self) -> None:
        if self._paused is not None and not self._paused.done():
            self._paused.set_result(None)

    def _run(self) -> None:
        self._paused = self.loop.create_future()
        self.loop.run_until_complete(self._paused)
        if self._task.done():
            self.summary = self._task.result()  # a campaign that failed raises here, with its own error
