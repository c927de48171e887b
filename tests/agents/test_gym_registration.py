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


@pytest.mark.parametrize("env_id", ["labtwin/Scheduling-v0", "labtwin/Planning-v0", "labtwin/ReactorControl-v0",
                                    "labtwin/SynthesisRoute-v0"])
def test_sb3s_make_vec_env_makes_each_environment_without_a_warning_and_gets_its_pictures(env_id):
    """`make_vec_env(ID)` asks every environment for render_mode="rgb_array": ours warned "not in the possible
    render_modes ([])" for each, and had nothing to draw."""
    import warnings

    from stable_baselines3.common.env_util import make_vec_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        vec = make_vec_env(env_id, n_envs=2, seed=0)
        vec.reset()
        pictures = vec.get_images()
    vec.close()
    assert len(pictures) == 2 and all(p.ndim == 3 and p.shape[2] == 3 and p.dtype == "uint8" for p in pictures)


def test_the_scheduling_picture_has_a_row_per_device_busy_where_it_ran_steps():
    import numpy as np

    from agents.rendering import MARGIN, ROW_H, STATE_COLOURS

    env = gym.make("labtwin/Scheduling-v0", render_mode="rgb_array")
    check_env(env.unwrapped)  # with its render check
    env.reset(seed=3)
    for _ in range(40):
        env.step(int(env.unwrapped.action_masks().nonzero()[0][0]))
    picture = env.render()
    devices = sorted(env.unwrapped.campaign.core.devices.values(), key=lambda d: d.name)
    assert picture.shape[0] == 2 * MARGIN + ROW_H * len(devices)
    for i, device in enumerate(devices):
        row = picture[MARGIN + i * ROW_H + ROW_H // 2]
        busy = (row == np.array(STATE_COLOURS["busy"], np.uint8)).all(axis=1).any()
        assert busy == (device.busy_s > 0 or device.attempt is not None), device.name
    env.close()


def test_the_reactor_picture_draws_the_temperature_where_it_is():
    import numpy as np

    from devices.models import thermal

    env = gym.make("labtwin/ReactorControl-v0", render_mode="rgb_array")
    check_env(env.unwrapped)
    env.reset(seed=0, options={"setpoint": 450.0})
    for _ in range(60):
        env.step(np.array([0.5]))
    picture, inner = env.render(), env.unwrapped
    lo = thermal.T_AMBIENT_K
    hi = max(inner.setpoint, *(t for t, _ in inner._trace)) + 20.0
    x = round(6 + (480 - 12) * 60 / inner.steps)
    y = round(240 - 6 - (240 - 12) * (inner.t - lo) / (hi - lo))
    column = picture[:, x]
    red = np.flatnonzero((column == np.array([228, 87, 86], np.uint8)).all(axis=1))
    assert len(red) and abs(red.mean() - y) <= 3, (red, y)
    env.close()


@pytest.mark.parametrize("env_id", ["labtwin/Planning-v0", "labtwin/ReactorControl-v0"])
def test_a_nan_action_is_refused_before_it_reaches_the_lab(env_id):
    """A diverged policy's NaN went on to the chemistry as parameters (Planning) or to the heater, whose temperature
    was NaN from then on (ReactorControl): every reward after it NaN."""
    import numpy as np

    env = gym.make(env_id).unwrapped
    try:
        env.reset(seed=0)
        with pytest.raises(ValueError, match="NaN"):
            env.step(np.full(env.action_space.shape, np.nan, dtype=np.float32))
        _, reward, *_ = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        assert np.isfinite(reward)
        _, reward, *_ = env.step(np.full(env.action_space.shape, np.inf, dtype=np.float32))  # clipped, as before
        assert np.isfinite(reward)
    finally:
        env.close()
