"""The reactor's heater: first-order thermal dynamics under a PID loop with anti-windup.

dT/dt = (u - (T - T_amb)) / tau, where u in [0, U_MAX] is the heater power in
kelvin of steady-state rise. A mild exotherm above 430 K makes the plant
nonlinear. The PID integrates only when its output is not saturated in the
direction of the error (conditional integration), so heat-up does not wind up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


def simulate(setpoint_k: float, hold_s: float, dt_s: float = 10.0, t0_k: float = T_AMBIENT_K,
             pid: Pid | None = None) -> np.ndarray:
    """The temperature trace (one value per dt) of a heat-up and hold at ``setpoint_k``."""
    pid = pid or Pid()
    n = max(1, int(math.ceil(hold_s / dt_s)))
    trace = [0.0] * n
    t, step, exp, gain = t0_k, pid.step, math.exp, dt_s / TAU_S
    for i in range(n):
        u = step(setpoint_k - t, dt_s)
        exo = EXOTHERM_K / (1 + exp((430.0 - t) / 10.0))
        t += gain * (u + exo - (t - T_AMBIENT_K))
        trace[i] = t
    return np.array(trace)
