"""A device in the fast runtime: the ``DeviceActor``'s behaviour without asyncio.

The driver's ``async def run`` is driven by ``send()``: each ``await
ctx.clock.sleep(s)`` yields a request, and the step resumes from a timer
``s`` lab-seconds later. Faults are the actor's (a step that fails, one that
hangs until cancelled, crashes with a restart), drawn from the same streams,
and messages are the same envelopes, passed as dicts.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections.abc import Callable
from typing import Any


from twin.campaign import DeviceMessage, InvalidInput, Presence
from twin.core.streams import KeyedGenerator, seeded
from twin.core import held
from twin.device.habits import Habits
from twin.device.driver import (SWALLOWED, Driver, StepContext, busy_with, fault_text, feature,
                                simulated_faults, step_result)
from twin.core.errors import PLUGIN_ERRORS, DriverError, Refused
from twin.core.messages import Dropped, InvalidMessage, Kind, decode, envelope, excerpt, to_wire, within_limit
from twin.view.observer import WATCHED
from twin.runtime.queue import EventQueue, Park, QueueClock, Sleep, Timer

log = logging.getLogger(__name__)
#: Messages whose body holds what a driver gave (the others the runtime writes itself).
_DRIVERS_WORDS = frozenset({Kind.RESULT, Kind.TELEMETRY, Kind.PROGRESS})


class FastRuntimeRefused(DriverError):
    """A driver does something only the asyncio runtime can serve (awaits I/O, connects to an instrument):
    ``why``, about the device type ``device_type``."""

    def __init__(self, why: str, device_type: str = "") -> None:
        self.why, self.device_type = why, device_type
        super().__init__(f"{why}. Use --runtime asyncio" + (
            f", or give devices.{device_type}.twin: {{driver: NAME}}, a simulated driver that stands in for it "
            "on a virtual clock (docs/drivers.md)" if device_type else ""))

    def running_again(self, what: str) -> str:
        """What the auto runtime says as it runs ``what`` (the campaign, the lab) again on the asyncio runtime: a
        bench or what-if runs it so too, and takes no --runtime."""
        return (f"{self.why} — running the {what} again, from the start, on the asyncio runtime ("
                + (f"give devices.{self.device_type}.twin: {{driver: NAME}}, a simulated driver that stands in for "
                   "it on a virtual clock, to keep it on the fast one (docs/drivers.md); " if self.device_type else "")
                + "twin run --runtime asyncio starts there)")


class FastDevice:
    def __init__(self, name: str, device_type: str, spec: Any, driver: Driver, queue: EventQueue, seed: int,
                 deliver: Callable[[Any], None], watch: Callable[[dict], None] | None = None,
                 shared: dict[str, Driver] | None = None, warn: bool = True) -> None:
        """``watch``: given the envelope of each result and telemetry message, decoded (an in-process observer).
        ``shared``: the device serves several campaigns — campaign -> the driver that simulates its chemistry;
        their steps draw faults and durations by campaign too (their task ids repeat). ``warn``: log a driver that
        raises as a warning (a training episode's go to debug: its fault is in the run all the same)."""
        self.name, self.device_type, self.spec, self.driver = name, device_type, spec, driver
        self._log_raised = log.warning if warn else log.debug
        self._watch = watch
        self._q, self._clock, self._deliver, self._seed = queue, QueueClock(queue), deliver, seed
        self._crash_rng = seeded(seed, "crashes", name)[0] if spec.faults.mtbc_h > 0 else None
        self._step_rngs = KeyedGenerator()
        self._ids = itertools.count(1)
        self._job: Any = None  # the running step's coroutine
        self._slept = 0  # sleeps the driver loop was handed: awaited
        self._current: tuple[str, int] | None = None
        self._campaign = ""
        self._token = ""
        self._cancel_reason = ""
        self._safing = False  # the step has ended; the driver's safe_state() has not returned
        self._timer: Timer | None = None
        self._shared = shared or {}
        self._habits = Habits(name)
        self._dropped = Dropped(log)  # its messages that did not pass the wire's checks
        self.online = False

    # -- life cycle -------------------------------------------------------------------
    def start(self) -> None:
        if feature(self.driver, "connect") is not None:
            raise FastRuntimeRefused(f"{self.name}: its driver connects to an instrument of its own, which the "
                                     "fast runtime cannot wait for", self.device_type)
        self._set_online(True)
        if self.spec.faults.mtbc_h > 0:
            self._schedule_crash()

    def stop(self) -> None:
        if self._job is not None:
            self._cancel_reason = "stop"
            self._throw_cancel()
        job = self._job
        if job is not None:  # it swallowed the cancel and waits again: the queue would never empty
            log.error("%s: %s", self.name, SWALLOWED)
            if self._timer is not None:
                self._timer.cancel()
            self._job = self._current = self._timer = None
            with contextlib.suppress(RuntimeError):  # GeneratorExit at its await, which those do not catch
                job.close()
        try:
            _complete(self.driver.safe_state(), self.name, self.device_type)
        except FastRuntimeRefused:
            raise
        except PLUGIN_ERRORS as exc:  # the campaign is over; say so, and let the others stop too
            log.error("%s: safe_state() failed at shutdown: %r; check the instrument by hand", self.name, exc)
        self.online = False

    def _set_online(self, alive: bool) -> None:
        self.online = alive
        self._deliver(Presence(self.name, alive))

    def _schedule_crash(self) -> None:
        rng = self._crash_rng
        assert rng is not None  # only a device that crashes schedules crashes
        self._q.call_later(rng.expovariate(1.0 / (self.spec.faults.mtbc_h * 3600)), self._crash)

    def _crash(self) -> None:
        log.info("%s crashed at t=%.0f s", self.name, self._q.now)
        self._set_online(False)
        if self._job is not None:
            self._cancel_reason = "crash"
            self._throw_cancel()
        self._q.call_later(self.spec.faults.restart_s, self._restart)

    def _restart(self) -> None:
        self._set_online(True)
        self._schedule_crash()

    # -- messages ---------------------------------------------------------------------
    def _emit(self, kind: Kind, body: dict, task: str, attempt: int, token: str, campaign: str | None = None) -> None:
        """The message about ``task#attempt``; the attempt's token travels beside it (no bus to carry it)."""
        campaign = self._campaign if campaign is None else campaign
        env = envelope(kind, body, id=f"{self.name}:{next(self._ids)}", sender=self.name, t_lab=self._q.now,
                       campaign=campaign, task=task, attempt=attempt)
        # encoded once, as the journal stores it; a body that cannot go on the wire fails here, as on a bus
        payload = within_limit(kind, to_wire(env))
        if kind in _DRIVERS_WORDS:  # checked as a receiver on a bus checks it (a NaN reading goes as null)
            try:
                # what enters the ledger is what the wire carries (numpy → numbers, tuples → lists)
                body = decode(payload, self.name)[1].to_dict()
            except InvalidMessage as exc:
                self._dropped.said(f"from {self.name}", exc)
                self._deliver(InvalidInput(exc.sender, exc.reason, excerpt=excerpt(payload)))
                return
        if self._watch is not None and kind in WATCHED:
            self._watch({**env, "body": body})
        self._deliver(DeviceMessage(kind, self.name, task, attempt, body, payload, token=token, campaign=campaign))

    def command(self, task: str, attempt: int, campaign: str, body: dict, token: str) -> None:
        if not self.online:
            return  # off the bus: the command is lost, as it would be
        if self._job is not None:
            self._emit(Kind.REJECTED, busy_with(self._current, self._safing), task, attempt, token, campaign)
            return
        self._campaign = campaign
        self._current, self._token = (task, attempt), token
        self._job = self._run(task, attempt, token, body)
        self._resume()

    def cancel(self, task: str, attempt: int, token: str) -> None:
        if self.online and self._current == (task, attempt) and self._job is not None and token == self._token:
            self._cancel_reason = "cancel"
            self._throw_cancel()

    # -- driving the step -------------------------------------------------------------
    def _resume(self, exc: BaseException | None = None) -> None:
        self._timer = None
        job, current, token = self._job, self._current, self._token
        watch, clock = self._habits, time.perf_counter
        while True:
            since = clock()
            try:
                held.holding(watch.holder, since)
                req = job.send(None) if exc is None else job.throw(exc)
            except (StopIteration, asyncio.CancelledError):
                return
            except PLUGIN_ERRORS as err:  # the step died in the device's own handling (a safe_state that raised)
                log.error("%s: step %s died in the device's own handling: %s; reported as a driver error",
                          self.name, current, fault_text(err))
                if current is not None:
                    self._emit(Kind.FAULT, {"code": "driver_error", "reason": fault_text(err, 500)}, *current, token)
                return
            finally:
                held.released()
                if clock() - since > watch.blocking_s:  # inline: the call is only made for a driver that blocked
                    watch.ran(since)
            exc = None
            if type(req) is Sleep:
                self._slept += 1
                if req.seconds > 0:
                    self._timer = self._q.call_later(req.seconds, self._resume)
                    return
                continue
            if type(req) is Park:
                return
            job.close()
            self._job = self._current = None
            what = ("a bare yield (asyncio.sleep(0)?)" if req is None else
                    f"an asyncio future (asyncio.sleep, an Event, I/O: {type(req).__name__})"
                    if isinstance(req, asyncio.Future) else repr(req))
            raise FastRuntimeRefused(
                f"{self.name}: the {self.device_type} driver awaited {what}, not the lab clock; the fast runtime "
                "can only run drivers that wait with ctx.clock.sleep", self.device_type)

    def _throw_cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._resume(asyncio.CancelledError())

    async def _to_safety(self) -> None:
        """The driver's ``safe_state`` after a step; until it returns the device says so when it is offered one."""
        self._safing = True
        await self.driver.safe_state()

    async def _run(self, task: str, attempt: int, token: str, cmd: dict) -> None:
        spec, faults = self.spec, self.spec.faults
        step = cmd["step"]

        def emit(kind: Kind, body: dict) -> None:
            self._emit(kind, body, task, attempt, token)

        def telemetry(readings: dict) -> None:
            self._habits.reported(self._q.now, "telemetry")
            emit(Kind.TELEMETRY, {"readings": readings})

        def progress(fraction: float, note: str = "") -> None:
            self._habits.reported(self._q.now, "progress")
            emit(Kind.PROGRESS, {"fraction": fraction, "note": note})

        key = f"{self._campaign}/{task}" if self._shared else task
        ctx = StepContext(
            clock=self._clock,  # type: ignore[arg-type]
            rng=self._step_rngs.keyed(f"{self._seed}:steps:{key}:{attempt}"),
            duration=spec.duration,
            progress=progress,
            telemetry=telemetry,
            expected_s=cmd["expected_s"],
            deadline_s=cmd.get("deadline_s"),
        )
        emit(Kind.ACCEPTED, {})
        try:
            hang, fail = simulated_faults(self._seed, key, attempt, faults)
            await self._clock.sleep(spec.setup_s)
            if hang:
                await Park()  # only a cancel (a timeout) ends a hung step
            driver = self._shared.get(self._campaign, self.driver)
            asked, slept = self._clock.made, self._slept
            result = step_result(await driver.run(step, cmd["params"], cmd["sample"], ctx), driver)
            if self._clock.made - asked > self._slept - slept:
                self._habits.sleep_not_awaited(step)
            await self._clock.sleep(spec.clean_s)
            if fail:
                emit(Kind.FAULT, {"code": "failed", "reason": f"{step} failed on {self.name} (simulated)"})
            else:
                emit(Kind.RESULT, {"outputs": result.outputs, "sample": result.sample})
        except asyncio.CancelledError:
            if self._cancel_reason == "cancel":
                await self._to_safety()
                emit(Kind.FAULT, {"code": "cancelled", "reason": f"{step} cancelled on {self.name}"})
            else:
                raise
        except Refused as no:
            emit(Kind.REJECTED, {"reason": str(no.reason)[:500], "infeasible": bool(no.infeasible)})
        except PLUGIN_ERRORS as exc:  # a driver bug must never take the lab down
            self._log_raised("%s: driver raised during %s: %s", self.name, step, fault_text(exc))
            await self._to_safety()
            emit(Kind.FAULT, {"code": "driver_error", "reason": fault_text(exc)})
        finally:
            self._job = self._current = None
            self._cancel_reason, self._safing = "", False


def _complete(coro: Any, name: str, device_type: str) -> Any:
    """Run a coroutine that must not wait (``safe_state``) to its end."""
    try:
        while True:
            req = coro.send(None)
            if type(req) is not Sleep:
                coro.close()
                raise FastRuntimeRefused(f"{name}: safe_state() awaited {req!r}; in the fast runtime it may only "
                                         "sleep", device_type)
    except StopIteration as done:
        return done.value
