"""Several campaigns sharing one lab on the fast runtime: one event queue, one set of in-process devices, a seat
(journal, planner, scheduler, timers) per campaign, and the ``SharedLab`` deciding whose turn it is."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from twin.campaign.events import Ask, Decided, TimerFired, TimerKey
from twin.campaign.decisions import Assignment, LabView, Planner, Scheduler
from twin.campaign.journal import Journal
from twin.campaign.sharing import LAB, SharedLab, by_campaign
from twin.runtime.draw_later import DrawLater
from twin.runtime.fast import Progress, Seat, asyncio_tripwire
from twin.runtime.fast_device import FastDevice
from twin.runtime.queue import EventQueue, Timer
from twin.scenario import Scenario
from twin.view.lab_observer import SharedLabObserver

SeatParts = tuple[Journal, Planner, Scheduler]


class FastLab:
    def __init__(self, lab: Scenario, scenarios: dict[str, Scenario], drivers: list[tuple[str, str, Any]],
                 per_device: dict[str, dict[str, Any]], parts: dict[str, SeatParts],
                 on_progress: Callable[[str], Progress | None] | None = None,
                 observer: SharedLabObserver | None = None, lab_scheduler: Scheduler | None = None,
                 alerts: bool = True, one_scheduler: bool | None = None) -> None:
        """``scenarios``: each campaign's; ``per_device``: each instance's driver for each campaign (a simulated
        device simulates the chemistry of the campaign whose step it runs); ``parts``: each campaign's journal,
        planner and scheduler; ``observer``: handed the lab's devices' results and telemetry and each campaign's
        notes (a recording), in batches (``drawing``); ``lab_scheduler``: the one scheduler of a lab whose
        ``orchestrator.lab_scheduler`` is set (it answers the lab's questions, with every campaign's steps);
        ``alerts``: log the campaigns' alerts as warnings (a training episode's are never read);
        ``one_scheduler``: ask one scheduler (``lab_scheduler``, or the caller of ``next_decision``) whatever the
        lab file says (``SharedLab``)."""
        self.lab, self.queue, self.lab_scheduler = lab, EventQueue(), lab_scheduler
        self.shared = SharedLab(lab, scenarios, one_scheduler=one_scheduler)
        self.drawing = DrawLater()  # ``drain`` it before drawing anything else
        watch = self.drawing.hand(observer.on_envelope) if observer is not None else None
        self.devices = {name: FastDevice(name, dtype, lab.devices[dtype], drv, self.queue, lab.campaign.seed,
                                         self.shared.feed_device, watch, shared=per_device[name], warn=alerts)
                        for name, dtype, drv in sorted(drivers)}
        self.seats = {name: Seat(self.shared.cores[name], *parts[name], self.queue, self.devices,
                                 on_progress(name) if on_progress else None, alerts,
                                 draw=self.drawing.hand(observer.campaign(name).on_note) if observer is not None
                                 else None)
                      for name in scenarios}
        self._lab_timers: dict[TimerKey, Timer] = {}
        self._started = False
        self.view: LabView | None = None  # the lab's one scheduler's question, until answered

    @property
    def now(self) -> float:
        return self.queue.now

    def run(self) -> None:
        while (view := self.next_decision()) is not None:
            assert self.lab_scheduler is not None
            started = time.perf_counter()
            decided = list(self.lab_scheduler.decide(view))
            self.answer(decided, time.perf_counter() - started)

    def next_decision(self) -> LabView | None:
        """Run to the next question for the lab's one scheduler (``orchestrator.lab_scheduler``), or to the end
        (``None``); a lab without one runs to the end."""
        shared, q = self.shared, self.queue
        with asyncio_tripwire():
            if not self._started:
                self._started = True
                self._perform(shared.start(q.now))
                for dev in self.devices.values():
                    dev.start()
            while not shared.finished:
                if self.view is not None:
                    return self.view
                q.run_ready()
                if shared.has_work:
                    self._perform(shared.advance(q.now))
                elif shared.waiting is None and (stalled := shared.stalled()):
                    shared.stop(stalled)  # it would idle to the campaigns' max_lab_hours
                elif shared.waiting is None and not q.jump():
                    shared.stop("nothing left to happen")
                    if not shared.has_work:  # nothing started, nothing to stop
                        break
            for dev in self.devices.values():
                dev.stop()
        return None

    def answer(self, assignments: list[Assignment], wall_s: float = 0.0) -> None:
        """The lab's one scheduler's answer to the question ``next_decision`` returned."""
        if self.view is None:
            raise RuntimeError("no decision is waiting: the lab is over")
        self.view = None
        self.shared.feed(LAB, Decided(list(assignments), wall_s))

    def stop(self, reason: str) -> None:
        self.shared.stop(reason, outside=True)

    def _perform(self, tagged: list[tuple[str, Any]]) -> None:
        for name, actions in by_campaign(tagged):
            self._to(name, actions)

    def _to(self, name: str, actions: list[Any]) -> None:
        if name != LAB:
            self.seats[name].perform(actions)
            return
        for a in actions:  # the lab's own: submission timers, and questions to its one scheduler
            if type(a) is Ask:
                self.view = a.view  # for the lab's one scheduler: ``next_decision`` hands it out
            else:
                self._lab_timers[a.key] = self.queue.call_later(a.delay, self._fire, a.key)

    def _fire(self, key: TimerKey) -> None:
        self._lab_timers.pop(key, None)
        self.shared.feed(LAB, TimerFired(key))
