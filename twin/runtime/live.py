"""The asyncio runtime: the campaign core driven over a bus, on any clock.

Device messages, presence and the core's timers become events; the core's
actions become bus messages, loop timers, planner and scheduler calls and
journal rows. In virtual time the core advances only when the loop is idle
(everything of the current instant has happened), exactly as the fast
runtime does, so both write the same journal; on a scaled or wall clock it
advances as soon as an event arrives.
"""

from __future__ import annotations

import asyncio
import functools
import hashlib
import itertools
import logging
from collections.abc import Callable
from typing import Any

from twin.core import keys
from twin.core.bus import Bus
from twin.campaign import (Ask, CampaignCore, CancelTimer, Decided, Finished, Note, Presence, Proposed,
                           RecordExperiment, RecordMessage, Send, SetTimer, Stop, TimerFired)
from twin.campaign import human, replay
from twin.campaign.events import ALERTS, PRESENCE, PROGRESS_KINDS, TimerKey
from twin.campaign.replay import RESUMED, Rebuilt
from twin.core.clock import LabClock, LabEventLoop, sleep_wall
from twin.campaign.decisions import Planner, Scheduler
from twin.campaign.journal import Journal
from twin.core.errors import BusError, TwinError
from twin.core.messages import Kind, json_from_wire, pack
from twin.runtime.alert_log import AlertLog
from twin.runtime.asked_of_people import AskedOfPeople
from twin.runtime.asking import ask_scheduler
from twin.runtime.checked_planner import covered
from twin.runtime.checked_scheduler import fallbacks
from twin.runtime.control import ControlDesk
from twin.runtime.decision_stream import SENDER, DecisionStream
from twin.runtime.event_decoder import EventDecoder
from twin.runtime.take_over import rearm, reported
from twin.view.observer import UNDRAWN
from twin.scenario import Scenario

log = logging.getLogger(__name__)

Progress = Callable[[CampaignCore], None]
PROGRESS_TICK_S = 1.0  # wall seconds: a live campaign's progress is said this often, events or none


def lab_elapsed(core: CampaignCore) -> float:
    """The lab time ``core``'s campaign has run: on a live clock up to now, read on the lab's loop (a progress call
    made there); the core's own ``elapsed_s`` is that of its last event, hours old during a long step."""
    try:
        loop = asyncio.get_running_loop()
    except RuntimeError:  # the fast runtime's, or no loop: the core's time is the lab's
        return core.elapsed_s
    return max(core.elapsed_s, loop.time() - core.t0) if isinstance(loop, LabEventLoop) else core.elapsed_s


class LiveCampaign:
    """One campaign of ``scenario`` on ``bus`` and ``clock``; ``await run()`` drives it to its end."""

    def __init__(self, scenario: Scenario, bus: Bus, clock: LabClock, journal: Journal, planner: Planner,
                 scheduler: Scheduler, campaign_id: str = "c1", on_progress: Progress | None = None,
                 rebuilt: Rebuilt | None = None, observer: Any = None, core: CampaignCore | None = None) -> None:
        """``rebuilt``: the core of a killed live campaign, rebuilt from its journal (``twin resume``). ``core``:
        one made elsewhere (a campaign of a shared lab, which the lab drives: its inputs are not journalled).
        ``observer``: a ``LabObserver`` in this process, handed the core's notes and the devices' results and
        telemetry as the campaign accepts them, decoded once here (not a second subscription that parses them again)."""
        self.observer = observer
        try:
            self._loop: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:  # made outside a loop (a test's core): notes are taken where they are made
            self._loop = None
        self.s, self.bus, self.clock, self.journal = scenario, bus, clock, journal
        self.planner = covered(planner, scenario.campaign.planner)
        self.scheduler, self.on_progress = scheduler, on_progress
        self.alert_log = AlertLog(virtual=clock.is_virtual, crashing={
            name: (dtype, spec.faults.restart_s) for dtype, spec in scenario.devices.items() if spec.faults.mtbc_h > 0
            for name in scenario.instance_names(dtype)}, people=frozenset(human.people(scenario)))
        for rule in fallbacks(scheduler):  # a scheduler's mistakes covered: journalled when the reason changes
            rule.on_fallback = lambda reason: self._note_from_any_thread("scheduler.fallback", reason)
            rule.on_recovered = lambda message: self._note_from_any_thread("scheduler.recovered", message)
        self.core = rebuilt.core if rebuilt is not None else core or CampaignCore(scenario, campaign_id)
        self._rebuilt = rebuilt
        self._rejected = self.core.counts.rejected  # messages rejected, as the notes said so far
        # a live campaign journals its core's inputs, so that a killed one can be rebuilt (virtual time re-runs)
        self._recording = not clock.is_virtual and core is None
        self._decoder = EventDecoder(observer, clock, lambda detail: self.note("device.clock_off", detail))
        self._shown: dict[bytes, dict[str, Any]] = {}  # of the messages the core handles now, what to draw
        self._fed: list[Any] = []
        self.decisions = DecisionStream(journal, bus, clock, scenario.lab, campaign_id)
        # named by its attempt secret, which its resumes keep, through a one-way hash that gives none of it away
        self.decisions.run = hashlib.sha256(self.core.secret).hexdigest()[:16]
        self.desk = ControlDesk(self.core, clock, self._feed, journal.flush)
        self.tell_people = AskedOfPeople(scenario, clock, campaign_id if core is not None else None, bus.listening)
        self._timers: dict[TimerKey, asyncio.TimerHandle] = {}
        self._ids = itertools.count(1)
        self._handles: list[Any] = []
        self._done: asyncio.Future | None = None
        self._kicked = False
        self._deciding: asyncio.Future | None = None
        self._planning: asyncio.Future | None = None  # a proposal being computed in the worker thread
        self._spare: Proposed | None = None  # an answer that came after the lab went on without it
        self._late: asyncio.TimerHandle | None = None

    def stop(self, reason: str) -> None:
        """Stop proposing and dispatching; what is in the lab is cancelled, the rest stays pending."""
        self._feed(Stop(reason, outside=True))

    def never_started(self, why: str) -> None:
        """The lab failed before the campaign began: its summary and journal say why."""
        self.core.stopping = f"the lab did not start: {why}"
        self.note("campaign.stopping", self.core.stopping)

    def _note_from_any_thread(self, kind: str, detail: Any) -> None:
        """``note`` from a scheduler asked off the loop (twin/runtime/off_loop.py), whose checks fall back in its
        worker thread: the journal is the loop's (SQLite refused the write, and the campaign stopped)."""
        try:
            on_loop = asyncio.get_running_loop() is self._loop
        except RuntimeError:
            on_loop = self._loop is None
        if on_loop or self._loop is None:
            self.note(kind, detail)
        else:
            self._loop.call_soon_threadsafe(self.note, kind, detail)

    def note(self, kind: str, detail: Any = None, device: str | None = None) -> None:
        """A runtime's own remark (a scheduler agent missing, say): journalled and published like the core's, and
        logged if it is an alert."""
        n = Note(self.clock.now(), kind, device=device, detail=detail)
        self._remark(n)
        if kind in ALERTS:
            self.alert_log(n)

    def _remark(self, n: Note) -> None:
        self._decided(n)
        self.decisions.publish()

    def _decided(self, n: Note) -> None:
        self.decisions.add(n, self.journal.note(n))
        if self.observer is not None and n.kind not in UNDRAWN:
            self.observer.on_note(n)

    async def run(self) -> None:
        lab, loop = self.s.lab, asyncio.get_running_loop()
        self._done = loop.create_future()
        self._handles = [
            self.bus.serve(self.decisions.history_key, self.decisions.history),
            self.bus.serve(keys.control(lab), self.desk.serve),
            self.bus.subscribe(keys.evt(lab), self._on_event),
            self.bus.subscribe(keys.telemetry(lab), self._on_event),
            self.bus.watch_tokens(keys.alive(lab), self._on_presence),
            self.bus.declare_token(keys.orchestrator(lab)),
        ]
        remove_hook = self.clock.on_idle(self._on_idle)
        ticking = None if self.clock.is_virtual or self.on_progress is None else \
            loop.create_task(self._tick_progress())
        try:
            if self._rebuilt is None:
                if self._recording:  # a resumed campaign needs the secret its tokens came from
                    self.journal.set("attempt_secret", self.core.secret.hex())
                    self.journal.inputs(self.clock.now(), {"start": True})
                self._perform(self.core.start(self.clock.now()))
            else:
                await self._take_over(self._rebuilt)
            await self._done
            await self.desk.drain()
        finally:
            remove_hook()
            if ticking is not None:
                ticking.cancel()
            if self._deciding is not None:
                self._deciding.cancel()
            if self._planning is not None:
                self._planning.cancel()
            self._close()

    async def _tick_progress(self) -> None:
        """Between events too: a step of hours leaves the lab's time moving while nothing is said."""
        assert self.on_progress is not None
        while True:
            await sleep_wall(PROGRESS_TICK_S)
            self.on_progress(self.core)

    # -- events in --------------------------------------------------------------------
    def _on_event(self, key: str, payload: bytes) -> None:
        self._feed(self._decoder.event(key, payload))

    def _on_presence(self, key: str, alive: bool) -> None:
        self._feed(Presence(keys.device_of(key), alive))

    def _on_timer(self, key: TimerKey) -> None:
        self._timers.pop(key, None)
        self._feed(TimerFired(key))

    def _feed(self, event: Any) -> None:
        self._give(event)
        if not self.clock.is_virtual:
            self._kick_soon()

    def _give(self, event: Any) -> None:
        if self._recording:
            self._fed.append(event)
        self.core.feed(event)

    def _kick_soon(self) -> None:
        if not self._kicked:
            self._kicked = True
            asyncio.get_running_loop().call_soon(self._kick)

    def _on_idle(self) -> bool:
        """Virtual time: everything of this instant has happened; let the core decide before time moves."""
        if self.core.has_work and not self.core.finished:
            self._kick_soon()
            return True
        return False

    def to_draw(self, held: dict[bytes, dict[str, Any]]) -> None:
        """What the observer is shown of the messages the core handles next, each when the core journals it (one
        it refuses, never)."""
        self._shown = held

    def _kick(self) -> None:
        self._kicked = False
        try:
            while self.core.has_work and not self.core.finished:
                now = self.clock.now()
                if self._recording:
                    self.journal.inputs(now, {"events": replay.encode_all(self._fed)})
                    self._fed.clear()
                self.to_draw(self._decoder.take())
                self._perform(self.core.advance(now))
                if self.clock.is_virtual:
                    break  # the next advance waits until the loop is idle again, as in the fast runtime
        except Exception as exc:  # a bug must end the campaign with its error, never leave it waiting silently
            if not isinstance(exc, TwinError):  # one said on purpose (a journal's disk full) is said as it is
                log.exception("the campaign stopped on an error")
            if self._done is not None and not self._done.done():
                self._done.set_exception(exc)

    # -- taking over a killed or stopped campaign ---------------------------------------
    async def _take_over(self, rebuilt: Rebuilt) -> None:
        """Re-arm what the dead (or stopped) process left pending, then find out what became of the steps it had
        in the lab."""
        if rebuilt.stopped:  # the stop is undone: a later rebuild skips it and what followed (replay.unstopped)
            self.journal.inputs(self.clock.now(), {RESUMED: rebuilt.stopped})
            self.journal.unset("summary")
        self.note("campaign.resumed", {"inputs_replayed": True, "timers": len(rebuilt.timers),
                                       "in_lab": [d.attempt.task.id for d in self.core.devices.values() if d.attempt],
                                       **({"after": rebuilt.stopped} if rebuilt.stopped else {})})
        if rebuilt.asked is not None:
            self._answer(rebuilt.asked)
        # asked before the deadlines are re-armed: a step whose deadline passed while the campaign was dead, on a
        # device that no longer runs it, is lost and retried at once, rather than timed out and cancelled (a cancel
        # nobody answers holds the device for orchestrator.cancel_grace_s)
        for dev in list(self.core.devices.values()):
            if dev.attempt is not None:
                await self._ask_about(dev.name, dev.attempt.task.id, dev.attempt.n, rebuilt.stopped)
        for key, due in rebuilt.timers.items():
            rearm(self.clock, self._timers, key, due, self._on_timer)
        if self.on_progress is not None:  # a progress bar starts where the campaign was, not at nothing done
            self.on_progress(self.core)
        self._kick_soon()

    async def _ask_about(self, device: str, task: str, attempt: int, stopped: str = "") -> None:
        """An attempt in the lab when the campaign died: still running, finished (its result is taken), or lost.
        ``stopped``: the stop the campaign ended with, which cancelled it: unless it finished first, it is sent
        again as after a "not now" (no attempt used, no strike against the device). People are not asked: they
        have no health key, and their step still waits for its confirmation."""
        if device in self.core.people:  # said again, for whoever tells people what waits for them
            att = self.core.attempts[(task, attempt)]
            note = human.said_again(self.core, att, self.clock.now(), "the campaign was resumed; the step still "
                                                                     "waits for twin ctl confirm")
            self._remark(note)
            self.tell_people(note)
            return
        wait = 5.0 * (1.0 if self.clock.is_virtual else self.clock.speed)
        try:
            report = json_from_wire(await self.bus.request(keys.health(self.s.lab, device), b"", wait))
        except (BusError, ValueError) as exc:  # no answer, or a failure in its stead
            log.warning("resume: %s does not answer (%s); its step %s#%d is lost", device, exc, task, attempt)
            self._give(Presence(device, False))
            return
        running, payload = reported(report, task, attempt, stopped)
        if running:
            return  # still at it: its result will come, or its re-armed deadline will pass
        if payload is not None:
            self._on_event(keys.evt(self.s.lab, device), payload.encode())
            return
        if stopped:
            kind, body = Kind.REJECTED, {"reason": f"cancelled when the campaign was stopped ({stopped}); sent "
                                                   "again now it is resumed", "began": True}
        else:
            kind, body = Kind.FAULT, {"code": "device_lost",
                                      "reason": f"{device} was not running {task}#{attempt} when the campaign resumed"}
        self._on_event(keys.evt(self.s.lab, device), pack(
            kind, body, id=f"{SENDER}:resume:{task}#{attempt}", sender=device, t_lab=self.clock.now(),
            campaign=self.core.campaign_id, task=task, attempt=attempt, token=self.core.token(task, attempt)))

    # -- actions out ------------------------------------------------------------------
    def _perform(self, actions: list[Any]) -> None:
        progressed = False
        # live runs are write-ahead: what caused a command is on disk before the command leaves
        live, unwritten = not self.clock.is_virtual, False
        for a in actions:
            t = type(a)
            if t is Send and unwritten:
                self.journal.flush()
                unwritten = False
            elif live and t is not Send:
                unwritten = True
            if t is Note:
                self._decided(a)
                if a.kind.startswith("operator."):
                    self.desk.noted(a)
                self.tell_people(a)
                if a.kind in ALERTS:
                    self.alert_log(a)
                elif a.kind in PRESENCE:
                    self.alert_log.presence(a)
                elif a.kind == "message.rejected":  # a device of your own echoes tokens? the first ten, then sparingly
                    # counted note by note: a batch of messages is performed after the core has counted them all
                    self._rejected += 1 + a.detail.get("left_out", 0)
                    rejected = self._rejected
                    if rejected <= 10 or a.detail.get("left_out"):
                        log.warning("rejected a message on %s: %s (%d so far; the journal has the first 1,000, then "
                                    "one row in 1,000)", a.detail["key"], a.detail["reason"], rejected)
                progressed = progressed or a.kind.startswith(PROGRESS_KINDS)
            elif t is RecordMessage:
                self.journal.received(a)
                if a.kind in ("msg.result", "msg.telemetry"):
                    self.decisions.accepted(a.payload, reading=a.kind == "msg.telemetry")
                if self._shown:
                    shown = self._shown.pop(a.payload, None)
                    if shown is not None:
                        self.observer.on_envelope(shown)
            elif t is Send:
                self.bus.publish(keys.cmd(self.s.lab, a.device),
                                 pack(a.kind, a.body, id=f"{SENDER}:{next(self._ids)}", sender=SENDER,
                                      t_lab=self.clock.now(), campaign=self.core.campaign_id, task=a.task,
                                      attempt=a.attempt, token=a.token))
            elif t is SetTimer:
                old = self._timers.pop(a.key, None)
                if old is not None:
                    old.cancel()
                self._timers[a.key] = self.clock.call_later(a.delay, functools.partial(self._on_timer, a.key))
            elif t is CancelTimer:
                handle = self._timers.pop(a.key, None)
                if handle is not None:
                    handle.cancel()
            elif t is RecordExperiment:
                self.journal.experiment(a.experiment)
                if a.final and not self.clock.is_virtual:
                    self.journal.flush()  # live runs: a finished experiment is on disk at once
            elif t is Ask:
                self._answer(a)
            elif t is Finished:
                self._ended()
        self.decisions.publish()
        if progressed and self.on_progress is not None:
            self.on_progress(self.core)

    def _ended(self) -> None:
        self._close()
        if self._done is not None and not self._done.done():
            self._done.set_result(None)

    def _answer(self, ask: Ask) -> None:
        if ask.what == "plan":
            self._plan(ask)
            return
        self._deciding = ask_scheduler(self.scheduler, ask, self._scheduled, self._failed)

    def _scheduled(self, decided: Decided, later: bool) -> None:
        self._deciding = None
        self._give(decided)
        if later:
            self._kick_soon()

    def _failed(self, exc: BaseException) -> None:
        """A scheduler that fails ends the run with its error."""
        self._deciding = None
        if self._done is not None and not self._done.done():
            self._done.set_exception(exc)

    def _plan(self, ask: Ask) -> None:
        """Ask the planner. In virtual time at once (time stands still while it thinks); on a scaled or wall
        clock in a worker thread, so that the loop goes on serving devices (a GP fit takes wall time, which
        is lab time there). Past ``campaign.planner_deadline_s`` the lab goes on without the answer
        (``planner.late``) if it has work in hand; the answer is used at the next question."""
        if self.clock.is_virtual:
            self._give(self.planner.answer(ask.n, list(ask.history), list(ask.pending)))
            return
        if self._spare is not None:
            spare, self._spare = self._spare, None
            self._give(spare)
            self._kick_soon()
            return
        if self._late is not None:
            self._late.cancel()
        self._late = self.clock.call_later(self.s.campaign.planner_deadline_s,
                                           functools.partial(self._planner_late, ask))
        if self._planning is not None:
            return  # still thinking about an earlier question (one call at a time: planners keep state)
        self._planning = asyncio.get_running_loop().run_in_executor(
            None, self.planner.answer, ask.n, list(ask.history), list(ask.pending))
        self._planning.add_done_callback(self._planned)

    def _planned(self, fut: asyncio.Future) -> None:
        self._planning = None
        if self._late is not None:
            self._late.cancel()
        if fut.cancelled():
            return
        if fut.exception() is not None:  # not the planner's (CheckedPlanner answers for it): ours, ending the run
            if self._done is not None and not self._done.done():
                self._done.set_exception(fut.exception())
            return
        asked = self.core.waiting
        if asked is not None and asked.what == "plan":
            self._give(fut.result())
            self._kick_soon()
        else:  # the lab went on without it: the next question gets it
            self._spare = fut.result()

    def _planner_late(self, ask: Ask) -> None:
        if self.core.waiting is not ask or not self.core.active:
            return  # nothing in hand: waiting for the planner is all the lab can do
        self.note("planner.late", {"deadline_s": self.s.campaign.planner_deadline_s, "asked_for": ask.n})
        self._give(Proposed([]))
        self._kick_soon()

    def _close(self) -> None:
        for h in self._handles:
            h.close()
        self._handles = []
        for handle in self._timers.values():
            handle.cancel()
        self._timers.clear()
