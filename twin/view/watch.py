"""Observers of a lab: a recorder beside a campaign, ``twin watch`` from elsewhere, ``twin replay``.

All three feed the same ``LabObserver`` the same messages: live from the bus,
or rebuilt from the journal, so a replay draws what the live recorder drew.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
from dataclasses import dataclass
from pathlib import Path

from twin.core import keys
from twin.core.bus import Bus, Closable, NoReplyError
from twin.core.clock import LabClock
from twin.core.errors import TwinError
from twin.campaign.journal import as_messages, read_events, read_run
from twin.view.observer import LabObserver

log = logging.getLogger(__name__)


@dataclass
class RecordOptions:
    """Where a recording goes: a file, a spawned viewer, a loopback web viewer."""

    save: str | Path | None = None
    viewer: bool = False
    serve: bool = False
    serve_port: int = 0
    web_port: int = 0

    @property
    def wanted(self) -> bool:
        return bool(self.save or self.viewer or self.serve)


def open_observer(options: RecordOptions, recording_id: str, dedupe: bool = False):
    """An observer drawing on a new Rerun recording; the recording is returned to be closed."""
    from twin.view.recorder import open_recording

    recording = open_recording(recording_id, options.save, options.viewer, options.serve,
                               options.serve_port, options.web_port)
    observer = LabObserver(recording.canvas, dedupe=dedupe)
    recording.before_close.append(observer.finish)
    return observer, recording


def open_lab_observer(options: RecordOptions, recording_id: str, campaigns: list[str], devices: dict[str, str]):
    """A ``SharedLabObserver`` of a lab these campaigns share, drawing on a new recording (returned to be closed)."""
    from twin.view.lab_observer import SharedLabObserver
    from twin.view.recorder import open_recording

    recording = open_recording(recording_id, options.save, options.viewer, options.serve,
                               options.serve_port, options.web_port, campaigns=campaigns)
    observer = SharedLabObserver(recording.canvas, devices)
    recording.before_close.append(observer.finish)
    return observer, recording


def attach(bus: Bus, lab: str, on_message) -> list[Closable]:
    """Subscribe ``on_message`` to everything an observer of ``lab`` needs."""
    return [bus.subscribe(k, on_message) for k in (keys.evt(lab), keys.telemetry(lab), keys.campaign(lab, "*"))]


def replay(journal: str | Path, options: RecordOptions) -> LabObserver:
    """Rebuild a run's recording from its journal alone."""
    path = Path(journal)
    if not path.exists():
        raise TwinError(f"{path}: no such journal; runs are written to runs/ by default")
    run = read_run(path)
    scenario = run.get("scenario", {})
    observer, recording = open_observer(options, f"{scenario.get('name', 'run')}-seed{run.get('seed', 0)}")
    try:
        for payload in as_messages(read_events(path)):
            observer.on_message("", payload)
    finally:
        recording.close()
    return observer


async def watch_async(bus: Bus, clock: LabClock, lab: str, options: RecordOptions, follow: bool = False,
                      stop: asyncio.Event | None = None) -> LabObserver:
    """Record a lab that runs elsewhere until its campaign ends (or ``stop`` is set)."""
    observer, recording = open_observer(options, f"watch-{lab}", dedupe=True)
    waiting: list | None = []  # live messages wait here until the history is read

    def on_message(key: str, payload: bytes) -> None:
        if waiting is not None:
            waiting.append((key, payload))
        else:
            observer.on_message(key, payload)

    handles = attach(bus, lab, on_message)
    stop = stop or asyncio.Event()
    try:
        await _catch_up(bus, clock, lab, observer)
        for key, payload in waiting:
            observer.on_message(key, payload)  # repeats of the history are dropped by id
        waiting = None
        while not stop.is_set() and (follow or not observer.done):
            await clock.sleep(0.25 * clock.speed)
            observer.c.flush()
    finally:
        for h in handles:
            h.close()
        recording.close()
    return observer


async def _catch_up(bus: Bus, clock: LabClock, lab: str, observer: LabObserver, patience_s: float = 30.0) -> None:
    """Ask the running campaign for what happened before we joined; wait for it to come up."""
    key = keys.campaign(lab, "*", "history")
    for _ in range(int(patience_s / 0.5)):
        try:
            page = json.loads(await bus.request(key, b"", timeout=2.0 * clock.speed))
        except (NoReplyError, ValueError, TwinError):
            await clock.sleep(0.5 * clock.speed)
            continue
        while True:
            for payload in page.get("items") or []:
                observer.on_message("", payload)
            if page.get("next") is None:
                return
            page = json.loads(await bus.request(key, json.dumps({"after": page["next"]}).encode(),
                                                timeout=2.0 * clock.speed))
    log.warning("lab %r did not answer for its history in %.0f s: recording from now on", lab, patience_s)


def watch(lab: str, options: RecordOptions, connect: list[str], listen: list[str], follow: bool = False,
          security_dir: str | None = None) -> LabObserver:
    """``twin watch``: a wall-clock Zenoh session that records another process's lab; with ``security_dir``,
    a client of the lab's router with the lab's watcher certificate (which may read, nothing else)."""
    from twin.core.bus import open_bus, security

    clock = LabClock("wall")
    extra: dict = {}
    if security_dir is not None:
        extra = security.session_config(security_dir, security.Identity("watcher", lab))
        listen = []

    async def main() -> LabObserver:
        bus = open_bus("zenoh", clock, listen=listen, connect=connect, extra=extra)
        await bus.start()
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        print(f"watching lab {lab!r}", flush=True)
        try:
            return await watch_async(bus, clock, lab, options, follow, stop)
        finally:
            await bus.close()

    return clock.run(main())
