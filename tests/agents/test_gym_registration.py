"""Gymnasium conventions: importing the packages registers every environment with a default scenario, so the
plain id works; ``scenario=`` still chooses another lab."""

import gymnasium as gym
import pytest
from gymnasium.utils.env_checker import check_env

import agents  # noqa: F401  (registers its environments)
import devices  # noqa: F401


@pytest.mark.parametrize("env_id", ["labtwin/Scheduling-v0", "labtwin/Planning-v0", "labtwin/ReactorControl-v0"])
def test_the_plain_id_makes_a_working_environment(env_id):
    env = gym.make(env_id)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_scenario_still_overrides_the_default():
    default = gym.make("labtwin/Scheduling-v0")
    other = gym.make("labtwin/Scheduling-v0", scenario="scenarios/jobshop.yaml")
    assert default.unwrapped.base.name == "flaky_lab" and other.unwrapped.base.name == "jobshop_ft06"
    default.close()
    other.close()
    with pytest.raises(Exception, match="no_such.yaml"):
        gym.make("labtwin/Planning-v0", scenario="no_such.yaml")


def test_the_route_env_is_registered_too():
    assert "labtwin/SynthesisRoute-v0" in gym.registry


@pytest.mark.process
def test_worker_processes_make_the_env_from_the_module_qualified_id():
    """A vectorised env's spawned workers have not imported agents: the id that names the module (as README
    says) imports it there, and each worker's lab is the one a plain make gives."""
    import numpy as np

    vec = gym.vector.AsyncVectorEnv([lambda: gym.make("agents:labtwin/Scheduling-v0")] * 2, context="spawn")
    try:
        obs, _ = vec.reset(seed=[0, 1])
    finally:
        vec.close()
    single = gym.make("labtwin/Scheduling-v0")
    first, _ = single.reset(seed=0)
    single.close()
    assert np.array_equal(obs[0], first) and not np.array_equal(obs[0], obs[1])
