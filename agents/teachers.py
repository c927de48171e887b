"""The teachers the candidate policy imitates (``agents.imitation``): a solved job shop's plan, or a dispatching rule;
each labels any state of its lab with the candidates it would choose (and waiting as the last)."""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from twin import SteppedCampaign, load_plugin


#: the wall seconds a training shop's solve is given when its work is what limits it: a guard against a solve that
#: never ends, far beyond what the work takes on any machine (4 s on the slowest seen here)
WORK_GUARD_S = 120.0


class SolveSettings(TypedDict, total=False):
    time_limit_s: float
    workers: int
    work_limit: float


def solve_settings(jobs: int, machines: int) -> SolveSettings:
    """CP-SAT's ``jobshop`` settings for one training shop, enough to be near the optimum on these sizes. Up to
    10×10 one thread, stopped by an amount of work (``agents.cpsat``): the same plan each time on any machine,
    however busy, so a seed trains the same policy (stopped in wall time, a busy CI's plans differed, and its
    policies with them; two threads race to one of several optima). There, with durations of 1-99 s, it proved
    the optimum on 6×6 and 10×5 shops always and on ~90 % of 10×10 ones (60 shops: the median needed 0.09 units of
    work, the 90th percentile 0.53, the slowest 4.2). Larger shops end at their time limit either way, and two
    threads' plans were 1.8 % shorter on 20×15 (ten shops)."""
    seconds = min(6.0, 0.2 + jobs * machines / 60)
    if jobs * machines <= 100:
        return {"time_limit_s": WORK_GUARD_S, "workers": 1, "work_limit": 0.3 * seconds}
    return {"time_limit_s": seconds, "workers": 2}


class PlanTeacher:
    """Each machine's order of operations in a solved shop; labels any state of that shop by it."""

    def __init__(self, jobs: list[list[tuple[int, int]]], starts: list[list[int]]) -> None:
        self.durations = [[d for _, d in job] for job in jobs]
        order: dict[str, list[tuple[float, int, int]]] = {}
        for j, job in enumerate(jobs):
            for k, (m, _) in enumerate(job):
                order.setdefault(f"m{m}", []).append((starts[j][k], j, k))
        self.order = {m: [(j, k) for _, j, k in sorted(ops)] for m, ops in order.items()}
        self.position = {m: {op: n for n, op in enumerate(ops)} for m, ops in self.order.items()}
        self.reset()

    def reset(self) -> None:
        self.ends: dict[tuple[int, int], float] = {}  # started operations: when each ends

    def start(self, campaign: SteppedCampaign, ready) -> None:
        """Note that ``ready`` was started (by whoever chose it)."""
        self.ends[self.op(campaign, ready)] = campaign.now + ready.expected_s

    def op(self, campaign: SteppedCampaign, ready) -> tuple[int, int]:
        j = int(campaign.core.experiments[ready.experiment].params["job"])
        return j, len(self.durations[j]) - 1 - len(ready.then)

    def next_on(self, machine: str) -> tuple[int, int] | None:
        return next((op for op in self.order.get(machine, ()) if op not in self.ends), None)

    def earliest(self, op: tuple[int, int], now: float) -> float:
        """The soonest ``op`` could start: after what of its job is running and still to come before it."""
        j, k = op
        q = max((i for i in range(k) if (j, i) in self.ends), default=-1)
        at = max(now, self.ends[(j, q)]) if q >= 0 else now
        return at + sum(self.durations[j][q + 1:k])

    def labels(self, campaign: SteppedCampaign, pairs, wait_allowed: bool) -> np.ndarray:
        """Per free machine, the candidate its plan runs first, unless the plan's next operation there is not
        ready and that candidate would still be running when it could be: then keep the machine for it (wait)."""
        taught = np.zeros(len(pairs) + 1, bool)
        first: dict[str, tuple[int, int]] = {}
        for i, (r, _) in enumerate(pairs):
            pos = self.position[r.device_type].get(self.op(campaign, r), 10**9)
            if r.device_type not in first or pos < first[r.device_type][0]:
                first[r.device_type] = (pos, i)
        now = campaign.now
        for machine, (pos, i) in first.items():
            nxt = self.next_on(machine)
            if (wait_allowed and nxt is not None and self.position[machine][nxt] < pos
                    and now + pairs[i][0].expected_s > self.earliest(nxt, now)):
                continue
            taught[i] = True
        if not taught.any():
            if wait_allowed:
                taught[-1] = True
            else:
                taught[min(i for _, i in first.values())] = True
        return taught


class RuleTeacher:
    """A dispatching rule as the teacher (any lab): the step of its first assignment in each state, on any free
    instance that may take it (which of several identical free instances a rule names is its arbitrary
    tie-break, and learning it cost the policy more than it taught: docs/benchmarks.md)."""

    def __init__(self, rule: str) -> None:
        self.rule = load_plugin("schedulers", rule)()

    def reset(self) -> None:
        pass

    def start(self, campaign: SteppedCampaign, ready) -> None:
        pass

    def labels(self, campaign: SteppedCampaign, pairs, wait_allowed: bool) -> np.ndarray:
        taught = np.zeros(len(pairs) + 1, bool)
        out = self.rule.decide(campaign.view)
        if out:
            for i, (r, _) in enumerate(pairs):
                taught[i] = r.task == out[0].task
        if not taught.any():
            taught[-1 if wait_allowed or not pairs else 0] = True
        return taught
