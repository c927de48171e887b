"""Simulated device drivers; the kernel finds them through the labtwin.devices entry point. Importing the package
registers ``labtwin/ReactorControl-v0`` (the reactor's heater as a gymnasium environment) with gymnasium."""

import gymnasium as gym

from devices.machine import Machine
from devices.reactor import Reactor
from devices.spectrometer import Spectrometer
from devices.synthesiser import Synthesiser

__all__ = ["Machine", "Reactor", "Spectrometer", "Synthesiser"]

if "labtwin/ReactorControl-v0" not in gym.registry:
    gym.register("labtwin/ReactorControl-v0", entry_point="devices.reactor_control:ReactorControlEnv")
