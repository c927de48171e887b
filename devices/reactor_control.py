"""The reactor's inner loop as a learning problem: a PPO heater controller, pure or on top of the PID.

`labtwin/ReactorControl-v0` steps the reactor's own thermal model
(``devices.models.thermal``, exotherm included) every ``dt`` seconds from
ambient to a random set-point and through the hold. The action is the heater
power (``pure``) or a correction added to the PID's output (``residual``: the
chapter's exercise 1, PID for the base, RL for the nonlinear part). Reward per
step: -(|error| + 3·overshoot beyond 1 K) / 50, since running hot costs
selectivity and cannot be undone, while running cold only costs time.
"""

from __future__ import annotations

import math

from typing import Any

import gymnasium as gym
import numpy as np

from devices.models import thermal

MODES = ("pure", "residual")
RESIDUAL_K = 200.0
SETPOINTS_K = (380.0, 520.0)
SIGNATURE = {"observation_size": 5, "dt_s": 10.0}


def control_observation(setpoint: float, t_k: float, t_prev: float, u_prev: float, dt: float) -> np.ndarray:
    return np.array([(setpoint - t_k) / 50.0, (setpoint - 450.0) / 100.0, (t_k - thermal.T_AMBIENT_K) / 200.0,
                     u_prev / thermal.U_MAX_K, (t_k - t_prev) / dt * thermal.TAU_S / 100.0], dtype=np.float32)


def step_reward(setpoint: float, t_k: float) -> float:
    return -(abs(setpoint - t_k) + 3.0 * max(0.0, t_k - setpoint - 1.0)) / 50.0


class PolicyController:
    """A trained policy behind the PID's interface: ``step(error, dt) -> heater power``."""

    def __init__(self, model: Any, setpoint: float, mode: str = "pure", pid: thermal.Pid | None = None) -> None:
        self.model, self.setpoint, self.mode = model, setpoint, mode
        self.pid = pid or thermal.Pid()
        self._t_prev: float | None = None
        self._u_prev = 0.0

    def step(self, error: float, dt: float) -> float:
        t_k = self.setpoint - error
        obs = control_observation(self.setpoint, t_k, self._t_prev if self._t_prev is not None else t_k, self._u_prev, dt)
        action = float(self.model.predict(obs, deterministic=True)[0][0])
        self._t_prev = t_k
        self._u_prev = command(self.mode, action, self.pid, error, dt)
        return self._u_prev


def command(mode: str, action: float, pid: thermal.Pid, error: float, dt: float) -> float:
    if math.isnan(action):  # it passed the clip and heated with NaN from then on (infinities are clipped)
        raise ValueError("the heater's action is NaN (a policy whose weights or inputs diverged?): a number from -1 "
                         "to 1 is the heater's command")
    action = min(max(action, -1.0), 1.0)
    if mode == "pure":
        return (action + 1.0) / 2.0 * thermal.U_MAX_K
    return min(max(pid.step(error, dt) + RESIDUAL_K * action, 0.0), thermal.U_MAX_K)


class ReactorControlEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, mode: str = "pure", pid: dict[str, float] | None = None, dt_s: float = 10.0,
                 hold_s: float = 3600.0, render_mode: str | None = None) -> None:
        """``render_mode`` ``"rgb_array"``: ``render()`` draws the episode's temperature (red) against its
        set-point (dark grey), and the heater's command (light blue, from nothing at the bottom to its most at the
        top)."""
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, not {mode!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r}: this environment draws rgb_array pictures (or give None)")
        self.render_mode = render_mode
        self._trace: list[tuple[float, float]] = []
        self.mode, self.pid_gains, self.dt, self.steps = mode, dict(pid or {}), dt_s, int(hold_s / dt_s)
        self.observation_space = gym.spaces.Box(-10.0, 10.0, (5,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.setpoint = float((options or {}).get("setpoint") or self.np_random.uniform(*SETPOINTS_K))
        self.t = self.t_prev = thermal.T_AMBIENT_K
        self.u = 0.0
        self.pid = thermal.Pid(**self.pid_gains)
        self.n = 0
        self._trace = [(self.t, self.u)]
        return self._obs(), {}

    def step(self, action):
        self.u = command(self.mode, float(np.asarray(action).reshape(-1)[0]), self.pid, self.setpoint - self.t, self.dt)
        self.t_prev, self.t = self.t, thermal.advance(self.t, self.u, self.dt)
        self.n += 1
        if self.render_mode is not None:
            self._trace.append((self.t, self.u))
        return self._obs(), step_reward(self.setpoint, self.t), False, self.n >= self.steps, {"temperature_k": self.t}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        from PIL import Image, ImageDraw

        width, height, margin = 480, 240, 6
        image = Image.new("RGB", (width, height), "white")
        draw = ImageDraw.Draw(image)
        lo, hi = thermal.T_AMBIENT_K, max(self.setpoint, *(t for t, _ in self._trace)) + 20.0
        def x(i: int) -> float:
            return margin + (width - 2 * margin) * i / max(1, self.steps)

        def y(value: float, low: float, high: float) -> float:
            return height - margin - (height - 2 * margin) * (value - low) / (high - low)

        draw.line((margin, y(self.setpoint, lo, hi), width - margin, y(self.setpoint, lo, hi)), fill=(60, 60, 60))
        if len(self._trace) > 1:
            draw.line([(x(i), y(u, 0.0, thermal.U_MAX_K)) for i, (_, u) in enumerate(self._trace)],
                      fill=(140, 175, 225))
            draw.line([(x(i), y(t, lo, hi)) for i, (t, _) in enumerate(self._trace)], fill=(228, 87, 86), width=2)
        return np.asarray(image, dtype=np.uint8)

    def _obs(self) -> np.ndarray:
        return control_observation(self.setpoint, self.t, self.t_prev, self.u, self.dt)




def tracking(trace: np.ndarray, setpoint: float, dt_s: float, band_k: float = 2.0) -> dict[str, float]:
    """Time to reach the set-point band, overshoot, and RMS error once there."""
    inside = np.flatnonzero(np.abs(trace - setpoint) <= band_k)
    first = int(inside[0]) if len(inside) else len(trace)
    after = trace[first:] - setpoint
    return {"time_to_target_s": (first + 1) * dt_s if len(inside) else float("inf"),
            "overshoot_k": max(0.0, float(np.max(trace) - setpoint)),
            "rms_k": float(np.sqrt(np.mean(after**2))) if len(after) else float("inf")}

