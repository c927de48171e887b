"""Job-shop instances as labs: one device per machine, deterministic durations, no faults.

The standard text format: ``#`` comments, then ``jobs machines``, then one line
per job of ``machine duration`` pairs in processing order. One time unit is one
lab-second.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path

from twin.core.errors import ScenarioError
from twin.scenario.files import read_text
from twin.scenario.model import Scenario


@dataclass(frozen=True)
class Instance:
    name: str
    machines: int
    jobs: list[list[tuple[int, int]]]  # per job: (machine, duration) in order


MAX_JOBS, MAX_MACHINES, MAX_DURATION = 1000, 256, 10**7


def read(path: str | Path) -> Instance:
    path = Path(path)
    where = str(path)
    lines = [ln.split("#")[0].strip() for ln in read_text(path, "job-shop").splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise ScenarioError(where, ["empty job-shop file: expected 'jobs machines' then one line per job"])
    try:
        n_jobs, n_machines = (int(x) for x in lines[0].split())
        jobs = []
        for row in lines[1 : 1 + min(n_jobs, MAX_JOBS)]:
            nums = [int(x) for x in row.split()]
            jobs.append(list(zip(nums[0::2], nums[1::2], strict=True)))
    except ValueError as exc:
        raise ScenarioError(where, [f"not in the standard job-shop format ('jobs machines', then per job "
                                    f"'machine duration' pairs): {str(exc)[:120]}"]) from None
    if not (1 <= n_jobs <= MAX_JOBS and 1 <= n_machines <= MAX_MACHINES):
        raise ScenarioError(where, [f"line 1: {n_jobs} jobs on {n_machines} machines; expected 1-{MAX_JOBS} jobs "
                                    f"on 1-{MAX_MACHINES} machines"])
    if len(jobs) != n_jobs or any(not job for job in jobs) or any(not 0 <= m < n_machines for job in jobs for m, _ in job):
        raise ScenarioError(where, [f"expected {n_jobs} non-empty jobs on machines 0..{n_machines - 1}"])
    bad = [(j, d) for j, job in enumerate(jobs) for _, d in job if not 0 <= d <= MAX_DURATION]
    if bad:
        raise ScenarioError(where, [f"job {bad[0][0]}: duration {bad[0][1]} is outside 0..{MAX_DURATION:,}"])
    return Instance(path.stem, n_machines, jobs)


def expand(scenario: Scenario, base_dir: Path) -> Scenario:
    """The lab and the fixed list of experiments (one per job) of the scenario's instance."""
    return as_lab(scenario, read(base_dir / scenario.jobshop.file))


def generate(jobs: int, machines: int, low: int, high: int, rng: random.Random) -> Instance:
    """A random instance in the usual way (Taillard): each job visits every machine once, in a random
    order, for a duration drawn uniformly from [low, high]."""
    return Instance(f"random-{jobs}x{machines}", machines,
                    [[(m, rng.randint(low, high)) for m in rng.sample(range(machines), machines)] for _ in range(jobs)])


def as_lab(scenario: Scenario, inst: Instance) -> Scenario:
    """``scenario`` with ``inst``'s machines as its devices and its jobs as its experiments."""
    devices = {
        f"m{m}": {
            "driver": "machine",
            "steps": ["op"],
            "duration": {"mean_s": 0, "cv": 0, "plus_param": "duration_s"},
        }
        for m in range(inst.machines)
    }
    proposals = [
        {
            "params": {"job": j},
            "route": [
                {"step": "op", "device": f"m{m}", "params": {"duration_s": d}} for m, d in job
            ],
        }
        for j, job in enumerate(inst.jobs)
    ]
    data = scenario.model_dump()
    data["devices"] = devices
    data["campaign"].update(
        planner="fixed",
        budget=len(proposals),
        max_in_flight=len(proposals),
        stop_on_target=False,
        planner_options={"proposals": proposals},
    )
    return Scenario.model_validate(data)
