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
from twin.scenario.model import Scenario


@dataclass(frozen=True)
class Instance:
    name: str
    machines: int
    jobs: list[list[tuple[int, int]]]  # per job: (machine, duration) in order


def read(path: str | Path) -> Instance:
    path = Path(path)
    lines = [ln.split("#")[0].strip() for ln in path.read_text().splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise ScenarioError(str(path), ["empty job-shop file: expected 'jobs machines' then one line per job"])
    try:
        n_jobs, n_machines = (int(x) for x in lines[0].split())
        jobs = []
        for row in lines[1 : 1 + n_jobs]:
            nums = [int(x) for x in row.split()]
            jobs.append(list(zip(nums[0::2], nums[1::2], strict=True)))
    except ValueError as exc:
        raise ScenarioError(str(path), [f"not in the standard job-shop format: {exc}"]) from None
    if len(jobs) != n_jobs or any(not 0 <= m < n_machines for job in jobs for m, _ in job):
        raise ScenarioError(str(path), [f"expected {n_jobs} jobs on machines 0..{n_machines - 1}"])
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
