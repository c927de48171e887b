"""Observers of a lab: a recorder beside a campaign, ``twin watch`` from elsewhere, ``twin replay``.

All three feed the same ``LabObserver`` the same messages: live from the bus,
or rebuilt from the journal, so a replay draws what the live recorder drew.
"""

from __future__ import annotations

import asyncio
import heapq
import logging
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.core import keys
from twin.core.bus import Bus, Closable, NoReplyError
from twin.core.clock import LabClock
from twin.core.tasks import kept
from twin.core.errors import TwinError
from twin.campaign.journal_read import as_messages, no_such_journal, read_events, read_run
from twin.view.lab_observer import SharedLabObserver
from twin.view.observer import LabObserver
from twin.view.history_pages import MalformedPage, another_run, history_page, pages, read_history
from twin.view.vouched import Vouched

log = logging.getLogger(__name__)


@dataclass
class RecordOptions:
    """Where a recording goes: a file, a spawned viewer, a loopback web viewer; ``log``: where the log of decisions
    and faults goes as lines too (``twin watch --log``), with a recording or without one."""

    save: str | Path | None = None
    viewer: bool = False
    serve: bool = False
    serve_port: int = 0
    web_port: int = 0
    log: Callable[[str], None] | None = None

    @property
    def recorded(self) -> bool:
        return bool(self.save or self.viewer or self.serve)

    @property
    def wanted(self) -> bool:
        return self.recorded or self.log is not None


def _recording(options: RecordOptions, recording_id: str, campaigns: list[str] | None = None) -> tuple[Any, Any]:
    """(the recording, or an ``Unrecorded`` where only the log is wanted; the canvas to draw on)."""
    from twin.view.log_canvas import LogCanvas, Unrecorded

    if not options.recorded:
        return Unrecorded(), LogCanvas(options.log or (lambda line: None))
    from twin.view.recorder import open_recording

    recording = open_recording(recording_id, options.save, options.viewer, options.serve, options.serve_port,
                               options.web_port, campaigns=campaigns)
    return recording, recording.canvas if options.log is None else LogCanvas(options.log, recording.canvas)


def open_observer(options: RecordOptions, recording_id: str, dedupe: bool = False):
    """An observer drawing on a new Rerun recording (and the log, if asked); the recording is returned to be
    closed."""
    recording, canvas = _recording(options, recording_id)
    observer = LabObserver(canvas, dedupe=dedupe)
    recording.before_close.append(observer.finish)
    return observer, recording


def open_lab_observer(options: RecordOptions, recording_id: str, campaigns: list[str], devices: dict[str, str],
                      dedupe: bool = False):
    """A ``SharedLabObserver`` of a lab these campaigns share, drawing on a new recording (returned to be closed);
    the recording's layout gains a tab for each campaign that comes later."""
    recording, canvas = _recording(options, recording_id, campaigns)
    observer = SharedLabObserver(canvas, devices, dedupe=dedupe, on_campaign=recording.lay_out)
    recording.before_close.append(observer.finish)
    return observer, recording


def attach(bus: Bus, lab: str, on_message) -> list[Closable]:
    """Subscribe ``on_message`` to everything an observer of ``lab`` needs."""
    return [bus.subscribe(k, on_message) for k in (keys.evt(lab), keys.telemetry(lab), keys.campaign(lab, "*"))]


def replay(journal: str | Path, options: RecordOptions) -> LabObserver | SharedLabObserver:
    """Rebuild a run's recording from its journal alone (a lab of several campaigns: from its directory of
    journals, drawn as the lab's recorder draws it)."""
    path = Path(journal)
    if not path.exists():
        raise no_such_journal(path)
    if path.is_dir():
        return _replay_lab(path, options)
    run = read_run(path)
    scenario = run.get("scenario", {})
    observer, recording = open_observer(options, f"{scenario.get('name', 'run')}-seed{run.get('seed', 0)}")
    try:
        for payload in as_messages(read_events(path)):
            observer.on_message("", payload)
    finally:
        recording.close()
    return observer


def _replay_lab(where: Path, options: RecordOptions) -> SharedLabObserver:
    """Every campaign's journal, merged by lab time, through one ``SharedLabObserver``."""
    dbs = sorted(where.glob("*.db"))
    if not dbs:
        raise TwinError(f"{where}: no journals (<campaign>.db) here")
    lab = read_run(dbs[0]).get("lab") or {}
    names = [c["name"] for c in lab.get("campaigns", []) if c.get("name")]
    names += [db.stem for db in dbs if db.stem not in names]  # submitted to a served lab
    observer, recording = open_lab_observer(options, f"{lab.get('name', where.name)}-seed"
                                            f"{(lab.get('campaign') or {}).get('seed', 0)}", names, {})
    try:
        # at one lab time the lab takes in events, then dispatches (a device freed, then taken), and its
        # summaries come last; among equals, the journals in step (campaigns that start together start
        # before their devices come), then in the lab file's order
        phase = {"attempt.dispatched": 1, "campaign.summary": 2}
        streams = []
        for db in dbs:
            rows, turn = read_events(db), names.index(db.stem)
            streams.append([(r["t_lab"], phase.get(r["kind"], 0), i, turn, db.stem, payload)
                            for i, (r, payload) in enumerate(zip(rows, as_messages(rows)))])
        for *_, name, payload in heapq.merge(*streams):  # each journal's own order is kept
            observer.campaign(name).on_message("", payload)
    finally:
        recording.close()
    return observer


async def watch_async(bus: Bus, clock: LabClock, lab: str, options: RecordOptions, follow: bool = False,
                      stop: asyncio.Event | None = None,
                      on_ended: Callable[[str, Any], None] | None = None,
                      on_gone: Callable[[], None] | None = None,
                      on_cut: Callable[[bool], None] | None = None,
                      on_present: Callable[[bool], None] | None = None) -> LabObserver | SharedLabObserver:
    """Record a lab that runs elsewhere until its campaign ends (or ``stop`` is set). A lab several campaigns
    share is drawn as ``twin run LAB.yaml --save`` draws it, each campaign found by its token as it comes.
    ``on_ended(name, observer)``: told once of each campaign whose summary has been drawn ("" for a lab's one
    campaign). ``on_gone()``: the lab's process left the bus (its presence gone) before its campaigns ended; the
    watch then ends too, unless ``follow`` (a resumed lab comes back). ``on_cut(True)``: the router the watcher
    reached the lab through is gone (restarting, its network down), so the lab is not called gone meanwhile;
    ``on_cut(False)``: it is back. ``on_present(back)``: the lab's presence came, the first time (``back``
    False) or after it had gone; a lab that ends before its presence reaches the watcher is never seen."""
    told: set[str] = set()
    presence = _Presence()
    cut, relinked_at = False, None  # the watcher's router gone; when it came back

    def tell_ended() -> None:
        if on_ended is None:
            return
        ended = ({n: c for n, c in observer.campaigns.items() if c.done} if isinstance(observer, SharedLabObserver)
                 else {"": observer} if observer.done else {})
        for name in sorted(set(ended) - told):
            told.add(name)
            on_ended(name, ended[name])

    waiting: list | None = []  # live messages wait here until the history is read
    seats: list[str] = []  # the campaigns of a shared lab, as their tokens appear

    def on_message(key: str, payload: bytes) -> None:
        if waiting is not None:
            waiting.append((key, payload))
        else:
            feed(key, payload)

    def on_seat(key: str, alive: bool) -> None:
        if alive:
            seats.append(key.split("/")[3])

    def on_lab(key: str, alive: bool) -> None:
        nonlocal waiting
        back = presence.changed(alive, clock.now())
        if back and waiting is None:
            waiting = []  # back: what it sends waits until what it did before is read again
        if alive and on_present is not None:
            on_present(back)

    handles = [*attach(bus, lab, on_message), bus.watch_tokens(keys.campaign(lab, "*", "seat"), on_seat),
               bus.watch_tokens(keys.orchestrator(lab), on_lab)]
    stop = stop or asyncio.Event()
    recording = None
    try:
        first = await _first_page(bus, clock, lab, stop, presence)
        if first is not None and first.get("shared"):
            observer, recording = open_lab_observer(options, f"watch-{lab}", [], {}, dedupe=True)
            shared = _SharedWatch(bus, clock, lab, observer)
            await shared.catch_up(str(first.get("campaign")), first)
            feed = Vouched(shared.on_message)  # a result heard live: drawn once its campaign names it
        else:
            observer, recording = open_observer(options, f"watch-{lab}", dedupe=True)
            if first is not None:
                await read_history(bus, clock, lab, first, observer.on_message)
            feed = Vouched(observer.on_message)
        for key, payload in waiting:
            feed(key, payload)  # repeats of the history are dropped by id
        waiting = None
        while not stop.is_set() and (follow or not observer.done):
            if presence.back:  # a lab resumed: what it did before this watcher's session reached it again
                presence.back = False
                if isinstance(observer, SharedLabObserver):
                    names = sorted(shared.read)
                    shared.read.clear()
                    for name in names:
                        await shared.catch_up(name)
                    if shared.another:
                        _another_run_said(lab, shared.another)
                        break
                else:
                    again = await _first_page(bus, clock, lab, stop, presence)
                    if again is not None and another_run(first, again):
                        _another_run_said(lab)
                        break
                    if again is not None:
                        await read_history(bus, clock, lab, again, observer.on_message)
                held: list = waiting or []
                waiting = None
                for key, payload in held:
                    feed(key, payload)  # repeats of the history are dropped
            if isinstance(observer, SharedLabObserver):
                while seats:
                    await shared.catch_up(seats.pop(0))
            await clock.sleep(0.25 * clock.speed)
            observer.c.flush()
            tell_ended()
            if cut != bus.router_lost():  # our router went, or came back (asked each turn: it learns of the router)
                cut = not cut
                relinked_at = None if cut else clock.now()
                if on_cut is not None:
                    on_cut(cut)
            if presence.gone_at is not None and (cut or (relinked_at is not None and clock.now() - relinked_at
                                                         < _RELINK_GRACE_S * clock.speed)):
                presence.gone_at = clock.now()  # gone from here only, as far as we know, until the lab could relink
            if presence.gone(clock) and not observer.done:
                presence.gone_at = None
                if on_gone is not None:
                    on_gone()
                if not follow:
                    break
        tell_ended()
    finally:
        for h in handles:
            h.close()
        if recording is not None:
            recording.close()
    return observer


_GONE_GRACE_S = 2.0  # wall seconds between the lab's presence going and the watcher calling it gone: a lab that
# ends says so (its summaries) before its presence goes, and this is a grace for those still in flight
_RELINK_GRACE_S = 10.0  # wall seconds the lab has to reach a router again after the watcher has (it retries each s)


@dataclass
class _Presence:
    """The watched lab's presence token: since when it is gone, and whether it came back after going (what the lab
    sent before the watcher's session reached it again is in its history only)."""

    gone_at: float | None = None
    lost: bool = False
    back: bool = False
    came_at: float | None = None  # when it last came

    def changed(self, alive: bool, now: float) -> bool:
        """The token came (``alive``) or went at ``now``; True when it came back after going."""
        self.gone_at = None if alive else now
        if alive:
            self.came_at = now
        returned = alive and self.lost
        self.back = self.back or returned
        self.lost = not alive
        return returned

    def gone(self, clock: LabClock) -> bool:
        """Gone for longer than the grace."""
        return self.gone_at is not None and clock.now() - self.gone_at > _GONE_GRACE_S * clock.speed


def _another_run_said(lab: str, campaign: str = "") -> None:
    """A following watch ends where its lab came back with another run (of ``campaign``, in a lab of several)."""
    of = f" of campaign {campaign!r}" if campaign else ""
    log.warning("lab %r came back with another run%s, not a resume of the one recorded (its message numbers start "
                "again): this watch records one run and ends here; start another `twin watch` for the new one", lab, of)


class _SharedWatch:
    """A watcher's side of a shared lab: each campaign's history read once, in order, before its live messages."""

    def __init__(self, bus: Bus, clock: LabClock, lab: str, observer: SharedLabObserver) -> None:
        self.bus, self.clock, self.lab, self.observer = bus, clock, lab, observer
        self.read: set[str] = set()
        self.held: dict[str, list] = {}  # a campaign's live decisions while its history is read
        self._catching_up: set[asyncio.Task] = set()
        self.runs: dict[str, dict] = {}  # which run of each campaign is recorded (its first page's "run")
        self.another = ""  # a campaign that came back with another run, not a resume of the one recorded

    async def catch_up(self, name: str, first: dict | None = None) -> None:
        if name in self.read:
            return
        self.read.add(name)
        self.held.setdefault(name, [])
        key = keys.campaign(self.lab, name, "history")
        try:
            if first is None:
                first = history_page(await self.bus.request(key, b"", timeout=2.0 * self.clock.speed), 0)
            if another_run(self.runs.get(name), first):
                self.another = self.another or name
                self.held.pop(name, None)
                self.read.discard(name)  # nothing of the new run is drawn: its messages come here again
                return
            self.runs.setdefault(name, {"run": first.get("run")})  # not the page: its items are drawn, not kept
            await pages(self.bus, self.clock, key, first, self.observer.campaign(name).on_message)
        except (NoReplyError, ValueError, TwinError) as exc:
            log.warning("campaign %r of lab %r did not give its history (%s): recording it from now on", name,
                        self.lab, exc)
        for key_, payload in self.held.pop(name):
            self.observer.campaign(name).on_message(key_, payload)

    def on_message(self, key: str, payload: bytes) -> None:
        parts = key.split("/")
        if len(parts) > 3 and parts[2] == "campaign":
            name = parts[3]
            if name in self.held:
                self.held[name].append((key, payload))
            elif name in self.read:
                self.observer.campaign(name).on_message(key, payload)
            else:  # a campaign whose token has not come yet: its history first, then this
                self.held[name] = [(key, payload)]
                kept(self._catching_up, self.catch_up(name))
        else:
            self.observer.on_message(key, payload)


async def _first_page(bus: Bus, clock: LabClock, lab: str, stop: asyncio.Event, presence: _Presence,
                      patience_s: float = 30.0) -> dict | None:
    """The first page of the running campaign's history (of one of them, in a shared lab); waits for it to come
    up, and gives up ``patience_s`` after the lab's presence last came (a lab not there yet is waited for:
    whether it is a shared lab is known from its first page), when ``stop`` is set, or when the lab's presence
    has been gone for the grace (a lab killed as it started: the caller tells it gone)."""
    key = keys.campaign(lab, "*", "history")
    given_up_at, why = None, ""
    while True:
        if stop.is_set() or presence.gone(clock):
            return None
        if given_up_at is None and presence.came_at is not None:
            given_up_at = presence.came_at + patience_s * clock.speed
        if given_up_at is not None and clock.now() >= given_up_at:
            break
        wait = 2.0 * clock.speed if given_up_at is None else min(2.0 * clock.speed, given_up_at - clock.now())
        try:
            return history_page(await bus.request(key, b"", timeout=wait), 0)
        except MalformedPage as exc:
            why = f" (its last answer: {exc})"
        except (NoReplyError, TwinError):
            pass
        await clock.sleep(0.5 * clock.speed)
    log.warning("lab %r did not answer for its history in %.0f s%s: recording from now on", lab, patience_s, why)
    return None


def watch(lab: str, options: RecordOptions, connect: list[str], listen: list[str], follow: bool = False,
          security_dir: str | None = None, wait_s: float = 30.0,
          on_gone: Callable[[], None] | None = None,
          on_cut: Callable[[bool], None] | None = None,
          on_present: Callable[[bool], None] | None = None) -> LabObserver | SharedLabObserver:
    """``twin watch``: a wall-clock Zenoh session that records another process's lab; with ``security_dir``,
    a client of the lab's router with the lab's watcher certificate (which may read, nothing else). ``wait_s``:
    how long ``connect`` may take to answer (a lab or router started after the watcher). ``on_gone``, ``on_cut``,
    ``on_present``: as :func:`watch_async`'s."""
    from twin.core.bus import open_bus, security
    from twin.core.bus.presence import elsewhere, labs_on

    clock = LabClock("wall")
    extra: dict = {}
    if security_dir is not None:
        extra = security.session_config(security_dir, security.Identity("watcher", lab))
        listen = []

    async def main() -> LabObserver | SharedLabObserver:
        if connect:
            print(f"connecting to {', '.join(connect)} (waiting up to {wait_s:g} s for it to answer)", file=sys.stderr,
                  flush=True)
        bus = open_bus("zenoh", clock, listen=listen, connect=connect, extra=extra,
                       connect_timeout_ms=round(wait_s * 1000), wait_longer="--wait SECONDS waits longer")
        await bus.start()
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        say = sys.stderr if options.log else sys.stdout  # stdout is the log's, if it is printed
        print(f"watching lab {lab!r}", flush=True, file=say)
        labs = await labs_on(bus)
        if lab not in labs:
            print(f"no campaign of lab {lab!r} is on this bus yet ({elsewhere(labs)}): waiting for one (Ctrl-C to "
                  "stop)", flush=True, file=say)

        def ended(name: str, seen: Any) -> None:
            print(f"campaign {name + ' ' if name else ''}ended: {seen.finished} experiments finished, "
                  "its summary drawn", flush=True, file=say)
        try:
            return await watch_async(bus, clock, lab, options, follow, stop, ended, on_gone, on_cut, on_present)
        finally:
            await bus.close()

    return clock.run(main())
