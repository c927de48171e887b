"""`labtwin/Scheduling-v0`: the twin's scheduling decisions as a gymnasium environment.

Each step is one decision of a real campaign — device actors, orchestrator,
retries and faults on the memory bus in virtual time (``twin.learning.stepper``) —
from one decision point (a device freed, a step ready) to the next. The
observation, action and mask are ``agents.scheduling_features``.

Reward (the shaping, documented), weighted by the scenario's
``training.weights``: −(lab time until the next decision point) ÷ the typical
step duration (× ``time``, default 1), so an episode's return is minus the
makespan in those units; −``degraded`` (0.5) for each sample that waited past
its stability before a step and −``abandoned`` (2) for each experiment
abandoned. ``reset(seed=)``
reseeds the whole twin (planner, durations, faults) and, when the scenario
declares ``training`` ranges and ``randomise`` is on, draws the lab's
durations, fault rates and instance counts — or, with ``training.random_labs``,
a whole other lab (``twin.scenario.random_labs``).
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from agents import candidates, default_scenario, lab_scheduling, scheduling_features
from agents.rendering import METADATA, Spans, render_mode_of
from twin import bottleneck, jobshop_as_lab, random_jobshop, random_lab
from twin import prepare
from twin import Scenario
from twin import SteppedCampaign

INVALID_PENALTY = 1.0
ENCODINGS = {"slots": scheduling_features, "candidates": candidates}


def randomised(s: Scenario, seed: int) -> Scenario:
    """A lab drawn from the scenario's ``training`` ranges (the same seed draws the same lab)."""
    t, rng = s.training, random.Random(f"randomise:{seed}")
    dur, fault = rng.uniform(*t.duration_scale), rng.uniform(*t.fault_scale)
    if t.random_labs is not None and not s.campaigns and rng.random() < t.random_labs.share:
        return prepare(random_lab(s, rng, dur, fault))
    over: dict[str, Any] = {}
    if t.stability_scale != (1.0, 1.0) and s.chemistry.stability_s:
        over["chemistry.stability_s"] = s.chemistry.stability_s * rng.uniform(*t.stability_scale)
    for name, d in s.devices.items():
        # drawn only when asked for, so that labs drawn without it stay the labs drawn before
        d_dur, d_fault = ((rng.uniform(*t.type_scale), rng.uniform(*t.type_scale)) if t.type_scale != (1.0, 1.0)
                          else (1.0, 1.0))
        over[f"devices.{name}.duration.mean_s"] = d.duration.mean_s * dur * d_dur
        over[f"devices.{name}.faults.fail_p"] = min(0.5, d.faults.fail_p * fault * d_fault)
        over[f"devices.{name}.faults.hang_p"] = min(0.5, d.faults.hang_p * fault * d_fault)
        over[f"devices.{name}.faults.mtbc_h"] = d.faults.mtbc_h / (fault * d_fault) if d.faults.mtbc_h else 0.0
        if name in t.instances:
            over[f"devices.{name}.instances"] = rng.randint(*t.instances[name])
    if t.bottleneck_share and s.jobshop is None and not s.campaigns and rng.random() < t.bottleneck_share:
        over = _with_bottleneck(s, over, rng)
    if s.jobshop is not None and t.jobshop_sizes:
        n_jobs, n_machines = rng.choice(t.jobshop_sizes)
        low, high = (int(x) for x in (t.operation_s or (1, 10)))
        return jobshop_as_lab(s, random_jobshop(n_jobs, n_machines, low, high, rng))
    jobs = s.campaign.planner_options.get("proposals")
    if jobs and (t.operation_s or t.shuffle_routes):
        over["campaign.planner_options.proposals"] = [_redraw(job, t, rng) for job in jobs]
    if s.campaigns:  # a lab of several: its campaigns' priorities and shares too
        over = lab_scheduling.variant(s, over, rng)
    return prepare(s, overrides=over)


def _with_bottleneck(s: Scenario, over: dict[str, Any], rng: random.Random) -> dict[str, Any]:
    """``over`` with one device type of the workflow, drawn, made the lab's bottleneck (``twin.bottleneck``), and
    up to half as long again."""
    lab = prepare(s, overrides=over)
    name = rng.choice(sorted({w.device for w in lab.workflow}))
    factor = bottleneck(lab, name) * rng.uniform(1.0, 1.5)
    return {**over, f"devices.{name}.duration.mean_s": lab.devices[name].duration.mean_s * factor} if factor else over


def _redraw(job: dict, t: Any, rng: random.Random) -> dict:
    """A job shop's job with fresh operation durations and/or machine order."""
    route = [dict(op, params=dict(op.get("params", {}))) for op in job["route"]]
    if t.shuffle_routes:
        devices = [op["device"] for op in route]
        rng.shuffle(devices)
        for op, device in zip(route, devices):
            op["device"] = device
    if t.operation_s:
        for op in route:
            op["params"]["duration_s"] = float(rng.randint(int(t.operation_s[0]), int(t.operation_s[1])))
    return {**job, "route": route}


class SchedulingEnv(gym.Env):
    metadata = METADATA

    def __init__(self, scenario: Scenario | str | Path | None = None, randomise: bool = True,
                 encoding: str = "candidates", render_mode: str | None = None) -> None:
        """``scenario``: a Scenario, a file or the mapping a file holds (default: ``scenarios/flaky_lab.yaml``). ``encoding``:
        ``candidates`` (one row per allowed pair, ``agents.candidates``; or a version of it, ``candidates-v3``)
        or ``slots`` (the fixed grid of ``agents.scheduling_features``, kept as a baseline). ``render_mode``
        ``"rgb_array"``: ``render()`` draws each device's states over the episode's lab time."""
        self.render_mode = render_mode_of(render_mode)
        self._spans = Spans()
        scenario = default_scenario(scenario, "flaky_lab.yaml")
        self.base, self.randomise = scenario, randomise
        candidates_of = encoding.startswith("candidates")  # "candidates" (this labtwin's) or a version of it
        self.features = ENCODINGS["candidates" if candidates_of else encoding]
        self.encoder = self.features.CandidateEncoder(scenario, encoding) if candidates_of else \
            self.features.Encoder(scenario)
        self.observation_space = gym.spaces.Box(-10.0, 10.0, (self.features.OBS_SIZE,), np.float32)
        self.action_space = gym.spaces.Discrete(self.features.ACTIONS)
        self.campaign: SteppedCampaign | None = None
        self._mask = np.ones(self.features.ACTIONS, bool)
        self._episode_seed = 0
        self.fits: dict | None = None

    # -- gymnasium ------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if self.base.campaigns:
            raise ValueError(f"{self.base.name}: a lab of several campaigns; this environment poses one campaign's "
                             f"questions. Train a lab's one scheduler with `twin train {self.base.name}.yaml` "
                             f"(imitation, agents.lab_scheduling), or step it with twin.SteppedLab")
        self._episode_seed = int(self.np_random.integers(2**31)) if seed is None else int(seed)
        lab = randomised(self.base, self._episode_seed) if self.randomise else self.base
        lab = prepare(lab, seed=self._episode_seed)
        self.fits = candidates.widen(self.fits, candidates.lab_shape(lab))  # what a policy trained here has seen
        self.close()
        self.campaign = SteppedCampaign(lab)
        self._spans = Spans()
        self._marks = self._counts()
        return self._observe(), {"lab_s": self.campaign.now}

    def step(self, action):
        c = self.campaign
        t0, (deg0, ab0) = c.now, self._marks
        penalty = 0.0
        if not 0 <= int(action) < len(self._mask):  # -1 read the last entry, 10**6 an IndexError from numpy
            raise ValueError(f"action {action} is outside the action space {self.action_space} (0 to "
                             f"{len(self._mask) - 1}; action_masks() says which of them may be taken now)")
        if not self._mask[int(action)]:  # unmasked sampling (a plain PPO, the env checker): never stall the lab
            action, penalty = int(np.flatnonzero(self._mask)[0]), INVALID_PENALTY
        c.answer(self.encoder.decode(c.view, action))
        self._marks = self._counts()
        deg, ab = self._marks
        w = self.base.training.weights
        reward = (-w.time * (c.now - t0) / self.encoder.scale - w.degraded * (deg - deg0)
                  - w.abandoned * (ab - ab0) - penalty)
        info = {"lab_s": c.now}
        if c.done:
            info["summary"] = c.summary
        return self._observe(), float(reward), c.done, False, info

    def action_masks(self) -> np.ndarray:
        return self._mask.copy()

    def render(self) -> np.ndarray | None:
        """``rgb_array``: a row per device, its states (busy green, idle blue, offline grey, quarantined orange) from
        the episode's start to now, as they stood at each decision."""
        return self._spans.picture() if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        if self.campaign is not None:
            self.campaign.close()
            self.campaign = None

    # -- internals ------------------------------------------------------------------
    def _counts(self) -> tuple[int, int]:
        core = self.campaign.core
        return sum(e.degraded for e in core.experiments), sum(e.status == "abandoned" for e in core.experiments)

    def _observe(self) -> np.ndarray:
        if self.render_mode is not None:
            core = self.campaign.core
            self._spans.snapshot(self.campaign.now, {d.name: "quarantined" if d.quarantined else "offline" if not
                                                     d.online else "busy" if d.attempt else "idle"
                                                     for d in core.devices.values()})
        if self.campaign.view is None:  # the campaign is over
            self._mask = np.zeros(self.features.ACTIONS, bool)
            self._mask[-1] = True
            return np.zeros(self.features.OBS_SIZE, np.float32)
        obs, self._mask = self.encoder.encode(self.campaign.view)
        return obs

