"""Run a campaign on the lab its scenario describes (built by ``twin.runtime.assembly``): the Python API
under ``twin run``, on the fast runtime or the asyncio one, with its journal, recording and signals."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any

from twin.campaign import CampaignCore
from twin.campaign.human import people as people_of
from twin.campaign.journal import Journal
from twin.campaign.replay import Rebuilt
from twin.campaign.summary import Summary, from_core
from twin.core.bus import security
from twin.core.clock import LabClock
from twin.core.errors import ClockError, PluginError, TwinError
from twin.core import held
from twin.device.driver import feature
from twin.runtime import FastCampaign, LiveCampaign
from twin.runtime.asked_of_people import say_where
from twin.runtime.assembly import (REMOTE, agent_on_bus, build_actors, fallback_for, live_scheduler, load_drivers,
                                   make_bus, make_clock, make_planner, make_scheduler, named_schedulers,
                                   prepare, untaken_option)
from twin.runtime.checked_scheduler import CheckedScheduler, fallbacks
from twin.runtime.lab_claim import refuse_if_taken
from twin.runtime.fast_device import FastRuntimeRefused
from twin.runtime.labtime import LabTimeSource
from twin.runtime.off_loop import OffLoopScheduler
from twin.runtime.remote_scheduler import RemoteScheduler
from twin.runtime.run_record import provenance
from twin.runtime.served_devices import ServedCheck
from twin.scenario import Scenario
from twin.view.lab_observer import SharedLabObserver
from twin.view.observer import LabObserver
from twin.view.watch import RecordOptions, open_observer

log = logging.getLogger(__name__)
#: The fast runtime refusing a driver, and the campaign run again on the asyncio runtime: a bench's or a what-if's
#: workers, whose every run would say it, hand it to the command, which says it once (``twin.tools.pool``)
FALLBACK_LOGGER = "twin.runtime.fallback"


WALL_CLOCK_FIELDS = ("wall_s", "journal", "decision_ms")  # differ between identical runs
RUNTIMES = ("auto", "fast", "asyncio")


def default_journal(s: Scenario) -> Path:
    """``runs/<name>-seed<seed>-<time>.db``, claimed (made, empty) here: campaigns of one scenario and seed started
    in the same second — a sweep run in parallel — each get their own (``…-2.db``, ``…-3.db``)."""
    return claim(_default_stem(s), ".db", _create)


def default_journals(s: Scenario) -> Path:
    """The directory of a lab's journals, named as a run's journal would be, claimed likewise."""
    return claim(_default_stem(s), "", os.mkdir)


@contextlib.contextmanager
def given_back(journals: Path, claimed: bool) -> Iterator[None]:
    """A lab's journals' directory, claimed for it (``default_journals``), given back if the lab fails before it
    wrote anything there: a lab refused at its start left an empty ``runs/<lab>-seed0-<time>/`` behind."""
    try:
        yield
    except BaseException:
        if claimed:
            with contextlib.suppress(OSError):  # not empty: a journal in it, kept
                journals.rmdir()
        raise


def _default_stem(s: Scenario) -> Path:
    return Path("runs") / f"{s.name}-seed{s.campaign.seed}-{time.strftime('%Y%m%d-%H%M%S')}"


def claim(stem: Path, suffix: str, make: Callable[[Path], None]) -> Path:
    """The first of ``stem + suffix``, ``stem-2 + suffix``, ... that ``make`` creates (it raises FileExistsError
    for one already there: another process's)."""
    try:
        stem.parent.mkdir(parents=True, exist_ok=True)
        for n in itertools.count(1):
            path = stem.with_name(f"{stem.name}-{n}{suffix}" if n > 1 else f"{stem.name}{suffix}")
            try:
                make(path)
            except FileExistsError:
                continue
            return path
    except FileExistsError:  # from mkdir: a file where the directory should be
        raise TwinError(f"cannot write a journal in {stem.parent}/: {stem.parent} is a file, not a directory; move "
                        "it away, or give --journal FILE (nothing has run yet)") from None
    except OSError as exc:
        raise TwinError(f"cannot write a journal in {stem.parent}/: {exc}; run from a directory you can write, or "
                        "give --journal FILE (nothing has run yet)") from None
    raise AssertionError("unreachable")


def _create(path: Path) -> None:
    os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))


def run(scenario: str | Path | Scenario, *, journal: str | Path | None = None,
        external_devices: Collection[str] = frozenset(),
        on_progress: Callable[[CampaignCore], None] | None = None,
        record: RecordOptions | None = None, observer: LabObserver | None = None, runtime: str = "auto",
        make_journal: JournalFactory = Journal, agent_in_process: bool = False, handle_signals: bool = True,
        options_checked: bool = False, **overrides: Any) -> Summary:
    """Run one campaign to its end and return its summary.

    ``overrides`` are ``seed``, ``clock``, ``speed``, ``bus`` or ``overrides``
    (a dict of dotted scenario paths). ``external_devices`` are device
    instances served by other processes (``twin device serve``). ``record``
    saves, shows or serves a Rerun recording of the campaign; ``observer``
    is an observer the caller opened (and closes) itself. ``runtime``:
    ``fast`` (virtual time on the memory bus, in-process), ``asyncio``
    (everything else), or ``auto``: fast where it can. ``make_journal`` opens the journal at a path.
    ``agent_in_process``: a scheduler that is an agent on the bus (rl) is asked in this process instead, so the
    fast runtime can run the campaign: the same decisions without a bus round trip each (benches, what-if).
    ``handle_signals``: SIGINT and SIGTERM stop the campaign cleanly, its journal and summary written (off where
    the caller handles them: a bench's worker, which its pool stops). ``options_checked``: the caller has checked
    ``campaign.planner_options`` and ``scheduler_options`` against every plugin it runs (a bench's row holds
    options meant for its others); else an option neither the campaign's planner nor its schedulers (nor any
    installed one) take is refused as misspelt.
    """
    s = prepare(scenario, **overrides)
    if s.campaigns:  # its own sections are the campaigns' defaults, not a campaign: it failed on a missing model
        raise TwinError(f"{s.name} is a lab of {len(s.campaigns)} campaigns ({', '.join(c.name for c in s.campaigns)})"
                        f": twin.run runs one campaign; twin.run_lab runs the lab and returns its LabSummary (each "
                        f"campaign's Summary in .campaigns)")
    if not options_checked:
        problem = untaken_option(s, "planners", [s.campaign.planner]) or \
            untaken_option(s, "schedulers", named_schedulers(s))
        if problem:
            raise PluginError(problem)
    why_not = fast_refused(s, external_devices, agent_in_process)
    check_runtime(runtime, why_not)
    claimed = journal is None
    journal = journal or default_journal(s)
    recording = None
    try:
        if record is not None and record.wanted and observer is None:
            observer, recording = open_observer(record, recording_id(s))
            for message in recording.messages:
                log.warning("%s", message)
        if runtime == "fast" or (runtime == "auto" and not why_not):
            try:
                return run_fast(s, journal, on_progress, handle_signals, make_journal, observer, agent_in_process)
            except FastRuntimeRefused as exc:
                if runtime == "fast":
                    raise
                logging.getLogger(FALLBACK_LOGGER).warning("%s", exc.running_again("campaign"))
                if recording is not None:  # the recording starts again with the campaign
                    recording.close()
                    recording.stop_serving()
                    observer, recording = open_observer(record, recording_id(s))
        clock = make_clock(s)
        return clock.run(run_async(s, clock, journal, external_devices, on_progress, observer,
                                   handle_signals=handle_signals, make_journal=make_journal))
    except BaseException:
        if claimed and Path(journal).exists() and not Path(journal).stat().st_size:
            Path(journal).unlink()  # nothing was written: the name goes back
        raise
    finally:
        if recording is not None:
            recording.close()
            recording.stop_serving()


def check_runtime(runtime: str, why_not: str, what: str = "campaign") -> None:
    """``runtime`` is one there is, and the fast one is asked for only where it can run (``why_not``: why not)."""
    if runtime not in RUNTIMES:
        raise TwinError(f"unknown runtime {runtime!r}: use one of {', '.join(RUNTIMES)}")
    if runtime == "fast" and why_not:
        raise ClockError(f"the fast runtime cannot run this {what}: {why_not}. Use --runtime asyncio (or auto).")


def fast_refused(s: Scenario, external_devices: Collection[str] = frozenset(), agent_in_process: bool = False) -> str:
    """Why the fast runtime cannot run ``s`` as asked ('' when it can)."""
    if s.clock.mode != "virtual":
        return f"the clock is {s.clock.mode} (the fast runtime keeps virtual time only)"
    if s.bus.kind != "memory":
        return f"the bus is {s.bus.kind} (the fast runtime passes messages in-process)"
    if external_devices:
        return f"devices {sorted(external_devices)} run in other processes"
    if s.campaign.scheduler == REMOTE or (not agent_in_process and agent_on_bus(s.campaign.scheduler)):
        return "the scheduler is an agent on the bus"
    return ""


def refuse_external(s: Scenario, external_devices: Collection[str]) -> None:
    """Devices served by other processes need a lab they can reach and a clock that sees their messages."""
    if not external_devices:
        return
    people = people_of(s)
    devices = [name for dtype in s.devices for name in s.instance_names(dtype) if name not in people]
    served = sorted(set(external_devices) & set(people))
    if served:
        raise TwinError(f"--external {', '.join(served)}: people (driver: operator), not devices: the campaign "
                        "serves their steps itself (twin ctl pending, twin ctl confirm); leave them out of --external")
    unknown = sorted(set(external_devices) - set(devices))
    if unknown:
        raise TwinError(f"--external {', '.join(unknown)}: not {'a device' if len(unknown) == 1 else 'devices'} of "
                        f"lab {s.lab} (its devices: {', '.join(devices)}; a type of several instances is named by "
                        "each instance)")
    if s.bus.security:
        _refuse_uncertified(s, external_devices)
    if s.clock.mode == "virtual":
        raise ClockError(f"devices {sorted(external_devices)} run in other processes, where a virtual clock cannot "
                         "see messages in flight: use --clock scaled or --clock wall")
    if s.bus.kind == "memory":
        raise TwinError(f"devices {sorted(external_devices)} run in other processes, and the bus is memory (no "
                        "sockets): none of them could join; use --bus zenoh")


def _refuse_uncertified(s: Scenario, external_devices: Collection[str]) -> None:
    """A device the security directory has no certificate for is one the lab's router admits no process serving."""
    root = str(s.bus.security)
    absent = sorted(set(external_devices) - security.devices_of(root, s.lab))
    if absent:
        them = "it" if len(absent) == 1 else "them"
        raise TwinError(f"--external {', '.join(absent)}: {root} has no certificate for {them}, so the lab's router "
                        f"admits no process serving {them}. Add {them} with `twin security init {root} --lab {s.lab} "
                        f"{' '.join('--device ' + d for d in absent)}`, copy the device folders to their hosts, and "
                        f"restart `twin router`, which reads whom it admits when it starts")


def recording_id(s: Scenario) -> str:
    return f"{s.name}-seed{s.campaign.seed}"


def run_fast(s: Scenario, journal_path: str | Path, on_progress: Callable[[CampaignCore], None] | None = None,
             handle_signals: bool = True, make_journal: JournalFactory = Journal,
             observer: LabObserver | None = None, agent_in_process: bool = False) -> Summary:
    """The campaign of ``s`` on the fast runtime (virtual time, in-process devices); ``observer`` is handed
    what the campaign does as it happens; ``agent_in_process``: see ``run``."""
    wall0 = time.perf_counter()
    drivers = load_drivers(s)
    refuse_realtime(drivers)
    planner, scheduler = make_planner(s), make_scheduler(s)
    if getattr(scheduler, "serve_on_bus", False) and not agent_in_process:
        raise FastRuntimeRefused(f"scheduler {s.campaign.scheduler!r} is an agent on the bus, which the fast "
                                 "runtime does not have")
    journal = open_journal(s, journal_path, make_journal)
    checked = CheckedScheduler(scheduler, fallback_for(s), s.campaign.scheduler)
    camp = FastCampaign(s, drivers, journal, planner, checked, on_progress=on_progress, observer=observer)
    with stop_on_signals(camp.stop, handle_signals):
        try:
            camp.run()
        finally:
            try:
                camp.drawing.drain()
            finally:  # an observer that raised does not cost the journal its summary
                summary = finish(camp.core, journal, wall0, camp.now, noted(journal, observer, camp.now),
                                 checked.fallback.count)
    return summary


def noted(journal: Journal, observer: LabObserver | None, now: float) -> Callable[[str, Any], None] | None:
    """How the fast runtime notes the summary: journalled, and shown to an in-process observer."""
    if observer is None:
        return None

    def note(kind: str, detail: Any) -> None:
        journal.event(now, kind, detail=detail)
        observer.on_decision(now, kind, {"info": detail})
        observer.c.flush()
    return note


def refuse_realtime(drivers: list[tuple[str, str, Any]]) -> None:
    realtime = {name: dtype for name, dtype, drv in drivers if feature(drv, "realtime")}
    if realtime:
        dtype = next(iter(realtime.values()))
        names = sorted(realtime)
        who = f"{names[0]} talks to a real instrument, which keeps" if len(names) == 1 else \
            f"{', '.join(names)} talk to real instruments, which keep"
        raise ClockError(f"{who} wall time: use --clock "
                         f"scaled (or wall), or give devices.{dtype}.twin: {{driver: NAME}}, a simulated driver "
                         "that stands in for it on a virtual clock (docs/drivers.md)")


JournalFactory = Callable[[Path], Journal]


def open_journal(s: Scenario, path: str | Path, make_journal: JournalFactory = Journal) -> Journal:
    journal = make_journal(Path(path))
    journal.set("scenario", s.model_dump())
    journal.set("seed", s.campaign.seed)
    first, now = journal.get("provenance"), provenance(s)
    if first is None:
        journal.set("provenance", now)
    else:  # a live campaign resumed: where it came from stays; each resume is added
        resumed = {k: now[k] for k in ("started_utc", "versions", "command")}
        journal.set("provenance", {**first, "resumed": [*first.get("resumed", []), resumed]})
    return journal


def finish(core: CampaignCore, journal: Journal, wall0: float, now: float,
           note: Callable[[str, Any], None] | None = None, fallbacks: int = 0) -> Summary:
    """The summary, journalled (and noted for watchers) the same way by every runtime."""
    summary = from_core(core, journal.label, time.perf_counter() - wall0, journal._seq + 1)
    summary.scheduler_fallbacks = fallbacks
    lab_only = {k: v for k, v in summary.to_dict().items() if k not in WALL_CLOCK_FIELDS}
    if note is not None:
        note("campaign.summary", lab_only)  # wall-clock facts stay out of the stream
    else:
        journal.event(now, "campaign.summary", detail=lab_only)
    journal.set("summary", summary.to_dict())
    journal.close()
    return summary


@contextlib.contextmanager
def stop_on_signals(stop: Callable[[str], None], enabled: bool):
    """SIGINT/SIGTERM stop the campaign cleanly (its journal and summary are written)."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def stopped(sig: int, frame: Any) -> None:
        why = f"interrupted ({signal.Signals(sig).name})"
        stop(why)
        held.interrupt_held(why)  # a driver's call that does not return would keep the stop from ever running

    for sig in previous:
        signal.signal(sig, stopped)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


async def run_async(s: Scenario, clock: LabClock, journal_path: str | Path,
                    external_devices: Collection[str] = frozenset(),
                    on_progress: Callable[[CampaignCore], None] | None = None,
                    observer: LabObserver | None = None, scheduler: Any = None,
                    on_start: Callable[[LiveCampaign], None] | None = None, handle_signals: bool = True,
                    make_journal: JournalFactory = Journal, rebuilt: Rebuilt | None = None,
                    planner: Any = None) -> Summary:
    """The campaign of ``s`` on the asyncio runtime; ``scheduler`` and ``planner`` replace the scenario's.

    ``handle_signals``: SIGINT/SIGTERM stop the campaign cleanly (off for the campaigns a training
    loop runs, where Ctrl-C must stop the training).
    """
    refuse_external(s, external_devices)
    wall0 = time.perf_counter()
    drivers = load_drivers(s, skip=set(external_devices))  # bad drivers fail before the bus opens
    if clock.is_virtual:
        refuse_realtime(drivers)
    planner, scheduler = planner or make_planner(s), scheduler or make_scheduler(s)
    result: dict[str, Summary] = {}
    # each resource is released by the stack, in reverse order, however the campaign ends
    async with contextlib.AsyncExitStack() as stack:
        bus = make_bus(s, clock)
        await bus.start()
        stack.push_async_callback(bus.close)
        stack.callback((await refuse_if_taken(bus, s, [name for name, _, _ in drivers])).close)
        say_where(s, bus.listening, clock)
        if s.bus.kind != "memory":  # before anything is dispatched: a joined device stamps in the lab's time
            source = LabTimeSource(bus, s.lab, clock)
            source.start()
            stack.callback(source.close)
        checked = None if scheduler == REMOTE or getattr(scheduler, "serve_on_bus", False) else \
            CheckedScheduler(scheduler, fallback_for(s), s.campaign.scheduler)
        scheduler, service = live_scheduler(s, checked or scheduler, bus, clock)
        journal = open_journal(s, journal_path, make_journal)
        journal.set("external", sorted(external_devices))
        camp = LiveCampaign(s, bus, clock, journal, planner, scheduler, on_progress=on_progress, rebuilt=rebuilt,
                            observer=observer)
        remote = scheduler if isinstance(scheduler, RemoteScheduler) else None
        stack.callback(lambda: result.setdefault("summary", finish(
            camp.core, journal, wall0, clock.now(), camp.note, sum(rule.count for rule in fallbacks(scheduler)))))
        if isinstance(scheduler, RemoteScheduler | OffLoopScheduler):
            stack.callback(scheduler.close)
        if service is not None:
            stack.callback(service.stop)
        try:
            for actor in build_actors(s, drivers, bus, clock):
                await actor.start()
                stack.push_async_callback(actor.stop)
        except TwinError as exc:  # the journal's summary says why the lab never ran
            camp.never_started(str(exc))
            raise
        if external_devices:
            stack.callback(ServedCheck(bus, s, clock, external_devices,
                                       lambda kind, device, detail: camp.note(kind, detail, device),
                                       s.orchestrator.startup_s).start().close)
        if handle_signals:
            stack.enter_context(stop_on_loop_signals(camp.stop))
        if observer is not None and not clock.is_virtual:
            stack.callback(asyncio.ensure_future(flush_live(clock, observer)).cancel)
        if on_start is not None:
            on_start(camp)
        if remote is not None and service is None:
            await _await_agent(remote, s, camp)
        await camp.run()
    return result["summary"]


@contextlib.contextmanager
def stop_on_loop_signals(stop: Callable[[str], None]) -> Iterator[None]:
    """SIGINT/SIGTERM stop the campaign cleanly, through the running loop."""
    loop = asyncio.get_running_loop()
    added = []
    for sig, name in ((signal.SIGINT, "SIGINT"), (signal.SIGTERM, "SIGTERM")):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop, f"interrupted ({name})")
            added.append(sig)
            # the loop runs ``stop`` when it next has control; a driver's call that does not return keeps it from
            # ever having it, so the handler that signal calls in this thread ends such a call too
            signal.signal(sig, lambda *_, n=name: held.interrupt_held(f"interrupted ({n})"))
    interrupts = getattr(loop, "on_interrupt", [])  # on a thread of its own (twin.run in a notebook)

    def interrupted() -> None:
        stop("interrupted (SIGINT)")

    interrupts.append(interrupted)
    try:
        yield
    finally:
        interrupts.remove(interrupted)
        for sig in added:
            loop.remove_signal_handler(sig)


async def _await_agent(remote: RemoteScheduler, s: Scenario, camp: LiveCampaign) -> None:
    if not await remote.wait_present(s.orchestrator.startup_s):
        there = ", ".join(repr(lab) for lab in sorted(remote.elsewhere)[:6])
        log.warning("no scheduler agent on the bus after %.0f lab-s: %s decides%s", s.orchestrator.startup_s,
                    s.campaign.fallback_scheduler,
                    f" (one is on it for lab {there}: an agent served with another lab file, or one of your own "
                    f"that puts another lab than {s.lab!r} in its keys, docs/wire.md)" if there else "")
        camp.note("scheduler.missing", s.campaign.fallback_scheduler)


async def flush_live(clock: LabClock, observer: LabObserver | SharedLabObserver, wall_s: float = 0.25) -> None:
    """A live viewer sees the campaign at most ``wall_s`` late."""
    while True:
        await clock.sleep(wall_s * clock.speed)
        observer.c.flush()
