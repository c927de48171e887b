"""Several campaigns sharing one lab on the asyncio runtime: one set of subscriptions for the lab's devices, a
seat per campaign (its journal, planner, scheduler, timers and decision stream — a ``LiveCampaign`` the lab
drives), and the ``SharedLab`` deciding whose turn it is. Any clock; devices in this process or others."""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Callable
from typing import Any

from twin.campaign.events import Ask, Decided, Note, TimerFired, TimerKey
from twin.campaign.lab_replay import RebuiltLab, encode
from twin.campaign.replay import RESUMED, merged
from twin.campaign.journal import Journal
from twin.campaign.decisions import Planner, Scheduler
from twin.campaign.sharing import LAB, SharedLab, by_campaign
from twin.core import keys
from twin.core.bus import Bus
from twin.core.clock import LabClock
from twin.campaign import Presence
from twin.core.errors import ScenarioError, TwinError
from twin.core.warnings_said import warnings_said
from twin.runtime.lab_desk import LabDesk
from twin.runtime.event_decoder import EventDecoder
from twin.runtime.asked_of_people import ctl_options
from twin.runtime.asking import ask_scheduler
from twin.runtime.live import LiveCampaign
from twin.runtime.take_over import rearm
from twin.runtime.trial import submitted_warning
from twin.scenario import Scenario
from twin.scenario.files import parse_yaml
from twin.scenario.sharing import campaign_scenario, parse_campaign
from twin.view.lab_observer import SharedLabObserver

SeatParts = tuple[Journal, Planner, Scheduler]


log = logging.getLogger(__name__)


class LiveSeat(LiveCampaign):
    """One campaign of a shared lab: the lab feeds and advances its core; the seat performs its actions."""

    def __init__(self, lab: LiveLab, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._lab = lab
        self.decisions.shared = True

    def on_bus(self) -> list[Any]:
        """Its history for watchers, and its token: how a watcher finds the lab's campaigns."""
        return [self.bus.serve(self.decisions.history_key, self.decisions.history),
                self.bus.declare_token(keys.campaign(self._lab.lab.lab, self.core.campaign_id, "seat"))]

    def _kick_soon(self) -> None:
        self._lab.kick_soon()

    def _give(self, event: Any) -> None:
        """What this campaign's timers, planner, scheduler and operators give it, journalled by the lab; presence
        (a device that did not answer when the lab resumed) is the lab's."""
        if type(event) is Presence:
            self._lab.feed_device(event)
            return
        self._lab.record(["seat", self.core.campaign_id, encode(event)])
        self.core.feed(event)

    def _on_event(self, key: str, payload: bytes) -> None:
        self._lab._on_event(key, payload)  # a device's message is routed by the lab (a resumed seat's reports)

    def _remark(self, n: Note) -> None:
        self._lab.record(["note", self.core.campaign_id, n.kind, n.detail, n.t_lab])
        self._lab.write_ahead()  # on disk before the campaign's journal can have it
        super()._remark(n)

    def _ended(self) -> None:
        self._close()  # the lab ends when its last campaign has


class LiveLab:
    def __init__(self, lab: Scenario, scenarios: dict[str, Scenario], bus: Bus, clock: LabClock,
                 parts: dict[str, SeatParts], adopt: Callable[[str, Scenario], SeatParts] | None = None,
                 admit: Callable[[str, Scenario], None] | None = None,
                 observer: SharedLabObserver | None = None, inputs: Journal | None = None,
                 rebuilt: RebuiltLab | None = None, lab_scheduler: Any = None) -> None:
        """``adopt``: a lab that serves (``twin lab serve``) takes campaigns as they are submitted; ``adopt(name,
        scenario)`` readies one (its drivers, journal, planner and scheduler) or raises a TwinError that says
        why not. ``observer``: handed each campaign's notes and the devices' results and telemetry (a
        recording). ``inputs``: where the lab journals what it is given, write-ahead (``twin resume`` rebuilds
        it from them: ``twin.campaign.lab_replay``); ``rebuilt``: such a lab, to take over (``scenarios`` then
        holds every campaign it had, those submitted included). ``lab_scheduler``: the lab's one scheduler
        (``orchestrator.lab_scheduler``), asked the lab's questions with every campaign's ready steps."""
        self.lab, self.bus, self.clock = lab, bus, clock
        self.shared = rebuilt.shared if rebuilt is not None else SharedLab(lab, scenarios, serving=adopt is not None)
        self._rebuilt, self._inputs = rebuilt, inputs
        self._fed: list[Any] = []
        self.parts = dict(parts)
        self._adopt, self._admit = adopt, admit
        self._trying = asyncio.Lock()
        self.observer = observer
        self.seats = {name: LiveSeat(self, scenarios[name], bus, clock, *parts[name], campaign_id=name,
                                     core=self.shared.cores[name], observer=self._feed(name))
                      for name in scenarios}
        self.desk = LabDesk(self)
        self._decoder = EventDecoder(observer, clock)
        self._timers: dict[TimerKey, asyncio.TimerHandle] = {}
        self._handles: list[Any] = []
        self._done: asyncio.Future | None = None
        self._kicked = False
        self.lab_scheduler = lab_scheduler
        self._lab_deciding: asyncio.Future | None = None

    def _feed(self, name: str) -> Any:
        return self.observer.campaign(name) if self.observer is not None else None

    def record(self, item: list[Any]) -> None:
        """An input for the lab's journal, written before the next advance (a run of undecodable messages as one
        entry with their count: replay.encode_all)."""
        if self._inputs is None:
            return
        last = self._fed[-1] if self._fed else None
        if (last is not None and item[0] == last[0] == "dev" and item[1][0] == last[1][0] == "invalid"
                and item[1][1] == last[1][1]):  # one sender: routed to the same campaign (sharing._owner)
            merged(last[1], item[1][5] if len(item[1]) > 5 else 1)
        else:
            self._fed.append(item)

    def _advance(self, now: float) -> list[tuple[str, Any]]:
        self.write_ahead(now)  # on disk before any command of this advance leaves
        return self.shared.advance(now)

    def write_ahead(self, advancing_at: float | None = None) -> None:
        """Journal the inputs given since the last batch — and, with ``advancing_at``, that the lab advances on
        them at that lab time — and flush."""
        if self._inputs is not None and (self._fed or advancing_at is not None):
            if advancing_at is None:
                self._inputs.inputs(self.clock.now(), {"items": self._fed, "advance": False})
            else:
                self._inputs.inputs(advancing_at, {"items": self._fed})
            self._inputs.flush()
            self._fed = []

    def feed_device(self, event: Any) -> None:
        self.record(["dev", encode(event)])
        self.shared.feed_device(event)

    def stop(self, reason: str) -> None:
        self.record(["stop", reason])
        self.shared.stop(reason, outside=True)
        self.kick_soon()

    async def run(self) -> None:
        lab = self.lab.lab
        self._done = asyncio.get_running_loop().create_future()
        for seat in self.seats.values():
            seat._done = self._done  # a seat's planner or scheduler that fails ends the lab with its error
        self._handles = [
            self.bus.subscribe(keys.evt(lab), self._on_event),
            self.bus.subscribe(keys.telemetry(lab), self._on_event),
            self.bus.watch_tokens(keys.alive(lab), self._on_presence),
            self.bus.declare_token(keys.orchestrator(lab)),
            self.bus.serve(keys.control(lab), self.desk.serve),
            *(h for seat in self.seats.values() for h in seat.on_bus()),
        ]
        remove_hook = self.clock.on_idle(self._on_idle)
        try:
            if self._rebuilt is not None:
                await self._take_over(self._rebuilt)
            else:
                now = self.clock.now()
                if self._inputs is not None:
                    self._inputs.inputs(now, {"start": True, "secrets": {
                        n: c.secret.hex() for n, c in self.shared.cores.items()}})
                    self._inputs.flush()
                self._perform(self.shared.start(now))
            self._check_done()
            await self._done
        finally:
            remove_hook()
            for seat in self.seats.values():
                for fut in (seat._deciding, seat._planning):
                    if fut is not None:
                        fut.cancel()
                seat._close()
            if self._lab_deciding is not None:
                self._lab_deciding.cancel()
            for h in self._handles:
                h.close()
            for handle in self._timers.values():
                handle.cancel()

    # -- the desk's side ------------------------------------------------------------------
    async def submit(self, body: dict[str, Any]) -> dict[str, Any]:
        """``twin submit``: a campaign file's text in ``file``; the answer names its journal and what the checks
        and a few trial experiments on the twin warn of it (a live lab's own file is tried before the lab starts:
        twin/runtime/trial.py), or why it is refused. It starts once tried."""
        if self._adopt is None or self._admit is None:
            raise ValueError(f"lab {self.lab.lab} runs the campaigns of its file; to take more, serve it with "
                             "`twin lab serve`")
        text, who = body.get("file"), str(body.get("who", ""))[:64]
        if not isinstance(text, str):
            raise ValueError("submit: give the text of a campaign file in 'file'")
        label = f"the campaign {who} submitted"
        try:
            entry = parse_campaign(parse_yaml(text, label), label)
            label = f"campaign {entry.name}"
            if entry.after is not None or entry.start_h:
                raise ScenarioError(entry.name, ["after / start_h: a submitted campaign starts when it is "
                                                 "submitted; leave them out"])
            self._refuse_taken(entry.name)
            scenario = campaign_scenario(self.lab, entry, len(self.shared.entries), named=label)
            with warnings_said() as checks:  # said on the lab's log as they come, and kept for the answer
                self._admit(entry.name, scenario)  # refused before any of its code is imported or tried
            warnings = [*checks.said, *await self._tried(entry.name, scenario)]
            self._refuse_taken(entry.name)  # submitted by another, or the lab stopped, while it was tried
            scenario = campaign_scenario(self.lab, entry, len(self.shared.entries), named=label)
            parts = self._adopt(entry.name, scenario)
        except ScenarioError as exc:
            named = label if exc.source in ("", self.lab.name) else exc.source  # the checks name the lab's scenario
            return {"ok": False, "error": str(ScenarioError(named, exc.problems))}
        except TwinError as exc:
            return {"ok": False, "error": str(exc)}
        core = self.shared.add(entry, scenario)
        self.record(["add", entry.model_dump(exclude_unset=True), scenario.model_dump(), core.secret.hex()])
        self.parts[entry.name] = parts
        seat = LiveSeat(self, scenario, self.bus, self.clock, *parts, campaign_id=entry.name, core=core,
                        observer=self._feed(entry.name))
        seat._done = self._done
        self.seats[entry.name] = seat
        self._handles += seat.on_bus()
        seat.note("campaign.submitted", {"who": who, "priority": entry.priority, "owner": entry.owner,
                                         "warnings": warnings})
        self.kick_soon()
        return {"ok": True, "campaign": entry.name, "journal": parts[0].label, "lab_hours": self.clock.now() / 3600,
                "warnings": warnings}

    def _refuse_taken(self, name: str) -> None:
        refusal = self.shared.refusal(name)
        if refusal:
            raise ScenarioError(name, [refusal])

    async def _tried(self, name: str, scenario: Scenario) -> list[str]:
        """What a few trial experiments on the twin warn of campaign ``name``, said on the lab's log too; nothing on a
        virtual clock, where the campaign is its own trial."""
        if self.clock.is_virtual:
            return []
        stop = f"`twin ctl stop {ctl_options(self.lab, name, self.bus.listening) or f'--campaign {name}'}` stops it"
        async with self._trying:  # one child process at a time, however many submit at once
            warning = await submitted_warning(scenario, name, stop)
        if warning:
            log.warning("campaign %s: %s", name, warning)
        return [warning] if warning else []

    def status(self) -> dict[str, Any]:
        """The lab's campaigns: each one's state, experiments and priority; and its one scheduler ("": each
        campaign's own, in turns)."""
        shared, rows = self.shared, []
        for name, entry in shared.entries.items():
            core = shared.cores[name]
            state = ("ended" if core.finished else "queued" if name not in shared.started else
                     f"paused by {core.paused_by}" if core.paused_by else "stopping" if core.stopping else
                     "stalled" if core.stalled else "running")
            counts = {k: sum(1 for e in core.experiments if e.status == k) for k in ("done", "abandoned")}
            rows.append({"campaign": name, "owner": entry.owner, "priority": entry.priority, "state": state,
                         "submitted_h": shared.submitted_at.get(name, 0.0) / 3600, **counts,
                         "in_progress": len(core.active), "budget": core.s.campaign.budget,
                         "targets_met": sorted(core.met_at)})
        return {"ok": True, "lab": self.lab.lab, "lab_hours": self.clock.now() / 3600, "serving": shared.serving,
                "scheduler": self.lab.orchestrator.lab_scheduler or "", "campaigns": rows}

    # -- events in --------------------------------------------------------------------
    def _on_event(self, key: str, payload: bytes) -> None:
        self.feed_device(self._decoder.event(key, payload))
        self._after_event()

    def _on_presence(self, key: str, alive: bool) -> None:
        self.feed_device(Presence(keys.device_of(key), alive))
        self._after_event()

    def _after_event(self) -> None:
        if not self.clock.is_virtual:
            self.kick_soon()

    def _on_idle(self) -> bool:
        if self.shared.has_work and not self.shared.finished:
            self.kick_soon()
            return True
        return False

    def kick_soon(self) -> None:
        if not self._kicked:
            self._kicked = True
            asyncio.get_running_loop().call_soon(self._kick)

    def _kick(self) -> None:
        self._kicked = False
        try:
            while self.shared.has_work and not self.shared.finished:
                held = self._decoder.take()  # each drawn by the campaign that journals it
                for seat in self.seats.values():
                    seat.to_draw(held)
                self._perform(self._advance(self.clock.now()))
                if self.clock.is_virtual:
                    break
            if not self.clock.is_virtual and self.shared.waiting is None and not self.shared.finished:
                why, stalled = self.shared.newly_stalled()
                for name in stalled:  # a remark in the lab's inputs, so that a rebuilt journal has it too
                    self.seats[name].note("scheduler.stalled", why)
            self._check_done()
        except Exception as exc:  # a bug must end the lab with its error, never leave it waiting silently
            if self._done is not None and not self._done.done():
                self._done.set_exception(exc)

    def _check_done(self) -> None:
        if self.shared.finished and self._done is not None and not self._done.done():
            self._done.set_result(None)

    # -- actions out --------------------------------------------------------------------
    def _perform(self, tagged: list[tuple[str, Any]]) -> None:
        for name, actions in by_campaign(tagged):
            self._to(name, actions)

    def _to(self, name: str, actions: list[Any]) -> None:
        if name != LAB:
            self.seats[name]._perform(actions)
            return
        for a in actions:  # the lab's own: submission timers, and questions to its one scheduler
            if type(a) is Ask:
                self._ask_lab(a)
            else:
                self._timers[a.key] = self.clock.call_later(a.delay, functools.partial(self._on_timer, a.key))

    def _ask_lab(self, ask: Ask) -> None:
        """The lab's one scheduler: at once, or (on a live clock, once it held the loop too long:
        ``OffLoopScheduler``) when its worker thread or, past the deadline, the fallback rule answers; the answer is
        journalled with the lab's inputs."""
        if self.lab_scheduler is None:
            raise RuntimeError(f"{self.lab.name}: the lab asked its one scheduler, and it has none")
        self._lab_deciding = ask_scheduler(self.lab_scheduler, ask, self._lab_decided, self._failed)

    def _lab_decided(self, decided: Decided, later: bool) -> None:
        self._lab_deciding = None
        self.record(["lab", encode(decided)])
        self.shared.feed(LAB, decided)
        if later:
            self.kick_soon()

    def _failed(self, exc: BaseException) -> None:
        self._lab_deciding = None
        if self._done is not None and not self._done.done():
            self._done.set_exception(exc)

    def _on_timer(self, key: TimerKey) -> None:
        self._timers.pop(key, None)
        self.record(["lab", encode(TimerFired(key))])
        self.shared.feed(LAB, TimerFired(key))
        self.kick_soon()

    # -- taking over a killed lab -----------------------------------------------------------
    async def _take_over(self, rebuilt: RebuiltLab) -> None:
        """Find out what became of the steps it had in the lab (still running, finished — its result is taken — or
        lost, and retried; cancelled by the Ctrl-C the lab was stopped with: sent again), then re-arm what the dead
        process left pending: asked first, as a single campaign does (``LiveCampaign._take_over``), so a step lost
        while its deadline passed is retried at once."""
        if rebuilt.stopped and self._inputs is not None:  # the stop is undone: a later rebuild skips it again
            self._inputs.inputs(self.clock.now(), {RESUMED: rebuilt.stopped})
            self._inputs.flush()
        for name, seat in self.seats.items():
            in_lab = [d.attempt.task.id for d in seat.core.devices.values() if d.attempt is not None]
            seat.note("campaign.resumed", {"inputs_replayed": True, "in_lab": in_lab,
                                           **({"after": rebuilt.stopped} if rebuilt.stopped else {})})
        for name, ask in rebuilt.asked.items():
            if name == LAB:
                self._ask_lab(ask)
            else:
                self.seats[name]._answer(ask)
        for seat in self.seats.values():
            for dev in list(seat.core.devices.values()):
                if dev.attempt is not None:
                    await seat._ask_about(dev.name, dev.attempt.task.id, dev.attempt.n, rebuilt.stopped)
        for (name, key), due in rebuilt.timers.items():
            owner = self if name == LAB else self.seats[name]
            rearm(self.clock, owner._timers, key, due, owner._on_timer)
        self.kick_soon()
