"""The driver contract: what a device does, without its messaging, timeouts or faults.

A driver runs one step at a time. It takes no ``timeout=``: the orchestrator
owns deadlines and cancels the step (an ``asyncio.CancelledError`` inside
``run``), after which the runtime calls ``safe_state``. Raise ``DriverError``
(or anything) to report a failed step; the runtime turns it into a fault.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from twin.clock import Clock

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


@dataclass
class StepContext:
    """What a running step may use: lab time, randomness, and ways to report."""

    clock: Clock
    rng: np.random.Generator
    duration: Any  # twin.scenario.Duration
    progress: Callable[[float, str], None]
    telemetry: Callable[[dict[str, float]], None]

    def draw_duration(self, params: dict[str, Any]) -> float:
        """A lognormal draw around the scenario's mean, plus the parameter it names."""
        d = self.duration
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


def expected_duration(duration: Any, params: dict[str, Any], setup_s: float, clean_s: float) -> float:
    """The step's mean duration, which the orchestrator turns into a deadline."""
    extra = float(params.get(duration.plus_param, 0.0)) if duration.plus_param else 0.0
    return duration.mean_s + extra + setup_s + clean_s


def seeded(seed: int, *names: str) -> tuple[random.Random, np.random.Generator]:
    """Independent, reproducible streams per (seed, names)."""
    key = ":".join([str(seed), *names])
    r = random.Random(key)
    return r, np.random.default_rng(r.getrandbits(64))


def simulated_faults(seed: int, task: str, attempt: int, faults: Any) -> tuple[bool, bool]:
    """Whether this attempt hangs, and whether it fails: drawn from the (seed, task, attempt) stream,
    so the draw does not depend on which device runs it or what ran before."""
    if not (faults.hang_p > 0 or faults.fail_p > 0):
        return False, False
    r = random.Random(f"{seed}:faults:{task}:{attempt}")
    hang = faults.hang_p > 0 and r.random() < faults.hang_p
    fail = faults.fail_p > 0 and r.random() < faults.fail_p
    return hang, fail
