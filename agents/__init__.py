"""Decision makers: planners, schedulers, route search, their gym environments and trainers.

Importing the package registers its environments with gymnasium, each with a default scenario, so
``gym.make("labtwin/Scheduling-v0")`` works after ``import agents`` (``scenario=`` still overrides):
``labtwin/Scheduling-v0`` (flaky_lab), ``labtwin/Planning-v0`` (quantum_dots) and
``labtwin/SynthesisRoute-v0`` (the shipped templates and stock). ``labtwin/ReactorControl-v0`` comes with
``import devices``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
ENVS = {"labtwin/Scheduling-v0": "agents.scheduling_env:SchedulingEnv",
        "labtwin/Planning-v0": "agents.planning_env:PlanningEnv",
        "labtwin/SynthesisRoute-v0": "agents.routes.env:SynthesisRouteEnv"}


def default_scenario(scenario: Any, file: str) -> Any:
    """``scenario`` as a Scenario: loaded if a path (or the mapping a file would hold), the shipped
    ``scenarios/<file>`` if None."""
    from twin import Scenario, prepare

    if isinstance(scenario, Scenario):
        return scenario
    if isinstance(scenario, dict):
        return prepare(scenario)
    path = Path(scenario) if scenario is not None else SCENARIOS / file
    if scenario is None and not path.exists():
        raise FileNotFoundError(f"the default scenario {path} is not here (labtwin installed without its "
                                "scenarios/): pass scenario=a Scenario or a scenario file")
    return prepare(path)


for _id, _entry in ENVS.items():
    if _id not in gym.registry:
        gym.register(_id, entry_point=_entry)
