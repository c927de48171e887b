"""The reactor's heater: first-order thermal dynamics under a PID loop with anti-windup.

dT/dt = (u - (T - T_amb)) / tau, where u in [0, U_MAX] is the heater power in
kelvin of steady-state rise. A mild exotherm above 430 K makes the plant
nonlinear. The PID integrates only when its output is not saturated in the
direction of the error (conditional integration), so heat-up does not wind up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

T_AMBIENT_K = 298.15
TAU_S = 300.0
U_MAX_K = 400.0
EXOTHERM_K = 6.0


@dataclass
class Pid:
    kp: float = 6.0
    ki: float = 6.0 / 150.0
    kd: float = 0.0
    integral: float = 0.0
    last_error: float | None = None

    def step(self, error: float, dt: float) -> float:
        last, self.last_error = self.last_error, error
        u = self.kp * error + self.ki * self.integral
        if self.kd and last is not None:
            u += self.kd * (error - last) / dt
        if u >= U_MAX_K:
            if error <= 0:
                self.integral += error * dt
            return U_MAX_K
        if u <= 0.0:
            if error >= 0:
                self.integral += error * dt
            return 0.0
        self.integral += error * dt
        return u


@dataclass(frozen=True)
class Plant:
    """The reactor as built; a real one differs (the bench checks controllers against a mismatched plant)."""

    tau_s: float = TAU_S
    u_max_k: float = U_MAX_K
    exotherm_k: float = EXOTHERM_K


NOMINAL = Plant()


def advance(t_k: float, u: float, dt_s: float, plant: Plant = NOMINAL) -> float:
    """The temperature one step of ``dt_s`` later under heater power ``u`` (clipped to the heater's range)."""
    u = min(max(u, 0.0), plant.u_max_k)
    exo = plant.exotherm_k / (1 + math.exp((430.0 - t_k) / 10.0))
    return t_k + dt_s / plant.tau_s * (u + exo - (t_k - T_AMBIENT_K))


def simulate(setpoint_k: float, hold_s: float, dt_s: float = 10.0, t0_k: float = T_AMBIENT_K,
             controller: Any = None, plant: Plant = NOMINAL) -> np.ndarray:
    """The temperature trace (one value per dt) of a heat-up and hold at ``setpoint_k``.

    ``controller.step(error, dt)`` gives the heater power; a PID by default.
    """
    step = (controller or Pid()).step
    n = max(1, int(math.ceil(hold_s / dt_s)))
    trace = [0.0] * n
    t, exp, gain, u_max, exo_k = t0_k, math.exp, dt_s / plant.tau_s, plant.u_max_k, plant.exotherm_k
    for i in range(n):  # advance() inlined: this loop is most of a catalyst campaign's physics
        u = min(max(step(setpoint_k - t, dt_s), 0.0), u_max)
        t += gain * (u + exo_k / (1 + exp((430.0 - t) / 10.0)) - (t - T_AMBIENT_K))
        trace[i] = t
    return np.array(trace)
