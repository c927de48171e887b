"""The reactor's heater as a learning problem, and the trained controllers in the reactor driver."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from devices.models import thermal
from devices.reactor import load_controller
from devices.reactor_control import PolicyController, ReactorControlEnv, tracking
from twin.runtime.lab import prepare
from twin.learning.workcell import open_workcell

ROOT = Path(__file__).resolve().parents[2]
POLICIES = ROOT / "devices" / "policies"
GAINS = {"kp": 6.0, "ki": 0.04}
torch.set_num_threads(1)


@pytest.mark.parametrize("mode", ["pure", "residual"])
def test_the_control_env_passes_the_gymnasium_checker(mode):
    env = gym.make("devices.reactor_control:labtwin/ReactorControl-v0", mode=mode, pid=GAINS)
    check_env(env.unwrapped, skip_render_check=True)


def test_a_residual_of_zero_is_exactly_the_pid():
    env = ReactorControlEnv("residual", GAINS)
    env.reset(options={"setpoint": 470.0})
    trace = [env.step(np.zeros(1, np.float32))[4]["temperature_k"] for _ in range(env.steps)]
    assert np.allclose(trace, thermal.simulate(470.0, 3600.0, 10.0, controller=thermal.Pid(**GAINS)))


def test_the_trained_controllers_track_the_setpoint_and_ppo_heats_up_faster():
    pid = tracking(thermal.simulate(450.0, 3600.0, 10.0, controller=thermal.Pid(**GAINS)), 450.0, 10.0)
    for name in ("reactor_pure.zip", "reactor_residual.zip"):
        policy, mode = load_controller(POLICIES / name)
        trace = thermal.simulate(450.0, 3600.0, 10.0, controller=PolicyController(policy, 450.0, mode, thermal.Pid(**GAINS)))
        m = tracking(trace, 450.0, 10.0)
        assert m["rms_k"] < 3.0 and m["overshoot_k"] < 3.0, (name, m)
        assert m["time_to_target_s"] < pid["time_to_target_s"], (name, m, pid)


def test_the_reactor_driver_runs_a_trained_controller_in_the_workcell():
    base = prepare(ROOT / "scenarios" / "catalyst.yaml")
    learned = prepare(ROOT / "scenarios" / "catalyst.yaml",
                      overrides={"devices.reactor.options.controller": str(POLICIES / "reactor_pure.zip")})
    params = {"temperature_k": 450.0, "time_s": 3000.0}
    a, b = open_workcell(base).run(params).outputs, open_workcell(learned).run(params).outputs
    assert a["yield"] > 85 and b["yield"] > 85
    assert a != b  # a different controller gives a different temperature trace


def test_a_missing_controller_policy_names_the_file_and_the_fix():
    from twin.core.errors import DriverError

    s = prepare(ROOT / "scenarios" / "catalyst.yaml", overrides={"devices.reactor.options.controller": "nope.zip"})
    with pytest.raises(DriverError, match="nope.zip.*twin train"):
        open_workcell(s)


def test_training_a_controller_in_a_lab_without_a_reactor_says_what_it_needs():
    from tests.conftest import twin_cli

    res = twin_cli("train", ROOT / "scenarios" / "quantum_dots.yaml", "--agent", "controller", "--steps", "10",
                   "--out", ROOT / "runs" / "never.zip")
    assert res.exit_code == 2  # a usage error, as every refusal of twin's
    assert ("quantum_dots has no device type whose driver is 'reactor' (its device types: synthesiser, "
            "spectrometer): --agent controller trains a reactor's heater loop; train it in a lab with one, e.g. "
            "scenarios/catalyst.yaml") in " ".join(res.stderr.split())
    assert "training the controller" not in res.stderr  # refused before its bar starts
    assert not (ROOT / "runs" / "never.zip").exists()
