"""The device actor: a driver on the bus, with presence and simulated faults.

The actor owns messaging (commands in; accepted, progress, result and fault
out), its liveliness token, and the faults a scenario declares: a step that
fails, a step that hangs until cancelled, and crashes (the device vanishes
from the bus, token and all, and comes back after ``restart_s``). The driver
only does the work.
"""

from __future__ import annotations

import asyncio
import collections
import functools
import itertools
import logging
from typing import Any

from twin.core import keys, log_floods
from twin.core.bus import Bus, Closable
from twin.core.clock import LabClock, end_by_force, wait_cancelled, wall_on_loop
from twin.core.streams import KeyedGenerator, seeded
from twin.device.habits import Habits, timed
from twin.device.driver import (SWALLOWED, Driver, StepContext, busy_with, fault_text, feature,
                                simulated_faults, step_result)
from twin.core.errors import PLUGIN_ERRORS, DriverError, Refused
from twin.core.messages import CommandBody, InvalidMessage, Kind, decode, pack, to_wire, within_limit

log = logging.getLogger(__name__)
# a driver's health() is given this much wall time: whoever asks waits 3 s (twin device health) to 5 s, and hears
# the rest of the device's report rather than nothing
HEALTH_WALL_S = 2.0


class DeviceActor:
    def __init__(self, name: str, spec: Any, driver: Driver, bus: Bus, clock: LabClock, lab: str, seed: int,
                 orphan_grace_s: float = 300.0, shared: dict[str, Driver] | None = None,
                 stop_grace_s: float = 60.0, served_as: dict[str, Any] | None = None) -> None:
        """``shared``: the device serves several campaigns — campaign -> the driver that simulates its chemistry;
        their steps draw faults and durations by campaign too (their task ids repeat). ``stop_grace_s``: lab
        seconds ``safe_state`` has at shutdown before the lab stops without it (``orchestrator.cancel_grace_s``).
        ``served_as``: the parts of its scenario it runs by, in its health answer (a lab compares them with its own:
        twin/runtime/served_devices.py)."""
        self.name, self.spec, self.driver, self.served_as = name, spec, driver, served_as
        self._shared = shared or {}
        self.orphan_grace_s, self.stop_grace_s = orphan_grace_s, stop_grace_s
        self._boss: Closable | None = None
        self._orphan_timer: asyncio.TimerHandle | None = None
        self._bus, self._clock, self._lab = bus, clock, lab
        self._seed = seed
        self._crash_rng, _ = seeded(seed, "crashes", name)
        self._step_rngs = KeyedGenerator()
        self._habits = Habits(name)
        self._ids = itertools.count(1)
        self._evt_key = keys.evt(lab, name)
        self._job: asyncio.Task | None = None
        self._current: tuple[str, int] | None = None
        self._safing = False  # the step has ended; the driver's safe_state() has not returned
        self._token_of_current = ""
        self._cancel_reason = ""
        self._forced: asyncio.Future | None = None  # a step ended by force (its driver swallowed the cancel)
        self._sub: Closable | None = None
        self._token: Closable | None = None
        self._health: Closable | None = None
        self._crasher: asyncio.Task | None = None
        self._recent: collections.deque[tuple[str, int, bytes]] = collections.deque(maxlen=16)
        self.dropped = 0

    def add_campaign(self, campaign: str, driver: Driver) -> None:
        """A campaign submitted to the shared lab it serves: ``driver`` simulates that campaign's chemistry."""
        self._shared[campaign] = driver

    # -- life cycle -------------------------------------------------------
    async def start(self) -> None:
        self._health = self._bus.serve(keys.health(self._lab, self.name), self._report_health)
        self._boss = self._bus.watch_tokens(keys.orchestrator(self._lab), self._on_orchestrator)
        connect = feature(self.driver, "connect")
        if connect is not None:  # an instrument with presence of its own (MQTT last will, say)
            try:
                await timed(connect(self._instrument_presence), self._habits)
            except PLUGIN_ERRORS as exc:
                raise DriverError(f"{self.name}: its driver's connect() failed: {type(exc).__name__}: {exc}; it "
                                  "did not start: check that the instrument is on and can be reached, then start "
                                  "again") from exc
        else:
            self._online()
        if self.spec.faults.mtbc_h > 0:
            self._crasher = asyncio.ensure_future(self._crash_loop())
            self._crasher.add_done_callback(self._crash_loop_ended)

    async def stop(self) -> None:
        if self._boss is not None:
            self._boss.close()
        if self._orphan_timer is not None:
            self._orphan_timer.cancel()
        if self._crasher:
            await wait_cancelled(self._crasher)
        job = self._job
        if job is not None:
            self._cancel_reason = "stop"
            await wait_cancelled(job)
            if not job.done():
                log.error("%s: %s", self.name, SWALLOWED)
                self._forced = job
                end_by_force(job)
        try:
            async with asyncio.timeout(self.stop_grace_s):  # lab time: on a virtual clock, no wait at all
                await timed(self.driver.safe_state(), self._habits)
        except TimeoutError:  # a driver that never returns must not keep the lab from ending
            log.error("%s: safe_state() did not return within %g lab-s at shutdown (orchestrator.cancel_grace_s); "
                      "the lab stopped without it: check the instrument by hand", self.name, self.stop_grace_s)
        except PLUGIN_ERRORS as exc:  # stopping goes on: the token goes, the other devices stop too
            log.error("%s: safe_state() failed at shutdown: %r; check the instrument by hand", self.name, exc)
        self._offline()
        if self._health is not None:
            self._health.close()
        disconnect = feature(self.driver, "disconnect")
        if disconnect is not None:
            try:
                await timed(disconnect(), self._habits)
            except PLUGIN_ERRORS as exc:  # the lab has ended: its summary and the other devices' stops go on
                log.error("%s: disconnect() failed at shutdown: %r; check the instrument's connection by hand",
                          self.name, exc)

    async def _report_health(self, key: str, payload: bytes) -> bytes:
        """``labtwin/<lab>/dev/<name>/health``: the actor's state and, if it has ``health()``, the driver's."""
        report: dict = {"device": self.name, "on_bus": self._token is not None, "dropped": self.dropped,
                        "t_lab": self._clock.now(), "clock": {"mode": self._clock.mode, "speed": self._clock.speed,
                                                              "in_lab_time": self._clock.anchored},
                        "running": list(self._current) if self._current else None,
                        "recent": [[t, n, p.decode()] for t, n, p in self._recent]}
        if self.served_as is not None:
            report["scenario"] = self.served_as
        check = feature(self.driver, "health")
        if check is not None:
            try:
                async with asyncio.timeout(wall_on_loop(HEALTH_WALL_S)):
                    report["driver"] = await timed(check(), self._habits)  # a blocking one is said, as run's
            except TimeoutError:  # the device answers still: its driver's part is what is missing
                report["driver"] = {"ok": False, "error": f"health() did not return within {HEALTH_WALL_S:g} s"}
            except PLUGIN_ERRORS as exc:  # a failing health check is itself the answer
                report["driver"] = {"ok": False, "error": fault_text(exc)}
        try:
            return to_wire(report)  # numpy's numbers as numbers
        except (TypeError, ValueError, OverflowError) as exc:  # what health() returned cannot be JSON
            report["driver"] = {"ok": False, "error": f"health() returned what is not JSON: {fault_text(exc, 200)}"}
            return to_wire(report)

    def _on_orchestrator(self, key: str, alive: bool) -> None:
        """The campaign came or went: a step it can no longer supervise is stopped after a grace period."""
        if self._orphan_timer is not None:
            self._orphan_timer.cancel()
            self._orphan_timer = None
        if not alive:
            self._orphan_timer = self._clock.call_later(self.orphan_grace_s, self._orphaned)
        # said where a device serves in a process of its own (`twin device serve` logs at info): a lab that ended
        # left it serving without a word, and it serves on for a `twin resume`
        log.info("%s: lab %s's campaign %s", self.name, self._lab,
                 "is on the bus" if alive else "left the bus (it ended, or died: `twin resume` brings it back); "
                                               "serving on until Ctrl-C")

    def _orphaned(self) -> None:
        self._orphan_timer = None
        if self._job is not None:
            log.warning("%s: the orchestrator has been gone %.0f lab-s; stopping %s in a safe state", self.name,
                        self.orphan_grace_s, self._current)
            self._cancel_reason = "orphaned"
            self._job.cancel()

    def _instrument_presence(self, present: bool) -> None:
        """The driver's instrument came or went: the device's presence on the bus follows it."""
        if present and self._token is None:
            log.info("%s: instrument present", self.name)
            self._online()
        elif not present and self._token is not None:
            log.warning("%s: instrument gone; leaving the bus", self.name)
            self._offline()
            if self._job is not None:
                self._cancel_reason = "lost"
                self._job.cancel()

    def _online(self) -> None:
        self._sub = self._bus.subscribe(keys.cmd(self._lab, self.name), self._on_cmd)
        self._token = self._bus.declare_token(keys.alive(self._lab, self.name))

    def _offline(self) -> None:
        for handle in (self._sub, self._token):
            if handle is not None:
                handle.close()
        self._sub = self._token = None

    async def _crash_loop(self) -> None:
        faults = self.spec.faults
        while True:
            await self._clock.sleep(self._crash_rng.expovariate(1.0 / (faults.mtbc_h * 3600)))
            log.info("%s crashed at t=%.0f s", self.name, self._clock.now())
            self._offline()
            if self._job is not None:
                self._cancel_reason = "crash"
                await wait_cancelled(self._job)
            await self._clock.sleep(faults.restart_s)
            self._online()

    # -- messages ---------------------------------------------------------
    def _emit(self, kind: Kind, body: dict, task: str, attempt: int, campaign: str, token: str,
              key: str | None = None) -> None:
        payload = within_limit(kind, pack(kind, body, id=f"{self.name}:{next(self._ids)}", sender=self.name,
                                          t_lab=self._clock.now(), campaign=campaign, task=task, attempt=attempt,
                                          token=token))
        if kind in (Kind.RESULT, Kind.FAULT):
            self._recent.append((task, attempt, payload))  # a campaign that died may ask for it (twin resume)
        self._bus.publish(key or self._evt_key, payload)

    def _on_cmd(self, key: str, payload: bytes) -> None:
        try:
            env, body = decode(payload, sender_hint=key)
        except InvalidMessage as exc:
            self._drop(str(exc))
            return
        if env.kind == Kind.COMMAND:
            if not self._clock.anchored:  # it would stamp its samples in a time of its own
                self._emit(Kind.REJECTED, {"reason": f"{self.name} has not heard lab {self._lab}'s clock yet"},
                           env.task, env.attempt, env.campaign, env.token)
                return
            if self._job is not None:
                self._emit(Kind.REJECTED, busy_with(self._current, self._safing), env.task, env.attempt, env.campaign,
                           env.token)
                return
            self._current, self._token_of_current = (env.task, env.attempt), env.token
            self._job = asyncio.ensure_future(self._run(env.task, env.attempt, env.campaign, env.token, body))  # type: ignore[arg-type]
            self._job.add_done_callback(functools.partial(self._job_ended, env.task, env.attempt, env.campaign,
                                                          env.token))
        elif env.kind == Kind.CANCEL:
            if self._current == (env.task, env.attempt) and self._job and env.token == self._token_of_current:
                self._cancel_reason = "cancel"  # only the orchestrator knows the token
                self._job.cancel()
            elif self._current == (env.task, env.attempt):
                self._drop(f"a cancel of {env.task}#{env.attempt} without its token")
        else:
            self._drop(f"a {env.kind} message from {env.sender!r} on its command key")

    def _job_ended(self, task: str, attempt: int, campaign: str, token: str, job: asyncio.Future) -> None:
        """A step that died in the actor's own handling (a safe_state() that raised, say) is reported, not lost."""
        if job.cancelled() or job.exception() is None or job is self._forced:  # forced: said already
            return
        exc = job.exception()
        log.error("%s: step %s#%d died in the device's own handling: %s; reported as a driver error", self.name,
                  task, attempt, fault_text(exc))
        self._emit(Kind.FAULT, {"code": "driver_error", "reason": fault_text(exc, 500)}, task, attempt, campaign,
                   token)

    def _crash_loop_ended(self, loop_task: asyncio.Future) -> None:
        if loop_task.cancelled() or loop_task.exception() is None:
            return
        log.error("%s: its simulated crashes stopped with %r; the device leaves the bus, and the campaign moves "
                  "its work", self.name, loop_task.exception())
        self._offline()

    def _drop(self, what: str) -> None:
        self.dropped += 1  # the health report has the count
        if log_floods.said(self.dropped):
            log.warning("%s dropped %s (%d so far)", self.name, what, self.dropped)

    def _driver_for(self, campaign: str) -> Driver:
        """The driver for a step of ``campaign``: in a shared lab, the one that simulates its chemistry. A
        simulator has none for a campaign its lab file did not list (one submitted later): it says so, and the
        step is retried later, when the device may have been served again with a lab file that lists it."""
        if not self._shared or campaign in self._shared or not feature(self.driver, "chemistry_models"):
            return self._shared.get(campaign, self.driver)  # a real instrument runs any campaign's steps
        raise Refused(f"{self.name} simulates the chemistry of campaigns {', '.join(sorted(self._shared))} (its "
                      f"lab file's), not campaign {campaign!r}'s: serve it again with a lab file that lists "
                      f"{campaign!r} (twin device serve LAB.yaml --id {self.name})", infeasible=False)

    async def _to_safety(self) -> None:
        """The driver's ``safe_state`` after a step; until it returns the device says so when it is offered one."""
        self._safing = True
        await timed(self.driver.safe_state(), self._habits)

    async def _run(self, task: str, attempt: int, campaign: str, token: str, cmd: CommandBody) -> None:
        spec, faults = self.spec, self.spec.faults

        def emit(kind: Kind, body: dict, key: str | None = None) -> None:
            self._emit(kind, body, task, attempt, campaign, token, key)

        def telemetry(readings: dict) -> None:
            self._habits.reported(self._clock.now(), "telemetry")
            emit(Kind.TELEMETRY, {"readings": readings}, keys.telemetry(self._lab, self.name))

        def progress(fraction: float, note: str = "") -> None:
            self._habits.reported(self._clock.now(), "progress")
            emit(Kind.PROGRESS, {"fraction": fraction, "note": note})

        drawn_by = f"{campaign}/{task}" if self._shared else task
        ctx = StepContext(
            clock=self._clock,
            rng=self._step_rngs.keyed(f"{self._seed}:steps:{drawn_by}:{attempt}"),
            duration=spec.duration,
            progress=progress,
            telemetry=telemetry,
            expected_s=cmd.expected_s,
            deadline_s=cmd.deadline_s,
        )
        try:
            driver = self._driver_for(campaign)
            emit(Kind.ACCEPTED, {})
            hang, fail = simulated_faults(self._seed, drawn_by, attempt, faults)
            await self._clock.sleep(spec.setup_s)
            if hang:
                await asyncio.Event().wait()  # only a cancel (a timeout) ends a hung step
            result = step_result(await timed(driver.run(cmd.step, cmd.params, cmd.sample, ctx), self._habits), driver)
            await self._clock.sleep(spec.clean_s)
            if fail:
                emit(Kind.FAULT, {"code": "failed", "reason": f"{cmd.step} failed on {self.name} (simulated)"})
            else:
                emit(Kind.RESULT, {"outputs": result.outputs, "sample": result.sample})
        except asyncio.CancelledError:
            if self._cancel_reason == "cancel":
                await self._to_safety()
                emit(Kind.FAULT, {"code": "cancelled", "reason": f"{cmd.step} cancelled on {self.name}"})
            elif self._cancel_reason == "orphaned":
                await self._to_safety()
                emit(Kind.FAULT, {"code": "cancelled", "reason": f"{cmd.step} stopped on {self.name}: the "
                                  f"orchestrator was gone for {self.orphan_grace_s:.0f} lab-s"})
            else:
                raise
        except Refused as no:
            emit(Kind.REJECTED, {"reason": str(no.reason)[:500], "infeasible": bool(no.infeasible)})
        except PLUGIN_ERRORS as exc:  # a driver bug must never take the actor down
            log.warning("%s: driver raised during %s: %s", self.name, cmd.step, fault_text(exc))
            await self._to_safety()
            emit(Kind.FAULT, {"code": "driver_error", "reason": fault_text(exc)})
        finally:
            self._job, self._current, self._cancel_reason, self._safing = None, None, "", False
