"""Build a lab from a scenario and run its campaign: the Python API under ``twin run``."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import threading
import time
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any

from twin.core import plugins
from twin.device.actor import DeviceActor
from twin.core.bus import Bus, open_bus, security
from twin.core.bus.security import Identity
from twin.core.clock import LabClock
from twin.device.driver import DRIVER_API, DriverSetup, capabilities, feature
from twin.core.errors import BusError, ClockError, DriverError, PluginError, TwinError
from twin.campaign.journal import Journal
from pydantic import ValidationError

from twin.campaign import CampaignCore
from twin.campaign.replay import Rebuilt
from twin.runtime import FastCampaign, LiveCampaign
from twin.runtime.fast_device import FastRuntimeRefused
from twin.runtime.labtime import LabTimeSource
from twin.runtime.off_loop import OffLoopScheduler
from twin.runtime.checked_scheduler import CheckedScheduler, fallbacks
from twin.runtime.remote_scheduler import Fallback, RemoteScheduler, SchedulerService
from twin.runtime.run_record import provenance
from twin.campaign.human import DRIVER as HUMAN
from twin.scenario import Scenario, load, parse_overridden
from twin.view.observer import LabObserver
from twin.campaign.summary import Summary, from_core
from twin.view.lab_observer import SharedLabObserver
from twin.view.watch import RecordOptions, open_observer

log = logging.getLogger(__name__)


def prepare(scenario: str | Path | Scenario, *, seed: int | None = None, clock: str | None = None,
            speed: float | None = None, bus: str | None = None,
            overrides: dict[str, Any] | None = None, lab_only: bool = False) -> Scenario:
    """Load a scenario and apply the command line's overrides. ``lab_only``: a lab whose campaigns come later
    (``twin lab serve``), or a device of it, needs no workflow."""
    extra = dict(overrides or {})
    if seed is not None:
        extra["campaign.seed"] = seed
    if clock is not None:
        extra["clock.mode"] = clock
    if speed is not None:
        extra["clock.speed"] = speed
    if bus is not None:
        extra["bus.kind"] = bus
    if isinstance(scenario, Scenario):
        if not extra:
            return scenario
        quick = _with_fields(scenario, extra)
        if quick is not None:
            return quick
        # what was set only: a campaign of a lab that never gave its own seed must still run on the lab's plus
        # its place (a full dump made every default look given, and every variant's campaigns ran on seed 0)
        return parse_overridden(scenario.model_dump(exclude_unset=True), extra,
                                f"{scenario.name} with {', '.join(extra)}", lab_only)
    return load(scenario, extra, lab_only)


_SIMPLE = ("campaign", "clock", "bus")  # sections whose fields no cross-field check of Scenario reads


def _with_fields(s: Scenario, extra: dict[str, Any]) -> Scenario | None:
    """``s`` with plain fields of its campaign, clock or bus replaced, re-validating only those sections
    (a reset of a training env does this; the whole scenario costs ~20× more). None: take the long way."""
    sections: dict[str, dict[str, Any]] = {}
    for dotted, value in extra.items():
        section, _, leaf = dotted.partition(".")
        if section not in _SIMPLE or not leaf or "." in leaf:
            return None
        sections.setdefault(section, {})[leaf] = value
    update = {}
    for section, fields in sections.items():
        sub = getattr(s, section)
        try:
            update[section] = type(sub).model_validate({**sub.model_dump(), **fields})
        except ValidationError:
            return None  # the long way names the field
    return s.model_copy(update=update)


def make_clock(s: Scenario) -> LabClock:
    return LabClock(s.clock.mode, s.clock.speed)


def make_bus(s: Scenario, clock: LabClock, who: Identity | None = None) -> Bus:
    """The bus of ``s`` for ``who`` (the lab's orchestrator unless said otherwise): with ``bus.security``, a
    client of the lab's router over mutual TLS with ``who``'s certificate; without it, loopback unless
    ``bus.insecure``."""
    if s.bus.kind == "memory":
        return open_bus("memory", clock)
    extra, mode, listen = dict(s.bus.zenoh), s.bus.mode, s.bus.listen
    if s.bus.security:
        who = who or Identity("orchestrator", s.lab)
        plain = [e for e in s.bus.connect if not e.startswith(("tls/", "quic/"))]
        if not s.bus.connect or plain:
            raise BusError(f"bus.security is on: connect to the lab's router over TLS (bus.connect: "
                           f"[tls/HOST:PORT], where `twin router --security DIR` listens), not {s.bus.connect}")
        extra.update(security.session_config(s.bus.security, who))
        mode, listen = "client", []
    for warning in security.check_listen(listen, secure=bool(s.bus.security), insecure=s.bus.insecure,
                                         what="bus.listen"):
        log.warning("%s", warning)
    return open_bus("zenoh", clock, mode=mode, listen=listen, connect=s.bus.connect, lease_ms=s.bus.lease_ms,
                    extra=extra, connect_timeout_ms=s.bus.connect_timeout_ms)


def load_driver(s: Scenario, device_type: str, name: str) -> Any:
    spec = s.devices[device_type]
    cls = plugins.load("devices", spec.driver)
    api = feature(cls, "labtwin_api") or DRIVER_API
    if api != DRIVER_API:
        raise DriverError(f"devices.{device_type}.driver: {spec.driver!r} was written for driver API {api}; this "
                          f"labtwin speaks {DRIVER_API}. Install a matching version of the driver or of labtwin.")
    models = feature(cls, "chemistry_models")
    if models is not None and s.chemistry.model not in models:
        raise DriverError(f"chemistry.model: the {spec.driver!r} driver of devices.{device_type} simulates "
                          f"{sorted(models)}, not {s.chemistry.model[:64]!r}: use one of those, or a driver of yours")
    setup = DriverSetup(name, device_type, spec.options, s.chemistry, spec.duration, s.campaign.seed)
    try:
        driver = cls(setup)
    except Exception as exc:
        raise DriverError(f"driver {spec.driver!r} for {name} failed to start: {exc}") from exc
    caps = capabilities(driver, f"devices.{device_type}.driver: {spec.driver!r}")
    missing = set(spec.steps) - caps
    if missing:
        raise DriverError(
            f"devices.{device_type}.driver: {spec.driver!r} runs {sorted(caps)}, "
            f"but the scenario asks it for {sorted(missing)}"
        )
    return driver


def load_drivers(s: Scenario, only: set[str] | None = None, skip: Collection[str] = frozenset()) -> list[tuple[str, str, Any]]:
    """(instance, device type, driver) for each device this process serves (people, ``driver: operator``, are
    served by the campaign itself: twin/campaign/human.py)."""
    return [
        (name, dtype, load_driver(s, dtype, name))
        for dtype in s.devices
        for name in s.instance_names(dtype)
        if name not in skip and (only is None or name in only) and s.devices[dtype].driver != HUMAN
    ]


def build_actors(s: Scenario, drivers: list[tuple[str, str, Any]], bus: Bus, clock: LabClock,
                 per_campaign: dict[str, dict[str, Any]] | None = None) -> list[DeviceActor]:
    """``per_campaign``: a lab of several campaigns — each instance's driver for each campaign's chemistry."""
    return [DeviceActor(name, s.devices[dtype], drv, bus, clock, s.lab, s.campaign.seed, s.orchestrator.orphan_grace_s,
                        (per_campaign or {}).get(name))
            for name, dtype, drv in drivers]


def make_planner(s: Scenario) -> Any:
    name, options = plugins.with_policy("planners", s.campaign.planner)
    cls = plugins.load("planners", name)
    if not s.chemistry.parameters and getattr(cls, "needs_parameters", True):
        raise PluginError(f"chemistry.parameters: empty, and planner {s.campaign.planner!r} proposes values for "
                          "parameters: give at least one parameter with low and high")
    try:
        return cls(parameters=s.chemistry.parameters, seed=s.campaign.seed, targets=s.chemistry.targets,
                   budget=s.campaign.budget, **{**options, **s.campaign.planner_options})
    except TwinError:
        raise
    except Exception as exc:
        raise PluginError(f"planner {s.campaign.planner!r} failed to start: {type(exc).__name__}: {exc}") from exc


REMOTE = "remote"  # campaign.scheduler: an agent served elsewhere (`twin scheduler serve`)


def make_scheduler(s: Scenario, spec: str | None = None) -> Any:
    """The scheduler named by ``spec`` (default: the scenario's); ``REMOTE`` for an agent elsewhere."""
    spec = spec or s.campaign.scheduler
    if spec == REMOTE:
        return REMOTE
    name, options = plugins.with_policy("schedulers", spec)
    cls = plugins.load("schedulers", name)
    try:
        return cls(scenario=s, seed=s.campaign.seed, **options)
    except TwinError:
        raise
    except Exception as exc:
        raise PluginError(f"scheduler {spec!r} failed to start: {exc}") from exc


def live_scheduler(s: Scenario, chosen: Any, bus: Bus, clock: LabClock,
                   in_process: bool = False) -> tuple[Any, SchedulerService | None]:
    """An agent scheduler (``serve_on_bus``, or ``remote``) is asked over the bus, with the fallback rule;
    ``in_process``: asked here even so (a lab's one scheduler), in a worker thread past its deadline."""
    deadline = s.campaign.scheduler_deadline_ms / 1000 * (1.0 if clock.is_virtual else clock.speed)
    if chosen != REMOTE and (in_process or not getattr(chosen, "serve_on_bus", False)):
        if clock.is_virtual:  # time stands still while it thinks
            return chosen, None
        return OffLoopScheduler(chosen, _fallback(s), deadline), None
    service = None
    if chosen != REMOTE:
        service = SchedulerService(bus, s.lab, chosen)
        service.start()
    return RemoteScheduler(bus, s.lab, _fallback(s), deadline), service


def _fallback(s: Scenario) -> Fallback:
    return Fallback(make_scheduler(s, s.campaign.fallback_scheduler), s.campaign.fallback_scheduler)


WALL_CLOCK_FIELDS = ("wall_s", "journal", "decision_ms")  # differ between identical runs
RUNTIMES = ("auto", "fast", "asyncio")


def default_journal(s: Scenario) -> Path:
    return Path("runs") / f"{s.name}-seed{s.campaign.seed}-{time.strftime('%Y%m%d-%H%M%S')}.db"


def run(scenario: str | Path | Scenario, *, journal: str | Path | None = None,
        external_devices: Collection[str] = frozenset(),
        on_progress: Callable[[CampaignCore], None] | None = None,
        record: RecordOptions | None = None, observer: LabObserver | None = None, runtime: str = "auto",
        make_journal: JournalFactory = Journal, agent_in_process: bool = False, **overrides: Any) -> Summary:
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
    """
    s = prepare(scenario, **overrides)
    why_not = fast_refused(s, external_devices, agent_in_process)
    if runtime not in RUNTIMES:
        raise TwinError(f"unknown runtime {runtime!r}: use one of {', '.join(RUNTIMES)}")
    if runtime == "fast" and why_not:
        raise ClockError(f"the fast runtime cannot run this campaign: {why_not}. Use --runtime asyncio (or auto).")
    recording = None
    if record is not None and record.wanted and observer is None:
        observer, recording = open_observer(record, recording_id(s))
        for message in recording.messages:
            log.warning("%s", message)
    try:
        if runtime == "fast" or (runtime == "auto" and not why_not):
            try:
                return run_fast(s, journal or default_journal(s), on_progress, make_journal=make_journal,
                                observer=observer, agent_in_process=agent_in_process)
            except FastRuntimeRefused as exc:
                if runtime == "fast":
                    raise
                log.warning("%s — running the campaign again, from the start, on the asyncio runtime", exc)
                if recording is not None:  # the recording starts again with the campaign
                    recording.close()
                    recording.stop_serving()
                    observer, recording = open_observer(record, recording_id(s))
        clock = make_clock(s)
        return clock.run(run_async(s, clock, journal or default_journal(s), external_devices, on_progress, observer,
                                   make_journal=make_journal))
    finally:
        if recording is not None:
            recording.close()
            recording.stop_serving()


def fast_refused(s: Scenario, external_devices: Collection[str] = frozenset(), agent_in_process: bool = False) -> str:
    """Why the fast runtime cannot run ``s`` as asked ('' when it can)."""
    if s.clock.mode != "virtual":
        return f"the clock is {s.clock.mode} (the fast runtime keeps virtual time only)"
    if s.bus.kind != "memory":
        return f"the bus is {s.bus.kind} (the fast runtime passes messages in-process)"
    if external_devices:
        return f"devices {sorted(external_devices)} run in other processes"
    if s.campaign.scheduler == REMOTE or (not agent_in_process and _agent_on_bus(s.campaign.scheduler)):
        return "the scheduler is an agent on the bus"
    return ""


def _agent_on_bus(spec: str) -> bool:
    """Whether the scheduler ``spec`` names sits on the bus (the rl agent), known from its class."""
    try:
        return bool(getattr(plugins.load("schedulers", plugins.with_policy("schedulers", spec)[0]), "serve_on_bus",
                            False))
    except TwinError:
        return False  # an unknown scheduler is reported, with the installed ones, when it is made


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
                                 "runtime does not have: use --runtime asyncio")
    journal = open_journal(s, journal_path, make_journal)
    checked = CheckedScheduler(scheduler, _fallback(s), s.campaign.scheduler)
    camp = FastCampaign(s, drivers, journal, planner, checked, on_progress=on_progress, observer=observer)
    with _stop_on_signals(camp.stop, handle_signals):
        try:
            camp.run()
        finally:
            summary = finish(camp.core, journal, wall0, camp.now, _noted(journal, observer, camp.now),
                             checked.fallback.count)
    return summary


def _noted(journal: Journal, observer: LabObserver | None, now: float) -> Callable[[str, Any], None] | None:
    """How the fast runtime notes the summary: journalled, and shown to an in-process observer."""
    if observer is None:
        return None

    def note(kind: str, detail: Any) -> None:
        journal.event(now, kind, detail=detail)
        observer.on_decision(now, kind, {"info": detail})
        observer.c.flush()
    return note


def refuse_realtime(drivers: list[tuple[str, str, Any]]) -> None:
    realtime = [name for name, _, drv in drivers if feature(drv, "realtime")]
    if realtime:
        raise ClockError(f"devices {realtime} talk to real instruments, which keep wall time: "
                         "use --clock scaled (or wall)")


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
def _stop_on_signals(stop: Callable[[str], None], enabled: bool):
    """SIGINT/SIGTERM stop the campaign cleanly (its journal and summary are written)."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig, name in ((signal.SIGINT, "SIGINT"), (signal.SIGTERM, "SIGTERM")):
        signal.signal(sig, lambda *_, n=name: stop(f"interrupted ({n})"))
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
                    make_journal: JournalFactory = Journal, rebuilt: Rebuilt | None = None) -> Summary:
    """The campaign of ``s`` on the asyncio runtime; ``scheduler`` replaces the scenario's.

    ``handle_signals``: SIGINT/SIGTERM stop the campaign cleanly (off for the campaigns a training
    loop runs, where Ctrl-C must stop the training).
    """
    if external_devices and clock.is_virtual:
        raise ClockError(
            f"devices {sorted(external_devices)} run in other processes, where a virtual clock cannot "
            "see messages in flight: use --clock scaled or --clock wall"
        )
    wall0 = time.perf_counter()
    drivers = load_drivers(s, skip=set(external_devices))  # bad drivers fail before the bus opens
    if clock.is_virtual:
        refuse_realtime(drivers)
    planner, scheduler = make_planner(s), scheduler or make_scheduler(s)
    result: dict[str, Summary] = {}
    # each resource is released by the stack, in reverse order, however the campaign ends
    async with contextlib.AsyncExitStack() as stack:
        bus = make_bus(s, clock)
        await bus.start()
        stack.push_async_callback(bus.close)
        if s.bus.kind != "memory":  # before anything is dispatched: a joined device stamps in the lab's time
            source = LabTimeSource(bus, s.lab, clock)
            source.start()
            stack.callback(source.close)
        checked = None if scheduler == REMOTE or getattr(scheduler, "serve_on_bus", False) else \
            CheckedScheduler(scheduler, _fallback(s), s.campaign.scheduler)
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
        for actor in build_actors(s, drivers, bus, clock):
            await actor.start()
            stack.push_async_callback(actor.stop)
        if handle_signals:
            stack.enter_context(_stop_on_loop_signals(camp.stop))
        if observer is not None and not clock.is_virtual:
            stack.callback(asyncio.ensure_future(_flush_live(clock, observer)).cancel)
        if on_start is not None:
            on_start(camp)
        if remote is not None and service is None:
            await _await_agent(remote, s, camp)
        await camp.run()
    return result["summary"]


@contextlib.contextmanager
def _stop_on_loop_signals(stop: Callable[[str], None]) -> Iterator[None]:
    """SIGINT/SIGTERM stop the campaign cleanly, through the running loop."""
    loop = asyncio.get_running_loop()
    added = []
    for sig, name in ((signal.SIGINT, "SIGINT"), (signal.SIGTERM, "SIGTERM")):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop, f"interrupted ({name})")
            added.append(sig)
    try:
        yield
    finally:
        for sig in added:
            loop.remove_signal_handler(sig)


async def _await_agent(remote: RemoteScheduler, s: Scenario, camp: LiveCampaign) -> None:
    if not await remote.wait_present(s.orchestrator.startup_s):
        log.warning("no scheduler agent on the bus after %.0f lab-s: %s decides", s.orchestrator.startup_s,
                    s.campaign.fallback_scheduler)
        camp.note("scheduler.missing", s.campaign.fallback_scheduler)


async def _flush_live(clock: LabClock, observer: LabObserver | SharedLabObserver, wall_s: float = 0.25) -> None:
    """A live viewer sees the campaign at most ``wall_s`` late."""
    while True:
        await clock.sleep(wall_s * clock.speed)
        observer.c.flush()
