"""One actor of a lab in its own process, joined to the lab over Zenoh: a device
(``twin device serve``) or a scheduler agent (``twin scheduler serve``)."""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from twin.campaign.human import people as people_of
from twin.core import keys
from twin.core.bus import Bus, NoReplyError, security
from twin.core.bus.endpoints import HOW, not_endpoints
from twin.core.bus.security import Identity
from twin.core.clock import LabClock
from twin.core.errors import BusError, ClockError, DriverError, PluginError
from twin.core.messages import excerpt
from twin.core.bus.presence import labs_on, present
from twin.runtime.labtime import LabTimeFollower
from twin.runtime.assembly import untaken_option
from twin.runtime.lab_claim import refuse_if_taken
from twin.runtime.served_devices import reported_differences
from twin.runtime.lab import build_actors, load_drivers, make_bus, make_clock, make_scheduler, prepare
from twin.runtime.shared_run import shared_drivers
from twin.scenario import BusSpec, Scenario
from twin.scenario.sharing import campaign_scenarios

log = logging.getLogger(__name__)


def _joined(scenario: str | Path, connect: list[str] | None, clock: str | None, speed: float | None,
            security_dir: str | None = None, wait_s: float | None = None) -> Scenario:
    """The scenario as seen from a process that joins the lab at ``connect`` (by default the scenario's
    ``bus.connect``: the lab's router, which the lab file names for the lab too) (through its router, with
    ``security_dir`` or the scenario's ``bus.security``), waiting ``wait_s`` (default: the scenario's
    ``bus.connect_timeout_ms``) for it to answer. Its clock is a wall clock until the lab's is heard."""
    if clock == "virtual":
        raise ClockError("a process joining a lab cannot follow a virtual clock: run the lab with --clock scaled "
                         "or wall, and start this process without --clock to follow it")
    s = prepare(scenario, clock=clock or "wall", speed=speed or 1.0, lab_only=True)
    connect = list(connect or s.bus.connect)
    if not connect:
        raise BusError(f"give --connect ENDPOINT: where the lab listens (twin run --listen …) or its router, e.g. "
                       f"tcp/127.0.0.1:7447; {scenario} names none (bus.connect)")
    bad = not_endpoints(connect)
    if bad:
        raise BusError(f"--connect: {', '.join(map(repr, bad))} is not a Zenoh endpoint: {HOW}")
    return s.model_copy(update={"bus": BusSpec(kind="zenoh", listen=[], connect=connect, lease_ms=s.bus.lease_ms,
                                               zenoh=s.bus.zenoh, security=security_dir or s.bus.security,
                                               connect_timeout_ms=(s.bus.connect_timeout_ms if wait_s is None
                                                                   else round(wait_s * 1000)))})


def _serve(s: Scenario, start: Callable[[Bus, LabClock], Awaitable[Callable[[], Awaitable[None]]]], ready: str,
           who: Identity, clock: str | None, speed: float | None) -> None:
    """Open the bus as ``who``, follow the lab's clock (``clock``/``speed``: what the operator asked for, None to
    take the lab's), ``start`` the actor (which returns its stop), print ``ready``, run until SIGINT/SIGTERM or
    until the lab runs a clock this process may not follow."""
    lab_clock = make_clock(s)
    problems: list[str] = []

    async def main() -> None:
        print(f"connecting to {', '.join(s.bus.connect)} (waiting up to {s.bus.connect_timeout_ms / 1000:g} s for "
              "it to answer)", file=sys.stderr, flush=True)
        bus = make_bus(s, lab_clock, who, wait_longer="--wait SECONDS waits longer")
        await bus.start()
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)

        def cannot_follow(reason: str) -> None:
            problems.append(reason)
            stop.set()

        follower = LabTimeFollower(bus, s.lab, lab_clock, clock, speed, on_error=cannot_follow)
        finish = None
        try:
            if not await follower.start(wait_s=min(2.0, s.bus.connect_timeout_ms / 1000)):
                log.info("lab %s is not running yet: commands are refused until its clock is heard", s.lab)
            finish = await start(bus, lab_clock)
            log.info("%s on %s", ready, s.bus.connect)
            print(ready, flush=True)
            await stop.wait()
        finally:
            follower.close()
            if finish is not None:
                await finish()
            await bus.close()

    lab_clock.run(main())
    if problems:
        raise ClockError(problems[0])


def serve_device(scenario: str | Path, name: str, connect: list[str] | None, clock: str | None = None,
                 speed: float | None = None,
                 security_dir: str | None = None, wait_s: float | None = None) -> None:
    s = _joined(scenario, connect, clock, speed, security_dir, wait_s)
    per_device: dict[str, dict[str, Any]] = {}
    if s.campaigns:  # a lab of several campaigns: a driver for each campaign's chemistry
        drivers, per_device = shared_drivers(campaign_scenarios(s, str(scenario)), only={name})
    else:
        drivers = load_drivers(s, only={name})
    if not drivers:
        raise DriverError(_not_a_device(s, scenario, [name]))

    async def start(bus: Bus, clock: LabClock):
        claims = await refuse_if_taken(bus, s, [name], orchestrator=False)
        actors = build_actors(s, drivers, bus, clock, per_device)
        for a in actors:
            await a.start()

        async def finish() -> None:
            for a in actors:
                await a.stop()
            claims.close()

        return finish

    _serve(s, start, f"ready {name}", Identity("device", s.lab, name), clock, speed)


def health(scenario: str | Path, ids: list[str], connect: list[str] | None, security_dir: str | None = None,
           wait_s: float = 3.0) -> list[dict]:
    """``twin device health``: each device's health report (``None`` for one that did not answer in ``wait_s``).
    With security, asked as the lab's orchestrator (the identity that may ask devices)."""
    s = _joined(scenario, connect, "wall", 1.0, security_dir)
    known = _devices(s)
    if any(i not in known for i in ids):
        raise DriverError(_not_a_device(s, scenario, [i for i in ids if i not in known]))
    clock = make_clock(s)

    async def ask() -> list[dict]:
        bus = make_bus(s, clock, Identity("orchestrator", s.lab))
        await bus.start()
        try:
            return await _ask_health(bus, s.lab, ids or known, wait_s)
        finally:
            await bus.close()

    return [_compared(s, answer) for answer in clock.run(ask())]


def _compared(s: Scenario, answer: dict) -> dict:
    """A device's answer with ``differs``: what of the scenario it reports running by differs from ``s`` (a device of
    another make reports none: nothing to compare)."""
    dtype = next(d for d in s.devices if answer["device"] in s.instance_names(d))
    found = reported_differences(s, dtype, answer.get("report"))
    return answer if found is None else {**answer, "differs": found}


def _devices(s: Scenario) -> list[str]:
    """The scenario's device instances: not its people (``driver: operator``), whom the campaign serves itself."""
    people = people_of(s)
    return [n for d in s.devices for n in s.instance_names(d) if n not in people]


def _not_a_device(s: Scenario, scenario: str | Path, names: list[str]) -> str:
    people = [n for n in names if n in people_of(s)]
    if people:
        return (f"{scenario}: {people[0]!r} is people (driver: operator), not a device: the campaign serves their "
                f"steps itself (`twin ctl pending`, `twin ctl confirm`); the devices are {_devices(s)}")
    return f"{scenario}: no device instance {names if len(names) > 1 else names[0]!r}; the scenario has {_devices(s)}"


def roster(lab: str, connect: list[str], security_dir: str | None = None, wait_s: float = 3.0,
           connect_timeout_ms: int = 5000) -> tuple[list[dict], list[str]]:
    """``twin devices --connect``: the devices on a running lab's bus (by their presence), with their health; and
    when it has none, the labs the bus has."""
    from twin.core.bus import open_bus

    clock = LabClock("wall")

    async def ask() -> tuple[list[dict], list[str]]:
        extra = security.session_config(security_dir, Identity("orchestrator", lab)) if security_dir else {}
        bus = open_bus("zenoh", clock, mode="client", listen=[], connect=connect, extra=extra,
                       connect_timeout_ms=connect_timeout_ms, wait_longer="")
        await bus.start()
        try:
            names = sorted(keys.device_of(key) for key in await present(bus, [keys.alive(lab)], 0.5))
            if not names:
                return [], await labs_on(bus)
            return await _ask_health(bus, lab, names, wait_s), [lab]
        finally:
            await bus.close()

    return clock.run(ask())


async def _ask_health(bus: Bus, lab: str, names: list[str], wait_s: float) -> list[dict]:
    """Each device asked at once: one after another, a lab of devices that do not answer took ``wait_s`` each."""
    async def ask(name: str) -> dict:
        try:
            answer = await bus.request(keys.health(lab, name), b"", wait_s)
        except NoReplyError:
            return {"device": name, "report": None}
        return {"device": name, "report": health_report(answer)}

    return list(await asyncio.gather(*(ask(name) for name in names)))


def health_report(answer: bytes) -> dict:
    """A device's answer to a health query as a report (a device of someone else's may answer anything):
    JSON that is not an object becomes its ``driver`` entry; an answer that is not JSON a failed one."""
    try:
        report = json.loads(answer)
    except (ValueError, UnicodeDecodeError, RecursionError):
        return {"driver": {"ok": False, "error": f"an answer that is not JSON: {excerpt(answer, 60)}"}}
    return report if isinstance(report, dict) else {"driver": report}


def serve_scheduler(scenario: str | Path, spec: str, connect: list[str] | None, clock: str | None = None,
                    speed: float | None = None,
                    security_dir: str | None = None, wait_s: float | None = None) -> None:
    """A scheduler (a rule or ``rl:PATH``) as an agent on a lab's bus."""
    from twin.runtime.remote_scheduler import SchedulerService

    s = _joined(scenario, connect, clock, speed, security_dir, wait_s)
    scheduler = make_scheduler(s, spec)
    problem = untaken_option(s, "schedulers", [spec])  # its options: the lab file's campaign.scheduler_options
    if problem:
        raise PluginError(problem)

    async def start(bus: Bus, clock: LabClock):
        claims = await refuse_if_taken(bus, s, [], orchestrator=False, agent=True)
        service = SchedulerService(bus, s.lab, scheduler)
        service.start()

        async def finish() -> None:
            service.stop()
            claims.close()

        return finish

    _serve(s, start, f"ready scheduler {spec}", Identity("scheduler", s.lab), clock, speed)
