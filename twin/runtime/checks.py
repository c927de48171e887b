"""What `twin validate` checks beyond the scenario's own fields: what only the installed plugins can tell."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any

from twin.core.counts import counted, quantity
from twin.core import plugins
from twin.core.errors import ScenarioError, TwinError
from twin.campaign.human import DRIVER as HUMAN
from twin.campaign.human import OPTION_NAMES as HUMAN_OPTIONS
from twin.campaign.policy import deadline_s, unusable_params, unusable_route
from twin.device.driver import declared_steps, feature
from twin.runtime.assembly import load_driver, make_planner, make_scheduler, named_schedulers, untaken_option
from twin.runtime.standby import standby_drivers
from twin.runtime.trial import trial_warnings
from twin.scenario import Scenario, load
from twin.scenario.model import expected_duration
from twin.scenario.sharing import campaign_scenarios

log = logging.getLogger(__name__)


def check(s: Scenario, external: Collection[str] = (), benched: bool = False, planners: Collection[str] = (),
          schedulers: Collection[str] = (), virtual: bool = False) -> None:
    """What only the installed plugins can tell about ``s`` (``twin validate`` and ``twin run`` both ask):
    its drivers, planner, scheduler and fallback load; its targets ask for outputs the workflow produces;
    its Zenoh settings make a config. A lab of several campaigns: each campaign's, on the device types its
    workflow uses. ``external``: instances served by other processes, whose drivers need not be installed here
    (a device type all of whose instances are external is not loaded). ``benched``: a bench names the schedulers
    to run and checks them itself, and a scheduler's training makes one, so the scenario's own is not loaded.
    ``planners``, ``schedulers``: the others the command runs (a bench's rows, ``twin whatif --schedulers``),
    whose options ``campaign.planner_options`` and ``scheduler_options`` may hold. ``virtual``: the command runs
    the lab on a virtual clock whatever its file says (a what-if, a bench, a training), so the twins stand in."""
    if not s.campaigns:
        _check(s, external=external, benched=benched, planners=planners, schedulers=schedulers, virtual=virtual)
        return
    for i, (name, cs) in enumerate(campaign_scenarios(s, s.name).items()):
        try:
            check_campaign(cs, external, virtual)
        except ScenarioError as exc:
            raise ScenarioError(exc.source or s.name, [f"campaigns.{i} ({name}): {p}" for p in exc.problems]) from None


def check_campaign(s: Scenario, external: Collection[str] = (), virtual: bool = False) -> None:
    """What the installed plugins tell about one campaign of a shared lab, on the device types it uses."""
    _check(s, {w.device for w in s.workflow}, external, virtual=virtual)


def _check(s: Scenario, types: set[str] | None = None, external: Collection[str] = (),
           benched: bool = False, planners: Collection[str] = (), schedulers: Collection[str] = (),
           virtual: bool = False) -> None:
    virtual = virtual or s.clock.mode == "virtual"  # on a scaled or wall clock the lab's own drivers run
    elsewhere = {dtype for dtype in s.devices if set(s.instance_names(dtype)) <= set(external)}
    for dtype, spec in s.devices.items():
        stray = sorted(set(spec.options) - HUMAN_OPTIONS) if spec.driver == HUMAN else []
        if stray:
            raise ScenarioError(s.name, [f"devices.{dtype}.options.{stray[0]}: people ('{HUMAN}') take only "
                                         f"{', '.join(sorted(HUMAN_OPTIONS))}; check its spelling"])
    problems: list[str] = []  # every plugin that does not load, at once: not one per try

    def loaded(field: str, make: Callable[..., Any], *args: Any) -> Any:
        try:
            return _at(field, make, *args)
        except ScenarioError as exc:
            problems.extend(exc.problems)
            return None

    served = [dtype for dtype in s.devices if s.devices[dtype].driver != HUMAN and (types is None or dtype in types)
              and dtype not in elsewhere]
    absent = _absent_behind_twins(s, served) if virtual else set()
    drivers = {dtype: loaded(f"devices.{dtype}.driver", load_driver, s, dtype, s.instance_names(dtype)[0], False)
               for dtype in served if dtype not in absent}
    twins = {dtype: loaded(f"devices.{dtype}.twin.driver", load_driver, s, dtype, s.instance_names(dtype)[0], True)
             for dtype in served if s.devices[dtype].twin is not None}
    planner = loaded("campaign.planner", make_planner, s)
    if not benched:  # a bench runs the schedulers it names, not the scenario's (nor loads its policy to warn of it)
        loaded("campaign.scheduler", make_scheduler, s)
    loaded("campaign.fallback_scheduler", make_scheduler, s, s.campaign.fallback_scheduler)
    if problems:
        raise ScenarioError("", problems)  # as ``_at`` raises each: the caller names the file or campaign
    # what the plugins tell, each at once too: the checks take the plugins loaded, so they come after those load
    found = [_unrunnable_given(s, planner),
             # options no plugin the command runs takes: likely misspelt (a scheduler bench checks its own rows)
             untaken_option(s, "planners", [s.campaign.planner, *planners]),
             "" if benched else untaken_option(s, "schedulers", [*named_schedulers(s), *schedulers]),
             _unproduced(s, drivers, elsewhere | absent), _sampleless(s, drivers, elsewhere | absent),
             "" if virtual else _claimed_twice(s, drivers, external)]
    if any(found):
        raise ScenarioError(s.name, [problem for problem in found if problem])
    if not virtual and s.bus.kind == "memory":
        problem = _out_of_ctl_reach(s, types)
        if problem:
            log.warning("%s", problem)
    if types is None:
        for problem in [*_idle_types(s, planner), *_reorder_points(s), *_unanswered(s)]:
            log.warning("%s", problem)
    if not s.chemistry.targets and getattr(planner, "aims_at_targets", False):
        log.warning("chemistry.targets: none, and planner %r chooses each experiment by its chance of meeting a "
                    "target, so it only explores (as lhs or random would): give the targets, or name the planner that "
                    "does what you mean", s.campaign.planner)
    for dtype, driver in drivers.items():
        problem = _short_deadline(s, dtype, driver)
        if problem:
            log.warning("%s", problem)
    simulated = twins and virtual
    problem = _unproduced(s, {**drivers, **twins}, elsewhere, " with their twins (devices.*.twin)") if simulated else ""
    if problem:  # a twin that only keeps time still serves a scheduler's training or a what-if of device counts
        log.warning("%s: on a virtual clock no experiment meets that target, and campaigns run their whole budget",
                    problem)
    problem = _sampleless(s, {**drivers, **twins}, elsewhere, twinned=True) if simulated else ""
    if problem:
        log.warning("with the twins (devices.*.twin) %s: on a virtual clock every experiment is abandoned there",
                    problem)
    if s.bus.zenoh:
        from twin.core.bus.zenoh_config import check_config

        check_config(s.bus.zenoh)


@contextlib.contextmanager
def said_once() -> Iterator[None]:
    """Within it, each warning of these checks is said once: a command that checks its scenario and then each of
    its variants (a what-if) says a problem they share once."""
    said: set[str] = set()

    def first(record: logging.LogRecord) -> bool:
        text = record.getMessage()
        fresh = text not in said
        said.add(text)
        return fresh

    log.addFilter(first)
    try:
        yield
    finally:
        log.removeFilter(first)


def _absent_behind_twins(s: Scenario, types: list[str]) -> set[str]:
    """The device types whose own driver does not load here (its package not installed, say, on a laptop away
    from the instrument) but which, on a virtual clock, a twin stands in for: said, not refused, since what runs
    here is the twin (checked as any driver)."""
    absent = set()
    for dtype in types:
        spec = s.devices[dtype]
        if spec.twin is None:
            continue
        try:
            plugins.load("devices", spec.driver)
        except TwinError as exc:
            absent.add(dtype)
            log.warning("devices.%s.driver: %s. On this virtual clock its twin (%s) runs its steps, so this goes on; "
                        "on a scaled or wall clock the lab runs its own driver, and stops here", dtype, exc,
                        spec.twin.driver)
    return absent


def _unrunnable_given(s: Scenario, planner: Any) -> str:
    """The first experiment a planner that knows them in advance (``known_in_advance``: the fixed list) gives and
    the lab would abandon before sending anything — a parameter missing or outside the box, a route it cannot
    run — with the field that gives it ('' if none)."""
    for where, proposal in getattr(planner, "known_in_advance", None) or ():
        why = unusable_params(proposal.params, s.chemistry.parameters) or (
            unusable_route(proposal.route, s.devices) if proposal.route is not None else "")
        if why:
            return f"{where}: {why}"
    return ""


def _idle_types(s: Scenario, planner: Any) -> list[str]:
    """Device types no step will run on: the workflow names none of their steps and the planner, one that says it
    proposes no routes of its own (``plans_routes = False``), adds none. A planner that does not say may."""
    if getattr(planner, "plans_routes", None) is not False or s.jobshop is not None:
        return []
    used = {w.device for w in s.workflow}
    return [f"devices.{dtype}: no workflow step runs on it (each step runs on the device type its `device:` names), "
            f"so its {counted(len(s.instance_names(dtype)), 'instance', 'instances')} will stay idle; name it in a "
            "step, or leave it out"
            for dtype, spec in s.devices.items() if dtype not in used and spec.driver != HUMAN]


def _short_deadline(s: Scenario, dtype: str, driver: Any) -> str:
    """A driver whose steps last as long as a parameter (``duration_param``) on a device type whose duration
    model leaves that parameter out, with a deadline shorter than the parameter's highest value: its long
    experiments would time out, attempt after attempt."""
    param, spec = feature(driver, "duration_param"), s.devices[dtype]
    if not isinstance(param, str) or spec.duration.plus_param == param:
        return ""
    box = s.chemistry.parameters.get(param)
    given = [float(w.params[param]) for w in s.workflow if w.device == dtype and isinstance(w.params.get(param),
                                                                                          (int, float))]
    longest = max(given + ([box.high] if box is not None and not given else []), default=0.0)
    expected = expected_duration(spec.duration, {}, spec.setup_s, spec.clean_s)
    deadline = deadline_s(expected, s.orchestrator)
    if longest <= deadline:
        return ""
    return (f"devices.{dtype}.duration: a step of {spec.driver} lasts at least {param} (up to {longest:g} lab-s "
            f"here), which the duration model leaves out, so its deadline is {deadline:.0f} lab-s ({expected:.0f} "
            f"expected × orchestrator.timeout_factor + timeout_slack_s) and longer ones will time out: give "
            f"devices.{dtype}.duration.plus_param: {param}")


def _unproduced(s: Scenario, drivers: dict[str, Any], elsewhere: set[str], how: str = "") -> str:
    """An output a target reads that no driver of the workflow declares (where all of them declare theirs)."""
    used = {w.device for w in s.workflow} or set(s.devices)
    # a type served elsewhere produces what its driver there says: unknown here, so targets are not checked
    declared = [None if d in elsewhere else feature(drivers[d], "outputs") if d in drivers else set() for d in used]
    if s.chemistry.targets and all(o is not None for o in declared):
        produced = set().union(*declared)
        for i, t in enumerate(s.chemistry.targets):
            for out in t.outputs:
                if out not in produced:
                    they = f"they produce {', '.join(sorted(produced))}" if produced else \
                        f"{_listed(sorted(used))} declare{'s' if len(used) == 1 else ''} no outputs"
                    able = _installed_that(lambda d: out in (feature(d, "outputs") or ()))
                    return (f"chemistry.targets.{i}.outputs.{out}: no device of the workflow{how} produces {out!r} "
                            f"({they}): measure it with a step on a device whose driver does"
                            f"{f' (installed: {_listed(able)})' if able else ''}, or drop the target")
    return ""


def _listed(names: list[str]) -> str:
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def _installed_that(has: Callable[[Any], bool]) -> list[str]:
    """The installed drivers whose class has it; for a refusal's advice only, since it imports each of them."""
    names = []
    for name in sorted(plugins.installed("devices")):
        try:
            driver = plugins.load("devices", name)
        except Exception:  # a plugin that does not load here is named by the look-up that needs it
            continue
        with contextlib.suppress(TwinError):
            if has(driver):
                names.append(name)
    return names


def _sampleless(s: Scenario, drivers: dict[str, Any], elsewhere: set[str], twinned: bool = False) -> str:
    """A workflow step whose driver needs a sample (``needs_sample``) after only steps whose drivers say they make
    none (``makes_sample``; people make none): every experiment would be abandoned there. A step whose driver
    does not say, or served elsewhere, may make one. ``twinned``: the drivers are the twins where there are any
    (the installed drivers that make one are no advice there: the lab's own does)."""
    def steps(dtype: str, name: str) -> frozenset[str] | None:
        return declared_steps(drivers[dtype], name, f"devices.{dtype}.driver {s.devices[dtype].driver!r}")

    have = False
    for i, w in enumerate(s.workflow):
        if w.device in drivers and not have and w.step in (steps(w.device, "needs_sample") or ()):
            makers = _makers(s, drivers)
            if makers or twinned:
                doing = f" ({_listed(makers)} {'does' if len(makers) == 1 else 'do'})" if makers else ""
                return (f"workflow.{i}: {w.step} on {w.device} needs a sample, and no step before it makes one"
                        f"{doing}: put a step that makes one first")
            able = _installed_that(lambda d: bool(declared_steps(d, "makes_sample", "")))
            return (f"workflow.{i}: {w.step} on {w.device} needs a sample, and no step before it makes one, nor "
                    f"does any device of the lab: put first a step on a device whose driver makes one"
                    f"{f' (installed: {_listed(able)})' if able else ''}, or a driver of yours that declares "
                    "makes_sample (docs/drivers.md)")
        if w.device in drivers:
            makes = steps(w.device, "makes_sample")
            have = have or makes is None or w.step in makes
        elif w.device in elsewhere or s.devices[w.device].driver != HUMAN:
            have = True
    return ""


def _makers(s: Scenario, drivers: dict[str, Any]) -> list[str]:
    """The lab's steps that make a sample ("synthesise on synthesiser"): of the device types checked, else of the
    lab's others (a campaign of a shared lab is checked on the types its workflow uses, and may need another)."""
    def made(dtype: str, driver: Any) -> list[str]:
        says = declared_steps(driver, "makes_sample", f"devices.{dtype}.driver {s.devices[dtype].driver!r}")
        return [f"{step} on {dtype}" for step in sorted(says or ()) if step in s.devices[dtype].steps]

    found = [m for dtype, driver in drivers.items() for m in made(dtype, driver)]
    for dtype in s.devices:
        if found or dtype in drivers or s.devices[dtype].driver == HUMAN:
            continue
        try:
            found += made(dtype, load_driver(s, dtype, s.instance_names(dtype)[0], False))
        except TwinError:  # a driver that cannot be loaded here names no step
            continue
    return found


def _reorder_points(s: Scenario) -> list[str]:
    return [f"consumables.{item}.reorder_at: {c.reorder_at:g} is not below its level, {quantity(c.level, c.unit)}, so "
            "consumable.low says it is low at its first step and never after a refill; give the level at which to "
            "reorder, below the starting one" for item, c in s.consumables.items() if c.reorder_at >= c.level]


def _unanswered(s: Scenario) -> list[str]:
    """A simulated operator slower than the question's timeout: the default answers every question instead (a
    what-if of a slow operator may mean it, so it is said, not refused)."""
    return [f"orchestrator.recovery.{i}.simulate.after_s: {r.simulate.after_s:g} lab-s is not below its timeout_s, "
            f"{r.timeout_s:g}, so the simulated operator never answers and the default ({r.default}) applies to "
            f"every question; give an after_s below {r.timeout_s:g} for it to answer {r.simulate.answer}"
            for i, r in enumerate(s.orchestrator.recovery)
            if r.simulate is not None and r.simulate.after_s >= r.timeout_s]


def _out_of_ctl_reach(s: Scenario, types: set[str] | None) -> str:
    """On a live clock and a memory bus, what waits for a `twin ctl` that cannot reach the campaign, or ''."""
    people = [dtype for dtype, spec in s.devices.items() if spec.driver == HUMAN and (types is None or dtype in types)]
    stocks = sorted(s.consumables)
    waits = ([f"devices.{people[0]} is people (driver: {HUMAN}), whose steps wait for `twin ctl confirm` and would "
              "each time out"] if people else []) + \
        ([f"consumables {', '.join(stocks)} may run out, and the steps that need one would wait to the end for a "
          "`twin ctl refill`"] if stocks else [])
    if not waits:
        return ""
    return (f"on a {s.clock.mode} clock and a memory bus, which twin ctl cannot reach (it reaches a campaign over "
            f"Zenoh only): {'; '.join(waits)}. Run it with --bus zenoh --listen tcp/127.0.0.1:7447 (and twin ctl … "
            "--connect there)")


def _claimed_twice(s: Scenario, drivers: dict[str, Any], external: Collection[str]) -> str:
    """The first thing two devices claim to hold alone (``claims``: an MQTT topic on a broker, a serial port), or ''.
    Each instance of a type whose driver claims is made to read its claim (a constructor sends nothing)."""
    holders: dict[str, str] = {}
    for dtype, first in drivers.items():
        if first is None or feature(first, "claims") is None:
            continue
        for name in s.instance_names(dtype):
            if name in external:
                continue
            driver = first if name == s.instance_names(dtype)[0] else _at(f"devices.{dtype}.driver", load_driver,
                                                                           s, dtype, name, False)
            claim = str(feature(driver, "claims"))
            if claim in holders:
                return (f"devices.{dtype}: {holders[claim]} and {name} both hold {claim}, which only one device "
                        "can hold")
            holders[claim] = name
    return ""


def _at(field: str, make: Callable[..., Any], *args: Any) -> Any:
    """``make(*args)``, its error prefixed with the scenario field it is about."""
    try:
        return make(*args)
    except ScenarioError:
        raise
    except TwinError as exc:
        text = str(exc)
        raise ScenarioError("", [text if text.startswith(field.split(".")[0]) else f"{field}: {text}"]) from None


def validate_file(path: str | Path, overrides: dict | None = None, served: bool = False) -> Scenario:
    """``twin validate``: the scenario file read (with the command line's ``--set`` overrides), checked field by
    field, and against the installed plugins. ``served``: read as ``twin lab serve`` reads it, a lab whose
    campaigns may come later: without campaigns, its devices' drivers are made as they stand by."""
    s = load(path, overrides, lab_only=served)
    if not served or s.campaigns:
        checked(s, path)
        for warning in trial_warnings(s, path):
            log.warning(warning)
        return s
    problems = []
    for dtype in s.devices:  # each type's drivers alone, so that each problem names its field, and all are said
        others = [name for other in s.devices if other != dtype for name in s.instance_names(other)]
        try:
            _at(f"devices.{dtype}.driver", standby_drivers, s, others)
        except ScenarioError as exc:
            problems += exc.problems
    if problems:
        raise ScenarioError(str(path), problems)
    return s


def checked(s: Scenario, path: str | Path, external: Collection[str] = (), benched: bool = False,
            planners: Collection[str] = (), schedulers: Collection[str] = (), virtual: bool = False) -> Scenario:
    """``s`` (read from ``path``) checked against the installed plugins; its errors name the file. What `twin run`
    checks before its progress bar, and a bench, a what-if or a training before its workers start, so that a
    driver that cannot run the lab is one error naming the file and field, not a traceback from a worker."""
    try:
        check(s, external, benched, planners, schedulers, virtual)
    except ScenarioError as exc:
        raise ScenarioError(str(path), exc.problems) from None
    except TwinError as exc:
        raise ScenarioError(str(path), [str(exc)]) from None
    return s
