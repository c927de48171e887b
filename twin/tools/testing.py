"""Helpers for testing a device driver against labtwin (used by `twin driver new`'s scaffold)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from twin.core.clock import LabClock
from twin.device.driver import DriverSetup, StepContext, StepResult, step_result
from twin.runtime.lab import prepare, run
from twin.scenario import Chemistry, Duration
from twin.campaign.summary import Summary


def driver_setup(name: str = "device-1", options: dict[str, Any] | None = None, mean_s: float = 60.0,
                 chemistry: Chemistry | None = None, seed: int = 0) -> DriverSetup:
    """What the lab would build a driver from."""
    return DriverSetup(name, name.rsplit("-", 1)[0], dict(options or {}), chemistry or Chemistry(model="none"),
                       Duration(mean_s=mean_s, cv=0.0), seed)


def run_step(driver: Any, step: str, params: dict[str, Any], sample: dict | None = None,
             seed: int = 0, setup: DriverSetup | None = None, mean_s: float | None = None) -> tuple[StepResult, float]:
    """Run one step of ``driver`` on a virtual clock: (its result, the lab seconds it took).

    ``ctx.draw_duration`` follows ``setup``'s duration (the ``driver_setup(...)`` the driver was built
    from), or ``mean_s`` (no spread), or 60 s."""
    clock = LabClock("virtual")
    duration = setup.duration if setup is not None else Duration(mean_s=60.0 if mean_s is None else mean_s, cv=0.0)
    ctx = StepContext(clock=clock, rng=np.random.default_rng(seed), duration=duration,
                      progress=lambda *_: None, telemetry=lambda _: None, expected_s=duration.mean_s)

    async def one() -> tuple[StepResult, float]:
        result = step_result(await driver.run(step, params, sample, ctx), driver)
        return result, clock.now()

    return clock.run(one())


def run_scenario(path: str | Path, **overrides: Any) -> Summary:
    """A whole campaign of the scenario at ``path``, in virtual time on the in-memory bus."""
    with tempfile.TemporaryDirectory() as d:
        return run(prepare(path, clock="virtual", bus="memory"), journal=Path(d) / "journal.db", **overrides)
