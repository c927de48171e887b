"""One experiment at a time, straight through a scenario's drivers: no bus, no orchestrator.

The planning environment (and anything else that needs many experiments fast)
runs the same drivers, physics, noise and sample ageing as a campaign, but
calls each step in turn on a *stepped clock*: ``sleep`` adds to the lab time
and returns without suspending, so a step's coroutine finishes in one
``send`` and no event loop is needed. Device faults, set-up and cleaning
times are the orchestrator's and actors' business and are left out.

A driver's refusal is taken as a campaign takes it: ``Refused(infeasible=True)`` ends the experiment with no
outputs, marked ``infeasible``; a "not now" is asked again after the scenario's retry back-off, lab time
passing, up to ``orchestrator.retry.max_attempts`` times. So is its fault (it raised, or returned what is not a
``StepResult``): the step is tried again, up to ``max_attempts`` times, and then the experiment ends with no
outputs, marked ``failed``; a driver that has failed every experiment, ten of them, is named. People (``driver:
operator``) confirm their step after its expected duration, as a virtual-time campaign's simulated operator does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from twin.campaign.human import DRIVER as HUMAN
from twin.campaign.policy import outside_envelope
from twin.core.clock import ClockMode, lab_seconds
from twin.core.streams import seeded
from twin.device.driver import StepContext, StepResult, step_result, talks_to_instrument
from twin.core.errors import DriverError, Refused
from twin.scenario import Scenario
from twin.scenario.model import DeviceType, expected_duration


class SteppedClock:
    """Lab time that advances only when a driver sleeps."""

    mode: ClockMode = "virtual"

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    async def sleep(self, seconds: float) -> None:
        self.t += max(0.0, lab_seconds(seconds))

    async def sleep_until(self, t_lab: float) -> None:
        self.t = max(self.t, lab_seconds(t_lab, "sleep_until"))

    def timeout(self, seconds: float | None) -> Any:
        raise DriverError("clock.timeout() is not available to a driver in a workcell: the caller owns timeouts")


@dataclass
class Measured:
    outputs: dict[str, Any]  # every step's outputs, as a planner would see them
    lab_s: float  # lab time the workflow took
    infeasible: str = ""  # why a device refused these parameters for good (then no outputs)
    failed: str = ""  # the driver's fault, each attempt failing (then no outputs)


#: experiments failed, none measured yet, before the workcell says the driver cannot run at all
FAILED_FROM_THE_START = 10


class _Failed(Exception):
    """A step whose every attempt failed (the driver raised): the experiment is abandoned, as in a campaign."""


class Workcell:
    """Runs ``scenario``'s workflow for given parameters on one instance of each device type."""

    def __init__(self, scenario: Scenario, drivers: dict[str, Any], seed: int = 0) -> None:
        self.scenario, self.drivers = scenario, drivers
        self.clock = SteppedClock()
        self._failed, self._measured, self._runs = 0, False, 0
        self._fenced = any(scenario.devices[w.device].envelope for w in scenario.workflow)
        self.reseed(seed)

    def reseed(self, seed: int) -> None:
        self.clock.t = 0.0
        self._rngs = {dtype: seeded(seed, "workcell", dtype)[1] for dtype in self.drivers}

    def run(self, params: dict[str, Any]) -> Measured:
        """One experiment: each step given the experiment's parameters with its own (its own win, as in a
        campaign); its outputs are every step's numbers and texts, a later step's winning, as a campaign keeps
        them (a spectrum or a trace is left out)."""
        start = self.clock.t
        outside = self._fenced and outside_envelope(self.scenario.workflow, params, self.scenario.devices)
        if outside:  # a campaign refuses it before anything is sent
            return Measured({}, 0.0, infeasible=outside)
        sample: Any = None
        outputs: dict[str, Any] = {}
        self._runs += 1
        for w in self.scenario.workflow:
            spec = self.scenario.devices[w.device]
            ctx = StepContext(clock=self.clock, rng=self._rngs[w.device], duration=spec.duration,
                              progress=lambda *_: None, telemetry=lambda _: None)
            try:
                result = self._step(w, {**params, **w.params} if w.params else params, sample, ctx)
            except Refused as refused:
                return Measured({}, self.clock.t - start, infeasible=f"{w.device} refused {w.step!r}: {refused.reason}")
            except _Failed as failed:
                self._failed += 1
                if not self._measured and self._failed >= FAILED_FROM_THE_START:
                    raise DriverError(f"the first {self._failed} experiments in a workcell all failed; the last: "
                                      f"{failed}. Fix the driver, or give devices.{w.device}.twin a simulated "
                                      "driver that stands in for it") from None
                return Measured({}, self.clock.t - start, failed=str(failed))
            if result.sample is not None:  # None passes on the one given; its id is the lab's, as in a campaign
                sample = {**result.sample, "id": sample["id"] if sample is not None else f"workcell/e{self._runs}"}
            for k, v in result.outputs.items():
                if not isinstance(v, (list, dict)):
                    outputs[k] = v
        self._measured = True
        return Measured(outputs, self.clock.t - start)

    def _step(self, w: Any, params: dict[str, Any], sample: Any, ctx: StepContext) -> Any:
        """The step's result; a "not now" asked again later. Raises ``Refused`` only for good."""
        retry, driver = self.scenario.orchestrator.retry, self.drivers[w.device]
        fault = ""
        for attempt in range(retry.max_attempts):
            try:
                return step_result(_complete(driver.run(w.step, params, sample, ctx), w.device), driver)
            except Refused as refused:
                if refused.infeasible:
                    raise
                reason = refused.reason
                self.clock.t += min(retry.backoff_s * 2 ** attempt, retry.backoff_max_s)
            except _NotStepped:
                raise
            except (Exception, SystemExit) as exc:  # the driver's fault: a campaign tries the step again, later
                fault = f"{w.device} failed {w.step!r}: {type(exc).__name__}: {exc}"
                self.clock.t += min(retry.backoff_s * 2 ** attempt, retry.backoff_max_s)
        if fault:
            raise _Failed(f"{fault} ({retry.max_attempts} attempts)")
        raise DriverError(f"the {w.device} driver answered 'not now' to {w.step!r} {retry.max_attempts} times in a "
                          f"row in a workcell (last: {reason}); a workcell has nothing else to wait for: raise "
                          "orchestrator.retry.max_attempts or backoff_s, or make the driver ready sooner")


class _NotStepped(DriverError):
    """A driver that waits on something other than the lab clock: no attempt would do better."""


def _complete(coro: Any, device: str) -> Any:
    try:
        coro.send(None)
    except StopIteration as done:
        return done.value
    coro.close()
    raise _NotStepped(f"the {device} driver waited on something other than the lab clock; it cannot run in a "
                      f"workcell: give devices.{device}.twin: {{driver: NAME}}, a simulated driver that stands in "
                      "for it (docs/drivers.md)")


class _Person:
    """People in a workcell: their step is confirmed after its expected duration, and the sample goes on as it was
    (a campaign's people make no outputs)."""

    def __init__(self, spec: DeviceType) -> None:
        self.capabilities, self.duration = frozenset(spec.steps), spec.duration

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        await ctx.clock.sleep(expected_duration(self.duration, params, 0.0, 0.0))
        return StepResult({}, sample)

    async def safe_state(self) -> None:
        """Nothing to make safe."""


def open_workcell(scenario: Scenario, seed: int = 0) -> Workcell:
    """A workcell with one driver of each device type the workflow uses: a type's twin where it has one, since a
    workcell is simulated whatever the scenario's clock; people as their simulated selves (``_Person``)."""
    from twin.runtime.assembly import load_driver

    used = dict.fromkeys(w.device for w in scenario.workflow)
    drivers = {d: _Person(scenario.devices[d]) if scenario.devices[d].driver == HUMAN else
               load_driver(scenario, d, f"{d}-workcell", simulated=True) for d in used}
    real = [d for d, drv in drivers.items() if talks_to_instrument(drv)]
    if real:
        raise DriverError(f"devices.{real[0]}: its driver talks to an instrument, which a workcell (simulated) "
                          f"cannot: give devices.{real[0]}.twin: {{driver: NAME}}, a simulated driver that stands "
                          "in for it (docs/drivers.md)")
    return Workcell(scenario, drivers, seed)
