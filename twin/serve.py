"""One device actor in its own process, joined to a lab over Zenoh (``twin device serve``)."""

from __future__ import annotations

import asyncio
import logging
import signal
from pathlib import Path

from twin.errors import DriverError
from twin.lab import build_actors, load_drivers, prepare
from twin.scenario import BusSpec

log = logging.getLogger(__name__)


def serve_device(scenario: str | Path, name: str, connect: list[str], clock: str = "wall", speed: float = 1.0) -> None:
    if clock == "virtual":
        from twin.errors import ClockError

        raise ClockError("a device in its own process cannot follow a virtual clock: use --clock scaled or wall")
    s = prepare(scenario, clock=clock, speed=speed)
    s = s.model_copy(update={"bus": BusSpec(kind="zenoh", listen=[], connect=connect, lease_ms=s.bus.lease_ms,
                                                zenoh=s.bus.zenoh)})
    drivers = load_drivers(s, only={name})
    if not drivers:
        known = [n for d in s.devices for n in s.instance_names(d)]
        raise DriverError(f"{scenario}: no device instance {name!r}; the scenario has {known}")
    from twin.lab import make_bus, make_clock

    lab_clock = make_clock(s)

    async def main() -> None:
        bus = make_bus(s, lab_clock)
        await bus.start()
        actors = build_actors(s, drivers, bus, lab_clock)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        try:
            for a in actors:
                await a.start()
            log.info("%s serving on %s", name, connect)
            print(f"ready {name}", flush=True)
            await stop.wait()
        finally:
            for a in actors:
                await a.stop()
            await bus.close()

    lab_clock.run(main())


def serve_scheduler(scenario: str | Path, spec: str, connect: list[str], clock: str = "wall", speed: float = 1.0) -> None:
    """A scheduler (a rule or ``rl:PATH``) as an agent on a lab's bus, until SIGINT/SIGTERM."""
    from twin.lab import make_bus, make_clock, make_scheduler
    from twin.remote_scheduler import SchedulerService

    s = prepare(scenario, clock=clock, speed=speed)
    s = s.model_copy(update={"bus": BusSpec(kind="zenoh", listen=[], connect=connect, lease_ms=s.bus.lease_ms,
                                                zenoh=s.bus.zenoh)})
    scheduler = make_scheduler(s, spec)
    lab_clock = make_clock(s)

    async def main() -> None:
        bus = make_bus(s, lab_clock)
        await bus.start()
        service = SchedulerService(bus, s.lab, scheduler)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        try:
            service.start()
            log.info("scheduler %s serving lab %s on %s", spec, s.lab, connect)
            print(f"ready scheduler {spec}", flush=True)
            await stop.wait()
        finally:
            service.stop()
            await bus.close()

    lab_clock.run(main())
