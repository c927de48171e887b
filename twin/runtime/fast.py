"""The fast runtime: the campaign core, in-process devices and one event queue, in virtual time.

No asyncio, no bus, no validation on the hot path: a device's message is an
object handed to the core. The core advances at each idle point of the
queue (everything of the current instant has happened), as the asyncio
runtime does in virtual time, so both write the same journal.

``run()`` drives a campaign to its end. With ``scheduler=None`` the caller
is the scheduler: ``next_decision()`` runs to the next decision and returns
its ``LabView`` (``None`` at the end), ``answer()`` gives the assignments.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from typing import Any

from twin.campaign import (Ask, CampaignCore, CancelTimer, Decided, Finished, Note, RecordExperiment,
                           RecordMessage, Send, SetTimer, Stop, TimerFired)
from twin.campaign.events import ALERTS, PROGRESS_KINDS, TimerKey
from twin.campaign.decisions import Assignment, LabView, Planner, Scheduler
from twin.core.errors import ClockError
from twin.campaign.journal import Journal
from twin.core.messages import Kind
from twin.runtime.alert_log import AlertLog
from twin.runtime.checked_planner import covered
from twin.runtime.checked_scheduler import fallbacks
from twin.runtime.draw_later import DrawLater
from twin.runtime.fast_device import FastDevice
from twin.runtime.queue import EventQueue, Timer
from twin.scenario import Scenario
from twin.view.observer import UNDRAWN

log = logging.getLogger(__name__)
Progress = Callable[[CampaignCore], None]


class Seat:
    """One campaign's side of the fast runtime: its core's actions go to its journal, planner, scheduler and
    timers, and its commands to the lab's devices."""

    def __init__(self, core: CampaignCore, journal: Journal, planner: Planner, scheduler: Scheduler | None,
                 queue: EventQueue, devices: dict[str, FastDevice], on_progress: Progress | None = None,
                 alerts: bool = True, draw: Callable[[Note], None] | None = None) -> None:
        """``draw``: given the notes an observer draws (``UNDRAWN`` kept back)."""
        self.core, self.journal, self.scheduler = core, journal, scheduler
        self.planner = covered(planner, core.s.campaign.planner)
        self.queue, self.devices, self.on_progress, self.draw = queue, devices, on_progress, draw
        self.alerts = ALERTS if alerts else frozenset()
        self.alert_log = AlertLog()
        self.timers: dict[TimerKey, Timer] = {}
        self.view: LabView | None = None  # a decision the caller of next_decision() is to make
        for rule in fallbacks(scheduler):  # a scheduler's mistakes covered: journalled when the reason changes
            rule.on_fallback = self._fell_back
            rule.on_recovered = self._recovered

    def _fell_back(self, reason: str) -> None:
        self.journal.event(self.queue.now, "scheduler.fallback", detail=reason)

    def _recovered(self, message: str) -> None:
        self.journal.event(self.queue.now, "scheduler.recovered", detail=message)

    def perform(self, actions: list[Any]) -> None:
        journal, progressed, watched = self.journal, False, self.on_progress is not None
        note, received, draw = journal.note, journal.received, self.draw
        for a in actions:
            t = type(a)
            if t is Note:
                note(a)
                if draw is not None and a.kind not in UNDRAWN:
                    draw(a)
                if a.kind in self.alerts:
                    self.alert_log(a)
                if watched and not progressed:
                    progressed = a.kind.startswith(PROGRESS_KINDS)
            elif t is RecordMessage:
                received(a)
            elif t is Send:
                dev = self.devices.get(a.device)
                if dev is not None:
                    if a.kind == Kind.COMMAND:
                        dev.command(a.task, a.attempt, self.core.campaign_id, a.body, a.token)
                    else:
                        dev.cancel(a.task, a.attempt, a.token)
            elif t is SetTimer:
                old = self.timers.pop(a.key, None)
                if old is not None:
                    old.cancel()
                self.timers[a.key] = self.queue.call_later(a.delay, self._fire, a.key)
            elif t is CancelTimer:
                handle = self.timers.pop(a.key, None)
                if handle is not None:
                    handle.cancel()
            elif t is RecordExperiment:
                journal.experiment(a.experiment)
            elif t is Ask:
                self._answer(a)
            elif t is Finished:
                for handle in self.timers.values():
                    handle.cancel()
                self.timers.clear()
        if progressed and self.on_progress is not None:
            self.on_progress(self.core)

    def _fire(self, key: TimerKey) -> None:
        self.timers.pop(key, None)
        self.core.feed(TimerFired(key))

    def _answer(self, ask: Ask) -> None:
        if ask.what == "plan":
            self.core.feed(self.planner.answer(ask.n, list(ask.history), list(ask.pending)))
        elif self.scheduler is None:
            self.view = ask.view
        else:
            started = time.perf_counter()
            decided = self.scheduler.decide(ask.view)  # covered (CheckedScheduler): a list of assignments
            self.core.feed(Decided(list(decided), time.perf_counter() - started))


class FastCampaign:
    def __init__(self, scenario: Scenario, drivers: list[tuple[str, str, Any]], journal: Journal,
                 planner: Planner, scheduler: Scheduler | None, campaign_id: str = "c1",
                 on_progress: Progress | None = None, alerts: bool = True, observer: Any = None) -> None:
        """``alerts``: log the campaign's alerts (a device type gone, say) as warnings; a training run's
        thousands of campaigns keep them in their journals only. ``observer``: a ``LabObserver`` in this
        process, handed the core's notes and the devices' results and telemetry (no bus, no second parse), in
        batches (``drawing``: ``drain`` it before drawing anything else)."""
        self.s, self.journal, self.planner, self.scheduler = scenario, journal, planner, scheduler
        self.queue = EventQueue()
        self.core = CampaignCore(scenario, campaign_id)
        self.drawing = DrawLater()
        watch = self.drawing.hand(observer.on_envelope) if observer is not None else None
        self.devices = {name: FastDevice(name, dtype, scenario.devices[dtype], drv, self.queue,
                                         scenario.campaign.seed, self.core.feed, watch, warn=alerts)
                        for name, dtype, drv in drivers}
        self.seat = Seat(self.core, journal, planner, scheduler, self.queue, self.devices, on_progress, alerts,
                         self.drawing.hand(observer.on_note) if observer is not None else None)
        self._started = False

    # -- driving ----------------------------------------------------------------------
    def run(self) -> None:
        if self.scheduler is None:
            raise ClockError("FastCampaign.run() needs a scheduler; without one, use next_decision()/answer()")
        self.next_decision()  # a scheduler answers every decision inside, so this runs to the end

    def next_decision(self) -> LabView | None:
        """Run to the next scheduling decision the caller must make, or to the end (``None``)."""
        with asyncio_tripwire():
            if not self._started:
                self._start()
            core, q, seat = self.core, self.queue, self.seat
            while not core.finished:
                if seat.view is not None:
                    return seat.view
                q.run_ready()
                if core.has_work:
                    seat.perform(core.advance(q.now))
                elif core.waiting is None and not q.jump():
                    core.feed(Stop("nothing left to happen"))
            self._stop_devices()
        return None

    def answer(self, assignments: list[Assignment]) -> None:
        if self.seat.view is None:
            raise RuntimeError("no decision is waiting: the campaign is over")
        self.seat.view = None
        self.core.feed(Decided(list(assignments)))

    def stop(self, reason: str) -> None:
        self.core.feed(Stop(reason, outside=True))

    @property
    def now(self) -> float:
        return self.queue.now

    def _start(self) -> None:
        self._started = True
        self.seat.perform(self.core.start(self.queue.now))
        for dev in self.devices.values():
            dev.start()

    def _stop_devices(self) -> None:
        for dev in self.devices.values():
            dev.stop()


_TRIPWIRE: asyncio.AbstractEventLoop | None = None


@contextlib.contextmanager
def asyncio_tripwire() -> Iterator[None]:
    """A driver that awaits asyncio (an Event, asyncio.sleep) finds a loop that never runs: what it
    awaits is yielded to the fast runtime, which names the driver, instead of failing obscurely."""
    global _TRIPWIRE
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        pass
    else:
        yield  # called from a running loop: asyncio futures already reach the driver loop
        return
    if _TRIPWIRE is None:
        _TRIPWIRE = asyncio.new_event_loop()
        atexit.register(_TRIPWIRE.close)  # one per process, kept: closed at exit, not left to a ResourceWarning
    asyncio._set_running_loop(_TRIPWIRE)
    try:
        yield
    finally:
        asyncio._set_running_loop(None)
