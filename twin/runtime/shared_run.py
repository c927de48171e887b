"""Run a lab that serves several campaigns (a scenario with ``campaigns:``) and summarise each and all."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Collection
from typing import Any
from pathlib import Path

from twin.campaign.events import ALERT_LOGGER, Note, alert_text
from twin.campaign.sharing import SharedLab
from twin.campaign.summary import LabSummary, Summary
from twin.core.clock import LabClock
from twin.core.errors import ClockError, DriverError, PluginError, TwinError
from twin.runtime.asked_of_people import say_where
from twin.runtime.fast_device import FastRuntimeRefused
from twin.runtime.fast_lab import FastLab
from twin.runtime.lab_claim import refuse_if_taken
from twin.campaign.journal import Journal
from twin.campaign.lab_replay import RebuiltLab
from twin.runtime.assembly import (REMOTE, agent_on_bus, build_actors, fallback_for, live_scheduler, load_drivers,
                                   make_bus, make_clock, make_planner, make_scheduler)
from twin.runtime.lab import (FALLBACK_LOGGER, JournalFactory, check_runtime, default_journals, finish, flush_live,
                              given_back, noted, open_journal, prepare, refuse_external, refuse_realtime,
                              stop_on_loop_signals, stop_on_signals)
from twin.runtime.checks import check_campaign
from twin.runtime.checked_scheduler import CheckedScheduler, fallbacks
from twin.runtime.labtime import LabTimeSource
from twin.runtime.live_lab import LiveLab
from twin.runtime.served_devices import ServedCheck
from twin.runtime.standby import standby_drivers
from twin.core import plugins
from twin.scenario import Scenario
from twin.scenario.sharing import campaign_scenarios
from twin.view.lab_observer import SharedLabObserver


LAB_INPUTS = "lab.inputs"  # beside the campaigns' journals: what a live lab was given (twin.campaign.lab_replay)


def run_lab(scenario: str | Path | Scenario | dict[str, Any], *, journals: str | Path | None = None,
            runtime: str = "auto", handle_signals: bool = True, **overrides: Any) -> LabSummary:
    """Run a lab of several campaigns (a scenario with ``campaigns:``) to its end, as ``twin run`` does, and
    return its ``LabSummary`` (each campaign's ``Summary`` in ``.campaigns``). ``journals``: the directory of the
    campaigns' journals (default ``runs/<lab>-seed<N>-<time>/``); ``overrides`` as ``twin.run`` takes them."""
    s = prepare(scenario, **overrides)
    if not s.campaigns:
        raise TwinError(f"{s.name} is one campaign (no campaigns: list): twin.run runs it")
    return run_shared(s, journals, handle_signals=handle_signals, runtime=runtime)


def run_shared(s: Scenario, journals: str | Path | None = None, handle_signals: bool = True,
               external_devices: Collection[str] = frozenset(),
               observer: SharedLabObserver | None = None, make_journal: JournalFactory = Journal,
               runtime: str = "auto", reopen: Callable[[], SharedLabObserver] | None = None,
               agent_in_process: bool = False) -> LabSummary:
    """Every campaign of ``s`` on its shared lab; each writes ``<journals>/<campaign>.db``. Virtual time on the
    fast runtime (``runtime`` auto or fast; auto runs the lab again on the asyncio runtime if a driver needs it,
    with a new observer from ``reopen``); a scaled or wall clock, or ``runtime`` asyncio, on the asyncio runtime,
    over the scenario's bus, with ``external_devices`` served by other processes (``twin device serve``).
    ``observer`` (``open_lab_observer``) is handed what the lab and each campaign do as it happens.
    ``agent_in_process``: a campaign's scheduler that is an agent on the bus (rl) is asked in this process, as
    ``run`` asks one in benches and what-if; otherwise it is refused."""
    check_runtime(runtime, "" if s.clock.mode == "virtual" else
                  f"the clock is {s.clock.mode} (the fast runtime keeps virtual time only)", "lab")
    refuse_external(s, external_devices)
    wall0 = time.perf_counter()
    scenarios = campaign_scenarios(s, s.name)
    if not agent_in_process:
        _refuse_agents(scenarios)
    one = _lab_scheduler(s)  # a policy that does not fit the lab is said before a journal is made
    where = Path(journals) if journals is not None else default_journals(s)
    with given_back(where, journals is None):
        return _run_shared(s, scenarios, where, wall0, handle_signals, external_devices, observer, make_journal,
                           runtime, reopen, one)


def _run_shared(s: Scenario, scenarios: dict[str, Scenario], where: Path, wall0: float, handle_signals: bool,
                external_devices: Collection[str], observer: SharedLabObserver | None, make_journal: JournalFactory,
                runtime: str, reopen: Callable[[], SharedLabObserver] | None, one: Any) -> LabSummary:

    def lab_drivers() -> tuple[list, dict]:
        """The lab's drivers, made afresh."""
        drivers, per_device = shared_drivers(scenarios, skip=external_devices)
        if s.clock.mode == "virtual":
            refuse_realtime(drivers)
        return drivers, per_device

    def campaign_parts() -> dict:
        """Each campaign's journal, planner and scheduler."""
        where.mkdir(parents=True, exist_ok=True)
        return {name: _parts(cs, where / f"{name}.db", external_devices, s, make_journal)
                for name, cs in scenarios.items()}

    drivers, per_device = lab_drivers()
    if s.clock.mode == "virtual" and runtime != "asyncio":
        parts = campaign_parts()
        try:
            return _fast(s, scenarios, drivers, per_device, parts, where, wall0, handle_signals, observer, one)
        except FastRuntimeRefused as exc:
            if runtime == "fast":
                raise
            logging.getLogger(FALLBACK_LOGGER).warning("%s", exc.running_again("lab"))
        for journal, _, _ in parts.values():
            journal.close()
        drivers, per_device = lab_drivers()  # the first run's drivers hold its state
        if observer is not None and reopen is not None:  # the recording starts again with the lab
            observer = reopen()
    clock = make_clock(s)
    return clock.run(_live(s, clock, scenarios, drivers, per_device, campaign_parts, where, wall0, handle_signals,
                           observer=observer, external=external_devices))


def _fast(s: Scenario, scenarios: dict[str, Scenario], drivers: list, per_device: dict, parts: dict, where: Path,
          wall0: float, handle_signals: bool, observer: SharedLabObserver | None, one: Any) -> LabSummary:
    lab = FastLab(s, scenarios, drivers, per_device, parts, observer=observer, lab_scheduler=one)
    with stop_on_signals(lab.stop, handle_signals):
        try:
            lab.run()
        finally:
            try:
                lab.drawing.drain()
            finally:  # an observer that raised does not cost the journals their summaries
                notes = {n: noted(parts[n][0], observer.campaign(n), lab.now) for n in parts} if observer else None
                summaries = lab_summaries(lab.shared, parts, wall0, lab.now, notes)
    return lab_summary(s, lab.shared, summaries, where, time.perf_counter() - wall0)


def serve_lab(s: Scenario, journals: str | Path | None = None, external_devices: Collection[str] = frozenset(),
              handle_signals: bool = True, on_start: Callable[[Any], None] | None = None,
              trust_modules: bool = False) -> LabSummary:
    """``twin lab serve``: the lab's devices and the campaigns of its file, taking more as they are submitted
    (``twin submit``), until it is stopped (Ctrl-C, SIGTERM). A lab file without campaigns gives the chemistry
    its simulated devices simulate by default. ``trust_modules``: a submitted campaign may name
    'package.module:Class' plugins the lab file does not, and files outside the folder the lab serves from."""
    if s.clock.mode == "virtual":
        raise ClockError(f"{s.name}: a lab that serves waits for campaigns in real time: use --clock scaled or wall")
    refuse_external(s, external_devices)
    _lab_scheduler(s)  # a scheduler that cannot start is said before anything does
    wall0 = time.perf_counter()
    scenarios = campaign_scenarios(s, s.name)
    _refuse_agents(scenarios)
    if scenarios:
        drivers, per_device = shared_drivers(scenarios, skip=external_devices)
    else:
        drivers, per_device = standby_drivers(s, external_devices), {}
    where = Path(journals) if journals is not None else default_journals(s)

    def campaign_parts() -> dict:
        where.mkdir(parents=True, exist_ok=True)
        return {name: _parts(cs, where / f"{name}.db", external_devices, s) for name, cs in scenarios.items()}

    clock = make_clock(s)
    with given_back(where, journals is None):
        return clock.run(_live(s, clock, scenarios, drivers, per_device, campaign_parts, where, wall0, handle_signals,
                               serving=external_devices, on_start=on_start, trust_modules=trust_modules))


def _lab_scheduler(s: Scenario) -> Any:
    """The one scheduler of a lab whose ``orchestrator.lab_scheduler`` is set (made for the lab file: a policy
    checks that it fits every campaign's steps), or None."""
    spec = s.orchestrator.lab_scheduler
    if not spec:
        return None
    chosen = make_scheduler(s, spec)
    if chosen == REMOTE:
        raise ClockError(f"{s.name}: orchestrator.lab_scheduler {spec!r} is an agent elsewhere; the lab's one "
                         "scheduler runs in its process (a rule, or rl:POLICY)")
    # an rl policy is asked in-process, as the fast runtime's benches ask it
    return CheckedScheduler(chosen, fallback_for(s), spec)


def _refuse_agents(scenarios: dict[str, Scenario]) -> None:
    agents = {n: cs.campaign.scheduler for n, cs in scenarios.items() if agent_on_bus(cs.campaign.scheduler)}
    if agents:
        spec = next(iter(agents.values()))
        raise ClockError(f"campaigns {list(agents)}: their scheduler ({spec}) is an agent on the bus, which serves "
                         f"one campaign; in a lab of several, a policy schedules as the lab's one scheduler, seeing "
                         f"every campaign's steps (--set orchestrator.lab_scheduler={spec}), or give each campaign "
                         f"a rule (fifo, mwkr, ...)")


_PLUGIN_FIELDS = (("planner", "planners"), ("scheduler", "schedulers"), ("fallback_scheduler", "schedulers"))


def module_plugins(cs: Scenario) -> dict[str, str]:
    """The campaign's fields that name a 'package.module:Class' plugin (not an installed name, nor rl:POLICY)."""
    specs = {f"campaign.{field}": (kind, getattr(cs.campaign, field)) for field, kind in _PLUGIN_FIELDS}
    return {field: spec for field, (kind, spec) in specs.items() if ":" in plugins.with_policy(kind, spec)[0]}


def refuse_module_plugins(name: str, cs: Scenario, trusted: Collection[str]) -> None:
    """A submitted campaign names installed plugins (or those ``trusted``: the lab file's own): a module path
    would have the lab import, and run, whatever module anyone who can submit names."""
    for field, spec in module_plugins(cs).items():
        if spec not in trusted:
            raise PluginError(
                f"campaign {name}: {field}: {spec!r} is a module path, which the lab would import for whoever "
                "submitted it; a submitted campaign names installed plugins (an entry point: docs/plugins.md, "
                "'Installed by name') or the ones the lab file names. Where everyone who can submit is trusted, "
                "serve the lab with --trust-modules")


def submitted_files(cs: Scenario) -> dict[str, str]:
    """The campaign's strings a plugin may open as files: each ``rl:PATH``'s policy, and every string of
    ``campaign.planner_options`` (a policy, a route planner's stock and templates), ``scheduler_options`` and
    ``chemistry.options``, by field."""
    out = {f"campaign.{field}": options["policy"] for field, kind in _PLUGIN_FIELDS
           if "policy" in (options := plugins.with_policy(kind, getattr(cs.campaign, field))[1])}

    def walk(field: str, value: Any) -> None:
        if isinstance(value, str):
            out[field] = value
        elif isinstance(value, dict):
            for key, item in value.items():
                walk(f"{field}.{key}", item)
        elif isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                walk(f"{field}.{i}", item)

    walk("campaign.planner_options", cs.campaign.planner_options)
    walk("campaign.scheduler_options", cs.campaign.scheduler_options)
    walk("chemistry.options", cs.chemistry.options)
    return out


def _outside(value: str, root: Path) -> bool:
    """Whether ``value``, read as a path from ``root`` (plugins open theirs from the working directory), leads
    out of it: absolute elsewhere, up through ``..``, or through a link."""
    try:
        where = Path(value).expanduser()
        return not (where if where.is_absolute() else root / where).resolve().is_relative_to(root)
    except (ValueError, OSError, RuntimeError):  # a NUL in it, a loop of links: no file anyone opens
        return False


def refuse_outside_files(name: str, cs: Scenario, trusted: Collection[str]) -> None:
    """A submitted campaign's files lie in the folder the lab serves from (or are the lab file's own): the lab
    opens them for whoever submitted it, and what a file that is not one says in the refusal (a stock's first line,
    a YAML error's excerpt) goes back to them."""
    root = Path.cwd().resolve()
    for field, value in submitted_files(cs).items():
        if value not in trusted and _outside(value, root):
            raise PluginError(
                f"campaign {name}: {field}: {value[:200]!r} is outside the folder the lab serves from ({root}), which "
                "the lab would open for whoever submitted it; a submitted campaign's files (a policy, a planner's "
                "stock) lie in that folder, or are the ones the lab file names. Where everyone who can submit is "
                "trusted, serve the lab with --trust-modules")


def _parts(s: Scenario, path: Path, external: Collection[str], lab: Scenario | None = None,
           make_journal: JournalFactory = Journal) -> tuple:
    """A campaign's journal (with the lab file it ran in, for ``twin resume`` of the lab), planner and
    scheduler."""
    journal = open_journal(s, path, make_journal)
    journal.set("external", sorted(external))
    if lab is not None:  # what was set only: each campaign's seed is then the lab's plus its place, as it was
        journal.set("lab", lab.model_dump(exclude_unset=True))
    scheduler = make_scheduler(s)
    if scheduler != REMOTE:  # a plugin's mistake is the fallback rule's to cover (logged; the lab goes on)
        scheduler = CheckedScheduler(scheduler, fallback_for(s), s.campaign.scheduler)
    return journal, make_planner(s), scheduler


async def _live(s: Scenario, clock: LabClock, scenarios: dict[str, Scenario], drivers: list, per_device: dict,
                parts: dict | Callable[[], dict], where: Path, wall0: float, handle_signals: bool,
                serving: Collection[str] | None = None, on_start: Callable[[Any], None] | None = None,
                observer: SharedLabObserver | None = None, rebuilt: RebuiltLab | None = None,
                external: Collection[str] = (), trust_modules: bool = False) -> LabSummary:
    """``serving``: None, or the external devices of a lab that takes campaigns as they are submitted;
    ``rebuilt``: a killed lab to take over (``twin resume``); ``trust_modules``: see ``serve_lab``; ``parts``: each
    campaign's, or what makes them (their journals), made once the lab is this process's: a lab refused for
    another process's had replaced the journals in its folder with ones of a run that never began."""
    async with contextlib.AsyncExitStack() as stack:
        bus = make_bus(s, clock)
        await bus.start()
        stack.push_async_callback(bus.close)
        stack.callback((await refuse_if_taken(bus, s, [name for name, _, _ in drivers])).close)
        if serving is None:  # a served lab says it with how to submit a campaign
            say_where(s, bus.listening, clock)
        if callable(parts):
            parts = parts()
        inputs = Journal(where / LAB_INPUTS, append=rebuilt is not None)
        stack.callback(inputs.close)
        if rebuilt is None:
            inputs.set("lab", s.model_dump(exclude_unset=True))
            inputs.set("serving", serving is not None)
            inputs.set("trust_modules", trust_modules)  # a resumed lab takes what it took
            inputs.set("external", sorted(serving if serving is not None else external))
        if s.bus.kind != "memory":
            source = LabTimeSource(bus, s.lab, clock)
            source.start()
            stack.callback(source.close)
        actors = build_actors(s, drivers, bus, clock, per_device)

        def seat_parts(name: str, cs: Scenario, made: tuple) -> tuple:
            return made[0], made[1], live_scheduler(cs, made[2], bus, clock)[0]

        # the lab file's: its campaigns', and its own campaign section's, which a submitted campaign inherits
        trusted = {spec for cs in [s, *scenarios.values()] for spec in module_plugins(cs).values()}
        own_files = {value for cs in [s, *scenarios.values()] for value in submitted_files(cs).values()}

        def admit(name: str, cs: Scenario) -> None:
            _refuse_agents({name: cs})
            if not trust_modules:
                refuse_module_plugins(name, cs, trusted)
                refuse_outside_files(name, cs, own_files)
            check_campaign(cs)

        def adopt(name: str, cs: Scenario) -> tuple:
            admit(name, cs)
            mine = {a.name for a in actors}
            _, per = shared_drivers({name: cs}, only=mine) if mine else ([], {})
            for actor in actors:
                if name in per.get(actor.name, {}):
                    actor.add_campaign(name, per[actor.name][name])
            return seat_parts(name, cs, _parts(cs, where / f"{name}.db", serving or (), s))

        one = _lab_scheduler(s)
        if one is not None:
            one = live_scheduler(s, one, bus, clock, in_process=True)[0]
            if hasattr(one, "close"):
                stack.callback(one.close)
        lab = LiveLab(s, scenarios, bus, clock, {n: seat_parts(n, scenarios[n], p) for n, p in parts.items()},
                      adopt if serving is not None else None, admit if serving is not None else None, observer,
                      inputs, rebuilt, one)
        if observer is not None and not clock.is_virtual:  # a virtual clock has no live viewer to keep up with
            stack.callback(asyncio.ensure_future(flush_live(clock, observer)).cancel)
        try:
            for actor in actors:
                await actor.start()
                stack.push_async_callback(actor.stop)
        except TwinError as exc:  # each campaign's journal says why it never ran (it read as killed)
            lab.shared.stop(str(exc))
            lab_summaries(lab.shared, lab.parts, wall0, clock.now())
            raise
        served = serving if serving is not None else external
        if served:  # a lab's device is every campaign's: said in the log, not in one campaign's journal
            def said(kind: str, device: str, detail: dict[str, Any]) -> None:
                logging.getLogger(ALERT_LOGGER).warning("%s", alert_text(Note(clock.now(), kind, device=device,
                                                                              detail=detail)))

            stack.callback(ServedCheck(bus, s, clock, served, said, s.orchestrator.startup_s).start().close)
        if handle_signals:
            stack.enter_context(stop_on_loop_signals(lab.stop))
        if on_start is not None:
            on_start(lab)
        try:
            await lab.run()
        finally:
            summaries = lab_summaries(lab.shared, lab.parts, wall0, clock.now(),
                                {n: seat.note for n, seat in lab.seats.items()})
            until = clock.now() if serving is not None else 0.0
    return lab_summary(s, lab.shared, summaries, where, time.perf_counter() - wall0, until)


def lab_summaries(shared: SharedLab, parts: dict, wall0: float, now: float,
            notes: dict[str, Callable[[str, Any], None]] | None = None) -> dict[str, Summary]:
    """Each started campaign's summary, journalled; a campaign that never started says why in its journal."""
    summaries = {}
    for name, (journal, _, scheduler) in parts.items():
        if name in shared.started:
            summaries[name] = finish(shared.cores[name], journal, wall0, now, (notes or {}).get(name),
                                     sum(rule.count for rule in fallbacks(scheduler)))
        else:
            journal.event(now, "campaign.not_started", detail=shared.unsubmitted.get(name, "the lab ended first"))
            journal.close()
    return summaries


Drivers = tuple[list[tuple[str, str, Any]], dict[str, dict[str, Any]]]


def shared_drivers(scenarios: dict[str, Scenario], only: set[str] | None = None,
                   skip: Collection[str] = frozenset()) -> Drivers:
    """The drivers of a lab's devices (instance, type, driver), and for each instance the driver that simulates
    each campaign's chemistry. A campaign's workflow types must have one; another type's driver that cannot
    simulate its chemistry is left out (the campaign sends it nothing)."""
    per_device: dict[str, dict[str, Any]] = {}
    first: dict[str, tuple[str, Any]] = {}
    for name, s in scenarios.items():
        used = {w.device for w in s.workflow}
        for dtype in s.devices:
            wanted = {n for n in s.instance_names(dtype) if (only is None or n in only) and n not in skip}
            if not wanted:
                continue
            try:
                loaded = load_drivers(s, only=wanted)
            except DriverError as exc:
                if dtype in used:
                    raise DriverError(f"campaigns.{name}: {exc}") from None
                continue
            for inst, dt, drv in loaded:
                per_device.setdefault(inst, {})[name] = drv
                first.setdefault(inst, (dt, drv))
    return [(inst, dt, drv) for inst, (dt, drv) in first.items()], per_device


def lab_summary(s: Scenario, shared: SharedLab, summaries: dict, where: Path, wall_s: float,
             served_until: float = 0.0) -> LabSummary:
    """``served_until``: a lab that served (``twin lab serve``) counts its hours until it was stopped."""
    ended = {n: shared.cores[n].now / 3600 for n in shared.started}
    hours = max([*ended.values(), served_until / 3600])
    busy: dict[str, float] = {}
    for name in shared.started:
        for dev in shared.cores[name].devices.values():
            busy[dev.name] = busy.get(dev.name, 0.0) + dev.busy_s
    return LabSummary(
        lab=s.name, seed=s.campaign.seed, journals=str(where), lab_hours=hours, campaigns=summaries,
        submitted_h={n: t / 3600 for n, t in shared.submitted_at.items() if n in shared.started},
        ended_h=ended, priority={n: c.priority for n, c in shared.entries.items()},
        owner={n: c.owner for n, c in shared.entries.items()}, not_started=dict(shared.unsubmitted),
        utilisation={d: round(b / max(hours * 3600, 1e-9), 4) for d, b in busy.items()}, wall_s=wall_s)
