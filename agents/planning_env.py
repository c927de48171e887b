"""`labtwin/Planning-v0`: the seed chapter's closed loop as a gymnasium environment.

Each step is one experiment, run through the scenario's own drivers in a
workcell (the same physics, noise and sample ageing as a campaign). The agent
moves from the best experiment so far: it sees where that is and how far its
outputs miss the target, and where the last attempt went and what it gave;
it answers with a move in the unit box. An episode ends when the target is
met or after ``horizon`` experiments.

Goals are the scenario's targets and, for ``value ± tol`` conditions, goals
drawn from what a random point of the box produces (so the policy learns to
reach anything reachable, not three memorised points).

Reward: the drop in log(1 + distance to target) of the best experiment,
+1 when the target is met, -0.02 per experiment: fewer experiments to target
is better, and a step that finds nothing new costs a little.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from agents import default_scenario
from agents.box import UnitBox
from agents.rendering import METADATA, points_picture, render_mode_of
from twin import Scenario
from twin import score
from twin import open_workcell

STEP = 0.3  # the largest move per experiment, as a fraction of the unit box
CLIP = 6.0
MET_BONUS, STEP_COST = 1.0, 0.02
MISS = 1e3  # the distance counted for an experiment with no outputs to score (refused as infeasible, say)


def signed_errors(outputs: dict[str, Any] | None, target: Any) -> np.ndarray:
    """Per condition, how far and which way an output misses, on a log scale of tolerances."""
    out = []
    for name, c in target.outputs.items():
        y = (outputs or {}).get(name)
        if not isinstance(y, (int, float)) or not math.isfinite(y):
            out.append(CLIP)
            continue
        if c.value is not None:
            e = (y - c.value) / c.tol
        else:
            scale = max(abs(c.min if c.min is not None else c.max) * 0.05, 1e-9)
            e = (y - c.min) / scale if c.min is not None else (c.max - y) / scale
            e = min(e, 0.0)  # a bound that holds is met; only the shortfall matters
        out.append(float(np.clip(np.sign(e) * math.log1p(abs(e)), -CLIP, CLIP)))
    return np.array(out, dtype=np.float32)


def observation(box: UnitBox, target: Any, best: tuple[np.ndarray, dict | None],
                last: tuple[np.ndarray, dict | None], used: float) -> np.ndarray:
    """[best point, its errors, last point − best point, last errors, fraction of the horizon used]."""
    return np.concatenate([best[0], signed_errors(best[1], target), last[0] - best[0],
                           signed_errors(last[1], target), [used]]).astype(np.float32)


def observation_size(dims: int, conditions: int) -> int:
    return 2 * dims + 2 * conditions + 1


def signature(parameters: list[str], conditions: list[str]) -> dict[str, Any]:
    """What a planner policy is tied to: the box it moves in and the target conditions it reads."""
    return {"observation_size": observation_size(len(parameters), len(conditions)),
            "parameters": list(parameters), "conditions": list(conditions)}


def move(u_best: np.ndarray, action: np.ndarray) -> np.ndarray:
    return np.clip(u_best + STEP * np.clip(action, -1.0, 1.0), 0.0, 1.0)


def target_shape(scenario: Scenario) -> tuple[str, ...]:
    """The conditions every target of the scenario must share for one policy to serve them all."""
    shapes = {tuple(t.outputs) for t in scenario.chemistry.targets}
    if not shapes:
        raise ValueError(f"{scenario.name}: the rl planner learns to reach the scenario's targets, and it has none: "
                         "give chemistry.targets (e.g. [{name: best, outputs: {yield: {min: 90}}}])")
    if len(shapes) != 1:
        raise ValueError(f"{scenario.name}: the rl planner needs every target on the same outputs, and these ask for "
                         f"{' / '.join(', '.join(s) for s in sorted(shapes))}: train one planner per kind of target")
    return shapes.pop()


@dataclass
class _Point:
    u: np.ndarray
    outputs: dict | None
    distance: float


class PlanningEnv(gym.Env):
    metadata = METADATA

    def __init__(self, scenario: Scenario | str | Path | None = None, horizon: int = 30, random_goals: float = 0.5,
                 seed: int = 0, render_mode: str | None = None) -> None:
        """``scenario``: a Scenario, a file or the mapping a file holds (default: ``scenarios/quantum_dots.yaml``).
        ``render_mode`` ``"rgb_array"``: ``render()`` draws the episode's experiments in the box's first two
        parameters, green as they near the target, the best ringed."""
        self.render_mode = render_mode_of(render_mode)
        self._tried: list[_Point] = []
        scenario = default_scenario(scenario, "quantum_dots.yaml")
        if scenario.campaigns:  # its own chemistry is only the campaigns' default: "targets on the same outputs; []"
            raise ValueError(f"{scenario.name}: a lab of several campaigns ({', '.join(c.name for c in scenario.campaigns)})"
                             f"; this environment plans one campaign's experiments: give it one of "
                             f"twin.campaign_scenarios(twin.prepare(LAB)) (by name), with the lab's devices")
        if scenario.campaign.planner == "route":  # its steps take a route's reaction and scale, not a box's point
            raise ValueError(f"{scenario.name}: its experiments are synthesis routes, which its route planner plans "
                             "(campaign.planner: route); this environment plans points in chemistry.parameters for "
                             "the workflow as written. The route search learns its expansion prior instead: "
                             "twin train SCENARIO --agent route (docs/routes.md)")
        target_shape(scenario)
        self.scenario, self.horizon, self.random_goals = scenario, horizon, random_goals
        self.box = UnitBox(scenario.chemistry.parameters)
        self.targets = list(scenario.chemistry.targets)
        self.workcell = open_workcell(scenario, seed)
        conditions = len(self.targets[0].outputs)
        self.observation_space = gym.spaces.Box(-CLIP, CLIP, (observation_size(self.box.dims, conditions),), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (self.box.dims,), np.float32)
        self.target = self.targets[0]
        self._best = self._last = None
        self._n = 0
        self.last_measured: Any = None  # the workcell's last Measured: its outputs, or why it measured nothing

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self.workcell.reseed(seed)
        self.target = self._goal() if (options or {}).get("target") is None else options["target"]
        self._n = 0
        self._tried = []
        self._best = self._last = self._experiment(self.np_random.random(self.box.dims))
        return self._obs(), {"distance": self._best.distance}

    def step(self, action):
        if np.isnan(np.asarray(action, dtype=float)).any():  # it proposed NaN parameters to the chemistry
            raise ValueError(f"action {action} holds NaN (a policy whose weights or inputs diverged?): each entry "
                             "is a move from -1 to 1 along one parameter")
        before = self._best.distance
        self._last = self._experiment(move(self._best.u, np.asarray(action, dtype=float)))
        if self._last.distance < self._best.distance:
            self._best = self._last
        met = self._best.distance == 0
        reward = math.log1p(min(before, MISS)) - math.log1p(min(self._best.distance, MISS)) - STEP_COST + (
            MET_BONUS if met else 0.0)
        truncated = not met and self._n >= self.horizon
        return self._obs(), float(reward), met, truncated, {"distance": self._best.distance, "experiments": self._n}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        points = [(float(p.u[0]), float(p.u[1]) if len(p.u) > 1 else 0.5, math.log1p(min(p.distance, MISS)) /
                   math.log1p(MISS)) for p in self._tried]
        return points_picture(points, next((i for i, p in enumerate(self._tried) if p is self._best), None))

    # -- internals -------------------------------------------------------------
    def _experiment(self, u: np.ndarray) -> _Point:
        self._n += 1
        self.last_measured = self.workcell.run(self.box.params(u))
        outputs = self.last_measured.outputs
        point = _Point(u, outputs, score(outputs, self.target))
        if self.render_mode is not None:
            self._tried.append(point)
        return point

    def _goal(self) -> Any:
        target = self.targets[int(self.np_random.integers(len(self.targets)))]
        values = [n for n, c in target.outputs.items() if c.value is not None]
        if not values or self.np_random.random() >= self.random_goals:
            return target
        reached = self.workcell.run(self.box.params(self.np_random.random(self.box.dims))).outputs
        if not all(isinstance(reached.get(n), (int, float)) for n in values):
            return target
        conds = {n: replace_value(c, reached[n]) if n in values else c for n, c in target.outputs.items()}
        return target.model_copy(update={"name": "random-goal", "outputs": conds})

    def _obs(self) -> np.ndarray:
        return observation(self.box, self.target, (self._best.u, self._best.outputs),
                           (self._last.u, self._last.outputs), self._n / self.horizon)


def replace_value(cond: Any, value: float) -> Any:
    return cond.model_copy(update={"value": float(value)})

