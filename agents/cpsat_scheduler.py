"""`cp-sat`: re-solve the known remaining work at every decision and start what the plan starts now.

The model holds every ready step with the rest of its experiment's route, and
every running experiment's later steps (released when its device is expected
to finish); device types are resources with as many units as instances that
are up. It minimises the makespan, then (with a smaller weight) the sum of
start times, so nothing waits that need not. Steps that have not been
proposed yet, retries in back-off and faults are invisible to it: this is
the strongest online rival a solver makes, not an oracle.
"""

from __future__ import annotations

from typing import Any

from agents.cpsat import Op, Solution, solve
from twin import time_scale
from twin import Assignment, LabView, capable


class CpSatScheduler:
    runs_long = True  # a solve takes up to time_limit_s of wall time: the live lab asks it off the event loop

    def __init__(self, scenario: Any = None, time_limit_s: float = 1.0, **_: Any) -> None:
        """``time_limit_s``: wall seconds a decision's solve may take (``campaign.scheduler_options``; more on a
        machine too busy to find a schedule in them: ``agents.cpsat.TRIES``)."""
        if isinstance(time_limit_s, bool) or not isinstance(time_limit_s, (int, float)) \
                or not 0.01 <= time_limit_s <= 3600:
            raise ValueError(f"time_limit_s: {str(time_limit_s)[:40]!r} is not a number of seconds from 0.01 to "
                             "3600 (the wall time each decision's solve may take)")
        self.time_limit_s = float(time_limit_s)
        self.unit = max(1.0, time_scale(scenario) / 50) if scenario is not None else 1.0  # lab-s per model tick

    @staticmethod
    def offline_bound(scenario: Any, time_limit_s: float = 120.0) -> float:
        """The optimum (or best found) makespan of a deterministic lab whose experiments are all known (a job shop)."""
        return float(CpSatScheduler.offline_solution(scenario, time_limit_s).makespan)

    @staticmethod
    def offline_solution(scenario: Any, time_limit_s: float = 120.0) -> Solution:
        """The best schedule found in ``time_limit_s`` of a deterministic lab whose experiments are all known (a job
        shop), and whether it is proven optimal; RuntimeError if CP-SAT found none in that time (once: tried again
        with twice the time, and twice that, a shop of 300 jobs on 50 machines took half an hour)."""
        jobs = [[Op(step["device"], round(float(step.get("params", {}).get("duration_s", 0))))
                 for step in p["route"]] for p in scenario.campaign.planner_options.get("proposals", [])]
        if not jobs:
            raise ValueError(f"{scenario.name}: an offline bound needs every experiment known in advance (a job shop)")
        return solve(jobs, {t: d.instances for t, d in scenario.devices.items()}, time_limit_s, tries=1)

    def _ticks(self, seconds: float) -> int:
        return max(1, round(seconds / self.unit))

    def decide(self, view: LabView) -> list[Assignment]:
        if not view.ready:
            return []
        up = [d for d in view.devices if d.free or d.busy_until is not None]
        capacity = {}
        for d in up:
            capacity[d.device_type] = capacity.get(d.device_type, 0) + 1
        jobs = [[Op(r.device_type, self._ticks(r.expected_s))] + [Op(t, self._ticks(s)) for t, s in r.then]
                for r in view.ready if r.device_type in capacity]
        steps = [r for r in view.ready if r.device_type in capacity]
        busy: dict[str, list[int]] = {}
        for d in up:
            if d.busy_until is None:
                continue
            left = max(0, round((d.busy_until - view.now) / self.unit))
            busy.setdefault(d.device_type, []).append(left)
            later = [(t, s) for t, s in d.then if t in capacity]
            if later:
                jobs.append([Op(later[0][0], self._ticks(later[0][1]), release=left)]
                            + [Op(t, self._ticks(s)) for t, s in later[1:]])
        for job in jobs:
            for op in job:
                capacity.setdefault(op.device_type, 1)
        plan = solve(jobs, capacity, self.time_limit_s, busy=busy, left_shift=True)
        order = sorted(range(len(steps)), key=lambda i: (plan.starts[i][0], steps[i].ready_since, steps[i].task))
        free, out = list(view.free), []
        for i in order:
            if plan.starts[i][0] > 0 and (out or any(d.busy_until is not None for d in view.devices)):
                break  # the plan starts it later; (if nothing would run at all, start the earliest anyway)
            options = capable(steps[i], tuple(free))
            if options:
                free.remove(options[0])
                out.append(Assignment(steps[i].task, options[0].name))
        return out
