"""The reactor: heats a sample to a set-point under its own control loop and holds it.

The loop is the PID (``options: {kp, ki, kd}``) unless ``options.controller``
names a trained heater policy (`twin train SCENARIO --agent controller`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from devices.models import catalyst, thermal
from devices.synthesiser import need
from twin import DriverSetup, StepContext, StepResult
from twin import load_policy, read_meta


class Reactor:
    capabilities = frozenset({"react"})
    makes_sample = capabilities  # from the feed it is given, or from nothing
    outputs = frozenset({"max_temperature_k", "overshoot_k"})
    chemistry_models = frozenset({"catalyst"})
    option_names = frozenset({"kp", "ki", "kd", "telemetry_s", "dt_s", "controller"})
    duration_param = "time_s"  # it heats, then holds for time_s: a step lasts at least that long

    def __init__(self, setup: DriverSetup) -> None:
        o = setup.options
        self.pid = dict(kp=float(o.get("kp", 6.0)), ki=float(o.get("ki", 0.04)), kd=float(o.get("kd", 0.0)))
        self.telemetry_s = float(o.get("telemetry_s", 600.0))
        self.dt_s = float(o.get("dt_s", 10.0))
        self.temperature_k = thermal.T_AMBIENT_K
        self.policy = self.mode = None
        if o.get("controller", "pid") != "pid":
            self.policy, self.mode = load_controller(Path(o["controller"]), self.dt_s)

    def controller(self, setpoint: float):
        pid = thermal.Pid(**self.pid)
        if self.policy is None:
            return pid
        from devices.reactor_control import PolicyController

        return PolicyController(self.policy, setpoint, self.mode, pid)

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        setpoint, hold = need(params, "temperature_k", "time_s")
        trace = thermal.simulate(setpoint, hold, self.dt_s, controller=self.controller(setpoint))
        total = ctx.draw_duration(params)
        every = max(1, int(self.telemetry_s / self.dt_s))
        elapsed = 0.0
        for i in range(every - 1, len(trace), every):
            t_i = (i + 1) * self.dt_s
            await ctx.clock.sleep(t_i - elapsed)
            elapsed = t_i
            self.temperature_k = float(trace[i])
            ctx.telemetry({"temperature_k": round(self.temperature_k, 3), "setpoint_k": setpoint})
        await ctx.clock.sleep(max(0.0, total - elapsed))
        result = catalyst.run(trace, self.dt_s)
        overshoot = float(np.max(trace) - setpoint)
        return StepResult(
            {"max_temperature_k": round(float(np.max(trace)), 3), "overshoot_k": round(max(overshoot, 0.0), 3)},
            {**(sample or {}), "kind": "reaction", **result, "t_made": ctx.clock.now()},
        )

    async def safe_state(self) -> None:
        """Heater off: the next run starts from ambient."""
        self.temperature_k = thermal.T_AMBIENT_K


def load_controller(path: Path, dt_s: float = 10.0) -> tuple[Any, str]:
    """A trained heater policy (`twin train ... --agent controller`) and its mode (pure or residual)."""
    from devices.reactor_control import SIGNATURE  # gymnasium and torch only for a reactor that uses one

    return load_policy(path, "controller", {**SIGNATURE, "dt_s": dt_s}), read_meta(path).get("mode", "pure")
