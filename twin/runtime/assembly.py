"""From a scenario to the parts of its lab: the scenario with the command line's overrides, its clock and
bus, its device drivers and actors, its planner and its scheduler (with the fallback rule, and over the bus
when it is an agent). ``twin.runtime.lab`` runs a campaign on them; the shared-lab runner and the checks of
``twin validate`` build from them too."""

from __future__ import annotations

import inspect
import logging
from collections.abc import Collection
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from twin.campaign.human import DRIVER as HUMAN
from twin.core import plugins
from twin.core.bus import Bus, open_bus, security
from twin.core.bus.security import Identity
from twin.core.clock import LabClock
from twin.core.errors import PLUGIN_ERRORS, BusError, DriverError, PluginError, ScenarioError, TwinError
from twin.device.actor import DeviceActor
from twin.device.driver import DRIVER_API, DriverSetup, capabilities, feature, talks_to_instrument
from twin.runtime.off_loop import OffLoopScheduler
from twin.runtime.remote_scheduler import Fallback, RemoteScheduler, SchedulerService
from twin.runtime.served_devices import served_as
from twin.scenario import Scenario, load, load_mapping, parse_overridden, plain
from twin.scenario.loading import disagreeing, model_of
from twin.scenario.objective import typical_step

log = logging.getLogger(__name__)


def prepare(scenario: str | Path | Scenario | dict[str, Any], *, seed: int | None = None, clock: str | None = None,
            speed: float | None = None, bus: str | None = None,
            overrides: dict[str, Any] | None = None, lab_only: bool = False, **unknown: Any) -> Scenario:
    """Load a scenario (a file, a ``Scenario``, or the mapping a file would hold) and apply the command line's
    overrides. ``lab_only``: a lab whose campaigns come later (``twin lab serve``), or a device of it, needs no
    workflow."""
    if unknown:
        raise TypeError(unknown_keywords(unknown))
    if overrides is not None and not isinstance(overrides, dict):
        raise TypeError(f"overrides must be a dict of dotted scenario fields, e.g. {{'campaign.budget': 5}} "
                        f"(got {type(overrides).__name__})")
    extra = dict(overrides or {})
    given = {"campaign.seed": ("seed", seed), "clock.mode": ("clock", clock), "clock.speed": ("speed", speed),
             "bus.kind": ("bus", bus)}
    for field in disagreeing({field: value for field, (_, value) in given.items()}, extra)[:1]:
        name, value = given[field]
        raise TypeError(f"{name}={value!r} and overrides[{field!r}]={extra[field]!r} disagree: give one of them")
    if seed is not None:
        extra["campaign.seed"] = seed
    if clock is not None:
        extra["clock.mode"] = clock
    if speed is not None:
        extra["clock.speed"] = speed
    if bus is not None:
        extra["bus.kind"] = bus
    extra = plain(extra)
    if isinstance(scenario, Scenario):
        if not extra:
            return scenario
        shop = next((k for k in extra if k == "jobshop" or k.startswith("jobshop.")), None)
        if shop is not None and scenario.jobshop is not None:  # its shop was read into devices and jobs already
            raise ScenarioError(scenario.name, [f"{shop}: a job shop is read when its scenario file is loaded, and "
                                                f"this one has read {scenario.jobshop.file}; load the file with "
                                                f"{shop} set (`--set {shop}=...`), or compare shops with `twin "
                                                "bench schedulers SCENARIO --jobshop A,B`"])
        quick = _with_fields(scenario, extra)
        if quick is not None:
            return quick
        # what was set only: a campaign of a lab that never gave its own seed must still run on the lab's plus
        # its place (a full dump made every default look given, and every variant's campaigns ran on seed 0)
        return parse_overridden(scenario.model_dump(exclude_unset=True), extra,
                                f"{scenario.name} with {', '.join(extra)}", lab_only)
    if isinstance(scenario, dict):
        return load_mapping(scenario, extra, lab_only)
    return load(scenario, extra, lab_only)


def unknown_keywords(given: dict[str, Any]) -> str:
    """Keywords that are not a run's own: a scenario field given by its leaf name (``budget=5``) is named in full."""
    parts = []
    for name, value in given.items():
        fields = [f"{section}.{name}" for section, info in Scenario.model_fields.items()
                  if name in getattr(model_of(info.annotation), "model_fields", {})]
        hint = (f"; scenario fields go in overrides, e.g. overrides={{{fields[0]!r}: {value!r}}}" if fields else
                "; scenario fields go in overrides={'section.field': value}")
        parts.append(f"unexpected keyword {name!r}{hint}")
    return "; ".join(parts) + " (the keywords are seed, clock, speed, bus and overrides)"


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
    if s.campaigns and set(sections.get("campaign", ())) - {"seed"}:  # campaigns with a section of their own take
        return None  # it too (the lab's seed is only the base of theirs)
    update = {}
    for section, fields in sections.items():
        sub = getattr(s, section)
        try:
            update[section] = type(sub).model_validate({**sub.model_dump(), **fields})
        except ValidationError:
            return None  # the long way names the field
    return s.model_copy(update=update)


#: Wall seconds the asyncio runtime spends per step it runs (messages, timers, the scheduler): measured ~1.6 ms,
#: which a scaled clock turns into speed × that many lab-seconds added to every step.
WALL_PER_STEP_S = 0.002


def _seconds(x: float) -> str:
    return f"{x:,.0f}" if x >= 10 else f"{x:.1f}"


def make_clock(s: Scenario) -> LabClock:
    """The lab's clock; a scaled one so fast that the runtime's own wall time per step would lengthen the lab by
    more than about 1 % is run as asked, with a warning that says so and what to use instead."""
    typical = typical_step(s) if s.clock.mode == "scaled" else None  # None: no steps yet to weigh the speed by
    if typical is not None:
        added = s.clock.speed * WALL_PER_STEP_S
        if added > 0.01 * typical:
            log.warning("clock.speed %g: each step costs the runtime about %.0f ms of wall time, %s lab-s at this "
                        "speed against %s's typical step of %s lab-s, so the lab will run longer than its devices "
                        "do and steps may time out; up to about %s× keeps that near 1 %%, and --clock virtual runs "
                        "a campaign as fast as it can go with exact lab times", s.clock.speed,
                        1000 * WALL_PER_STEP_S, _seconds(added), s.name, _seconds(typical),
                        f"{0.01 * typical / WALL_PER_STEP_S:,.0f}")
    return LabClock(s.clock.mode, s.clock.speed)


def make_bus(s: Scenario, clock: LabClock, who: Identity | None = None, wait_longer: str | None = None) -> Bus:
    """The bus of ``s`` for ``who`` (the lab's orchestrator unless said otherwise): with ``bus.security``, a
    client of the lab's router over mutual TLS with ``who``'s certificate; without it, loopback unless
    ``bus.insecure``. ``wait_longer``: how this command's user gives ``bus.connect`` longer to answer (default: the scenario's
    ``bus.connect_timeout_ms``)."""
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
                    extra=extra, connect_timeout_ms=s.bus.connect_timeout_ms,
                    **({} if wait_longer is None else {"wait_longer": wait_longer}))


def load_driver(s: Scenario, device_type: str, name: str, simulated: bool | None = None) -> Any:
    """The driver of one instance: the type's own, or on a virtual clock (``simulated``, by default) its
    ``twin`` where it has one."""
    spec = s.devices[device_type]
    stand_in = spec.twin if (s.clock.mode == "virtual" if simulated is None else simulated) else None
    driver, given, field = ((stand_in.driver, stand_in.options, f"devices.{device_type}.twin") if stand_in else
                            (spec.driver, spec.options, f"devices.{device_type}"))
    cls = plugins.load("devices", driver)
    api = feature(cls, "labtwin_api") or DRIVER_API
    if api != DRIVER_API:
        raise DriverError(f"{field}.driver: {driver!r} was written for driver API {api}; this "
                          f"labtwin speaks {DRIVER_API}. Install a matching version of the driver or of labtwin.")
    if stand_in and talks_to_instrument(cls):
        raise DriverError(f"{field}.driver: {driver!r} talks to an instrument of its own; a twin must be a "
                          "simulated driver (one that waits with ctx.clock.sleep), such as the built-in ones")
    models = feature(cls, "chemistry_models")
    if models is not None and s.chemistry.model not in models:
        if s.chemistry.model == "none":
            raise DriverError(f"chemistry.model: none given, and the {driver!r} driver of {field} simulates a "
                              f"chemistry: give chemistry.model, one of {sorted(models)}")
        raise DriverError(f"chemistry.model: the {driver!r} driver of {field} simulates "
                          f"{sorted(models)}, not {s.chemistry.model[:64]!r}: use one of those, or a driver of yours")
    names = feature(cls, "option_names")
    if "steps" in (names or ()) and "steps" not in given:  # a driver that runs the steps it is told: the type's
        given = {**given, "steps": sorted(spec.steps)}
    stray = sorted(set(given) - set(names)) if names is not None else []
    if stray:
        raise DriverError(f"{field}.options.{stray[0]}: the {driver!r} driver takes no option "
                          f"{stray[0]!r} (it takes {', '.join(sorted(names)) or 'none'}); check its spelling")
    setup = DriverSetup(name, device_type, given, s.chemistry, spec.duration, s.campaign.seed)
    try:
        instance = cls(setup)
    except PLUGIN_ERRORS as exc:
        said = str(exc) if isinstance(exc, TwinError) else f"{type(exc).__name__}: {exc}"  # KeyError: 'x', not 'x'
        raise DriverError(f"driver {driver!r} for {name} failed to start: {said}{_takes_setup(cls, setup, exc)}"
                          f"{_where_files_are(exc)}") from exc
    caps = capabilities(instance, f"{field}.driver: {driver!r}")
    missing = set(spec.steps) - caps
    if missing:
        raise DriverError(f"{field}.driver: {driver!r} runs {sorted(caps)}, but the scenario asks it for "
                          f"{sorted(missing)}")
    return instance


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
                        (per_campaign or {}).get(name), stop_grace_s=s.orchestrator.cancel_grace_s,
                        served_as=served_as(s, dtype, instrument=talks_to_instrument(drv)))
            for name, dtype, drv in drivers]


def make_planner(s: Scenario) -> Any:
    name, options = plugins.with_policy("planners", s.campaign.planner)
    cls = plugins.load("planners", name)
    if not s.chemistry.parameters and getattr(cls, "needs_parameters", True):
        raise PluginError(f"chemistry.parameters: empty, and planner {s.campaign.planner!r} proposes values for "
                          "parameters: give at least one parameter with low and high, or run a list of experiments "
                          "as given (campaign.planner: fixed, with planner_options: {proposals: [{params: {...}}, "
                          "...]})")
    if options and _options_not_taken(cls, options, PLANNER_ARGUMENTS)[0]:
        raise PluginError(f"campaign.planner: {s.campaign.planner!r}: planner {name!r} reads no policy file; a "
                          f"trained planner is rl:PATH (`--planner rl:{options['policy']}`)")
    try:
        own = _taken(cls, s.campaign.planner_options, PLANNER_ARGUMENTS)
        return constructed(cls, dict(parameters=s.chemistry.parameters, seed=s.campaign.seed,
                                     targets=s.chemistry.targets, budget=s.campaign.budget), {**options, **own})
    except TwinError:
        raise
    except PLUGIN_ERRORS as exc:
        raise PluginError(f"planner {s.campaign.planner!r} failed to start: {type(exc).__name__}: {exc}"
                          + _given(exc, "parameters, seed, targets, budget and planner_options")
                          + _where_files_are(exc)) from exc


PLANNER_ARGUMENTS = frozenset({"parameters", "seed", "targets", "budget"})  # what every planner is given
SCHEDULER_ARGUMENTS = frozenset({"scenario", "seed"})  # what every scheduler is given


def constructed(cls: Any, given: dict[str, Any], options: dict[str, Any]) -> Any:
    """A planner or scheduler: ``cls`` called with the kernel's arguments (``given``) that its constructor takes
    (all of them for a ``**kwargs``; none for a class without ``__init__``) and the scenario's ``options``."""
    try:
        params = inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return cls(**given, **options)
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        given = {k: v for k, v in given.items() if k in params}
    return cls(**given, **options)


def _takes_setup(cls: Any, setup: DriverSetup, exc: BaseException) -> str:
    """For a driver's constructor that cannot take the one argument it is given: what that is (docs/drivers.md)."""
    if not isinstance(exc, TypeError):
        return ""
    try:
        inspect.signature(cls).bind(setup)
    except TypeError:
        return " (a driver's constructor is given one argument, its DriverSetup: `def __init__(self, setup)`; " \
               "docs/drivers.md)"
    except ValueError:  # no signature to read
        pass
    return ""


def _where_files_are(exc: BaseException) -> str:
    """For a plugin that did not find a file it was given: where a scenario's files are looked for."""
    missing = isinstance(exc, FileNotFoundError) or "No such file or directory" in str(exc)
    return (" (a file a scenario gives its plugins is looked for beside the scenario, then in the working "
            "directory)" if missing else "")


def _given(exc: BaseException, what: str) -> str:
    """For a constructor that wanted other arguments: what the kernel gives (docs/plugins.md)."""
    return (f" (its constructor is given, by keyword, those of {what} it names: docs/plugins.md)"
            if isinstance(exc, TypeError) else "")


def _taken(cls: Any, options: dict[str, Any], given: frozenset[str]) -> dict[str, Any]:
    """The scenario's ``options`` that ``cls`` takes. One it does not is another's (a bench row's, the fallback's)
    or misspelt, which the checks before a command runs say (``untaken_option``: they know every plugin it runs)."""
    unknown = _options_not_taken(cls, options, given)[0]
    return {k: v for k, v in options.items() if k not in unknown}


def named_schedulers(s: Scenario) -> list[str]:
    """The schedulers a campaign names: its own, its fallback, its lab's one."""
    return [spec for spec in (s.campaign.scheduler, s.campaign.fallback_scheduler, s.orchestrator.lab_scheduler)
            if spec]


def _options_not_taken(cls: Any, options: dict[str, Any], given: frozenset[str]) -> tuple[list[str], list[str]]:
    """The ``options`` a plugin's constructor has no parameter for, and the options it has: known only when its
    catch-all, if any, is ``**_`` (the kernel's arguments it does not use); a ``**kwargs`` of another name may read
    anything, so nothing is refused."""
    try:
        params = inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return [], []
    if any(p.kind is p.VAR_KEYWORD and p.name != "_" for p in params.values()):
        return [], []
    named = [n for n, p in params.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and n not in given]
    return [k for k in options if k not in named], named


def _installed_takes(kind: str, option: str, given: frozenset[str]) -> bool:
    """Whether an installed planner (scheduler) names ``option`` (or may read any). Each is read from its source,
    and imported only where that does not say (importing all took seconds: scikit-learn, torch, RDKit)."""
    for other in plugins.installed(kind):
        read = plugins.parameters_unimported(kind, other)
        if read is not None:
            named, takes_any = read
            if takes_any or (option in named and option not in given):
                return True
            continue
        try:
            unknown, _ = _options_not_taken(plugins.load(kind, other), {option: None}, given)
        except Exception:  # one that cannot be loaded here says nothing about this option
            continue
        if not unknown:
            return True
    return False


REMOTE = "remote"  # campaign.scheduler: an agent served elsewhere (`twin scheduler serve`)


def untaken_option(s: Scenario, kind: str, specs: list[str]) -> str:
    """Why an option of ``campaign.planner_options`` (``kind`` "planners") or ``scheduler_options`` ("schedulers")
    is likely misspelt: none of the plugins ``specs`` (those a command runs: the scenario's own, a bench's rows)
    nor any installed one takes it ('' if each is taken)."""
    field, given = (("planner_options", PLANNER_ARGUMENTS) if kind == "planners" else
                    ("scheduler_options", SCHEDULER_ARGUMENTS))
    options = getattr(s.campaign, field)
    if not options:  # the usual case, asked by every twin.run: nothing to load
        return ""
    classes = {name: plugins.load(kind, name) for name in
               dict.fromkeys(plugins.with_policy(kind, spec)[0] for spec in specs if spec and spec != REMOTE)}
    for option in options:
        if any(not _options_not_taken(cls, {option: None}, given)[0] for cls in classes.values()):
            continue
        if _installed_takes(kind, option, given):
            continue
        takes = {name: _options_not_taken(cls, {}, given)[1] for name, cls in classes.items()}
        said = "; ".join(f"{name!r} takes {', '.join(t) or 'none'}" for name, t in takes.items())
        return (f"campaign.{field}.{option}: no installed {kind[:-1]} takes an option {option!r}"
                f"{' (' + said + ')' if said else ''}; check its spelling")
    return ""


def make_scheduler(s: Scenario, spec: str | None = None) -> Any:
    """The scheduler named by ``spec`` (default: the scenario's, which must play the lab ahead if
    ``campaign.rollouts`` asks it to; a bench's or a fallback's need not); ``REMOTE`` for an agent elsewhere."""
    own, spec = spec is None, spec or s.campaign.scheduler
    if own and s.campaign.plays_ahead:
        _plays_ahead(s, spec)
    if spec == REMOTE:
        return REMOTE
    name, options = plugins.with_policy("schedulers", spec)
    cls = plugins.load("schedulers", name)
    if options and _options_not_taken(cls, options, SCHEDULER_ARGUMENTS)[0]:
        raise PluginError(f"scheduler {spec!r}: {name!r} reads no policy file; a trained scheduler is "
                          f"rl:PATH (`--scheduler rl:{options['policy']}`)")
    try:
        return constructed(cls, dict(scenario=s, seed=s.campaign.seed),
                           {**_taken(cls, s.campaign.scheduler_options, SCHEDULER_ARGUMENTS), **options})
    except TwinError:
        raise
    except PLUGIN_ERRORS as exc:
        raise PluginError(f"scheduler {spec!r} failed to start: {type(exc).__name__}: {exc}"
                          + _given(exc, "scenario and seed") + _where_files_are(exc)) from exc


def plays_ahead(spec: str) -> bool:
    """Whether the scheduler ``spec`` names can play a lab ahead (``campaign.rollouts``), known from its class (an
    agent elsewhere, ``remote``, reads the same file with ``twin scheduler serve`` and plays ahead there)."""
    return spec == REMOTE or bool(getattr(plugins.load("schedulers", plugins.with_policy("schedulers", spec)[0]),
                                          "plays_ahead", False))


def _plays_ahead(s: Scenario, spec: str) -> None:
    """``campaign.rollouts`` above 1 (or ``campaign.local_search``) asks the lab's own scheduler to play the lab
    ahead: refused unless it can."""
    if not plays_ahead(spec):
        asked = s.campaign.plays_ahead
        off = s.campaign.decides_as_it_goes
        raise PluginError(f"{asked}: only the rl scheduler plays a lab ahead, and {spec!r} decides as the lab goes; "
                          f"set {off}, or --scheduler rl:POLICY.zip")


def live_scheduler(s: Scenario, chosen: Any, bus: Bus, clock: LabClock,
                   in_process: bool = False) -> tuple[Any, SchedulerService | None]:
    """An agent scheduler (``serve_on_bus``, or ``remote``) is asked over the bus, with the fallback rule;
    ``in_process``: asked here even so (a lab's one scheduler), in a worker thread past its deadline."""
    deadline = s.campaign.scheduler_deadline_ms / 1000 * (1.0 if clock.is_virtual else clock.speed)
    if chosen != REMOTE and (in_process or not getattr(chosen, "serve_on_bus", False)):
        if clock.is_virtual:  # time stands still while it thinks
            return chosen, None
        return OffLoopScheduler(chosen, fallback_for(s), deadline), None
    service = None
    if chosen != REMOTE:
        service = SchedulerService(bus, s.lab, chosen)
        service.start()
    return RemoteScheduler(bus, s.lab, fallback_for(s), deadline), service


def fallback_for(s: Scenario) -> Fallback:
    """The rule that decides when the chosen scheduler cannot (``campaign.fallback_scheduler``)."""
    return Fallback(make_scheduler(s, s.campaign.fallback_scheduler), s.campaign.fallback_scheduler)


def agent_on_bus(spec: str) -> bool:
    """Whether the scheduler ``spec`` names sits on the bus (the rl agent), known from its class."""
    try:
        return bool(getattr(plugins.load("schedulers", plugins.with_policy("schedulers", spec)[0]), "serve_on_bus",
                            False))
    except TwinError:
        return False  # an unknown scheduler is reported, with the installed ones, when it is made
