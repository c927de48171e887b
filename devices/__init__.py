"""Simulated device drivers; the kernel finds them through the labtwin.devices entry point."""

from devices.machine import Machine
from devices.reactor import Reactor
from devices.spectrometer import Spectrometer
from devices.synthesiser import Synthesiser

__all__ = ["Machine", "Reactor", "Spectrometer", "Synthesiser"]
