"""The driver contract: what a device does, without its messaging, timeouts or faults.

A driver runs one step at a time. It takes no ``timeout=``: the orchestrator
owns deadlines and cancels the step (an ``asyncio.CancelledError`` inside
``run``), after which the runtime calls ``safe_state``. Raise ``DriverError``
(or anything) to report a failed step; the runtime turns it into a fault.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from twin.core.clock import Clock
from twin.core.errors import DriverError
from twin.core.messages import SAFING
from twin.core.streams import keyed_uniforms

DRIVER_API = 1  # a driver may say which it was written for: ``labtwin_api = 1``


@dataclass
class DriverSetup:
    """What a driver is built from: its scenario entry, the chemistry, and its seeds."""

    name: str
    device_type: str
    options: dict[str, Any]
    chemistry: Any  # twin.scenario.Chemistry
    duration: Any  # twin.scenario.Duration
    seed: int


@dataclass
class StepResult:
    outputs: dict[str, Any] = field(default_factory=dict)
    sample: dict[str, Any] | None = None


def talks_to_instrument(driver: Any) -> bool:
    """Whether ``driver`` (a class or an instance) reaches a real instrument: it keeps wall time, or connects."""
    return bool(feature(driver, "realtime")) or callable(feature(driver, "connect"))


def fault_text(exc: BaseException, most: int = 1000) -> str:
    """What a driver raised, as its step's fault and the log say it: type and message, cut to ``most`` characters
    (a driver that put a whole trace in its message flooded the log, and its fault went over a message's size)."""
    text = f"{type(exc).__name__}: {exc}"
    return text if len(text) <= most else f"{text[:most]}… ({len(text):,} characters)"


def step_result(result: Any, driver: Any) -> StepResult:
    """What ``driver.run`` returned, if it is a ``StepResult`` (or has its two fields); else the driver's error,
    saying what to return."""
    if isinstance(result, StepResult) or (hasattr(result, "outputs") and hasattr(result, "sample")):
        name = type(driver).__name__
        if not isinstance(result.outputs, Mapping):
            raise DriverError(f"{name}.run() returned outputs of type {type(result.outputs).__name__} "
                              f"{repr(result.outputs)[:60]}: outputs are what was measured, by name: "
                              "StepResult({name: value, ...}, sample)")
        if result.sample is not None and not isinstance(result.sample, Mapping):
            raise DriverError(f"{name}.run() returned a sample of type {type(result.sample).__name__} "
                              f"{repr(result.sample)[:60]}: a sample is a mapping of its fields (the one given, "
                              "updated), or None to pass on the one given")
        return result
    hint = (": a tuple (outputs, sample)? return StepResult(outputs, sample)" if isinstance(result, tuple) else
            ": return StepResult(outputs, sample)")
    raise DriverError(f"{type(driver).__name__}.run() returned {type(result).__name__} {repr(result)[:60]}, "
                      f"not a StepResult{hint}")


@dataclass
class StepContext:
    """What a running step may use: lab time, randomness, and ways to report."""

    clock: Clock
    rng: np.random.Generator
    duration: Any  # twin.scenario.Duration
    progress: Callable[..., None]  # progress(fraction, note="")
    telemetry: Callable[[dict[str, float]], None]
    expected_s: float = 0.0  # lab seconds the lab expects the step to take
    deadline_s: float | None = None  # lab seconds from dispatch after which the lab cancels the step

    def draw_duration(self, params: Mapping[str, Any] | None = None) -> float:
        """A lognormal draw around the scenario's mean, plus the parameter it names (``duration.plus_param``: then
        the step's ``params`` are needed)."""
        d = self.duration
        if params is None:
            if d.plus_param:
                raise TypeError(f"draw_duration() needs the step's params: this device type's duration adds the "
                                f"parameter {d.plus_param!r} (duration.plus_param); call ctx.draw_duration(params)")
            params = {}
        base = d.mean_s
        if base > 0 and d.cv > 0:
            sigma = math.sqrt(math.log(1 + d.cv**2))
            base = float(self.rng.lognormal(math.log(base) - sigma**2 / 2, sigma))
        extra = float(params.get(d.plus_param, 0.0)) if d.plus_param else 0.0
        return base + extra


class Driver(Protocol):
    capabilities: frozenset[str]

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult: ...

    async def safe_state(self) -> None: ...


class DriverFeatures(Protocol):
    """What a driver may add to ``Driver``; each is optional, and ``feature`` finds it (or None).

    ``labtwin_api``: the driver API it was written for. ``realtime``: it talks to a real instrument
    (refuses a virtual clock). ``connect(presence)``/``disconnect()``: an instrument with a connection
    and a presence of its own. ``health()``: what the device's health key reports about it.
    ``outputs``: every output name its results can hold (a target on an output no device of the
    workflow produces is then refused by ``twin validate``). ``chemistry_models``: the scenario
    ``chemistry.model`` values it can simulate (others are refused). ``option_names``: every key its
    ``setup.options`` may hold (a misspelt one is then refused, naming the field). ``duration_param``: the
    experiment parameter (lab seconds) its steps last at least as long as, a hold time (a scenario whose
    duration model leaves it out, with deadlines shorter than its highest value, is then warned of).
    ``makes_sample``: the steps after which the experiment has a sample (a synthesis; a step that only passes on
    the sample it was given is not one); ``needs_sample``: the steps it refuses without one (a measurement).
    A workflow with a step that needs a sample and, before it, only steps whose drivers say they make none is
    then refused by ``twin validate``, naming the step. ``claims``: what this instance holds alone, as text (an
    MQTT topic on a broker, a serial port); two devices of a lab that claim the same are refused by ``twin
    validate``, naming both.
    """

    labtwin_api: int
    realtime: bool
    outputs: frozenset[str]
    chemistry_models: frozenset[str]
    option_names: frozenset[str]
    duration_param: str
    makes_sample: frozenset[str]
    needs_sample: frozenset[str]
    claims: str

    async def connect(self, presence: Callable[[bool], None]) -> None: ...

    async def disconnect(self) -> None: ...

    async def health(self) -> dict[str, Any]: ...


FEATURES = frozenset({"labtwin_api", "realtime", "connect", "disconnect", "health", "outputs", "chemistry_models",
                      "option_names", "duration_param", "makes_sample", "needs_sample", "claims"})


def feature(driver: Any, name: str) -> Any:
    """The driver's optional feature ``name`` (one of ``DriverFeatures``), or None."""
    if name not in FEATURES:
        raise ValueError(f"{name!r} is not a driver feature: {sorted(FEATURES)}")
    return getattr(driver, name, None)


def capabilities(driver: Any, who: str) -> frozenset[str]:
    """The step names a driver runs; a declaration that is not a collection of them is refused, saying why."""
    caps = getattr(driver, "capabilities", None)
    if caps is None:
        raise DriverError(f"{who} declares no capabilities: give its class capabilities = "
                          "frozenset({'measure', ...}), the steps it runs")
    return _step_names(caps, "capabilities", who)


def _step_names(steps: Any, name: str, who: str) -> frozenset[str]:
    """A driver's declaration ``name`` of step names as a frozenset; anything else is refused, saying why."""
    if isinstance(steps, str) or not isinstance(steps, (set, frozenset, list, tuple)) or \
            not all(isinstance(c, str) for c in steps):
        example = f"{{{steps!r}}}" if isinstance(steps, str) else "{'measure', ...}"
        raise DriverError(f"{who}: {name} is {str(steps)[:60]!r}, not a set of step names: write "
                          f"{name} = frozenset({example})")
    return frozenset(steps)


def declared_steps(driver: Any, name: str, who: str) -> frozenset[str] | None:
    """The step names a driver's optional feature ``name`` (``makes_sample``, ``needs_sample``) declares, or None
    if it declares none; a declaration that is not a collection of step names is refused, saying why."""
    steps = feature(driver, name)
    return None if steps is None else _step_names(steps, name, who)


#: said of a device whose driver went on after its step was cancelled, when the lab stops
SWALLOWED = ("its driver went on after the lab cancelled its step (run() caught asyncio.CancelledError and did not "
             "re-raise it, or a bare except: did); the step was ended by force at shutdown. Stop the instrument in "
             "`except CancelledError:` and re-raise (docs/drivers.md)")


def busy_with(running: tuple[str, int], safing: bool = False) -> dict[str, str]:
    """The "not now" a device answers while it runs a step (one at a time: the lab retries it later); ``safing``:
    the step has ended, and its driver's ``safe_state`` has not returned."""
    task, attempt = running
    return {"reason": f"busy with {task} (attempt {attempt}){SAFING if safing else ''}"}


def simulated_faults(seed: int, task: str, attempt: int, faults: Any) -> tuple[bool, bool]:
    """Whether this attempt hangs, and whether it fails: drawn from the (seed, task, attempt) stream,
    so the draw does not depend on which device runs it or what ran before."""
    if not (faults.hang_p > 0 or faults.fail_p > 0):
        return False, False
    u_hang, u_fail = keyed_uniforms(f"{seed}:faults:{task}:{attempt}")
    return u_hang < faults.hang_p, u_fail < faults.fail_p
