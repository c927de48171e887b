"""labtwin's kernel: a flat public API over private modules."""

from twin.actor import DeviceActor
from twin.bus import Bus, MemoryBus, open_bus
from twin.clock import Clock, LabClock
from twin.decisions import Assignment, FreeDevice, LabView, Outcome, Planner, Proposal, ReadyStep, Scheduler
from twin.driver import Driver, DriverSetup, StepContext, StepResult
from twin.errors import (
    AccountingError,
    BusError,
    ClockError,
    DriverError,
    PluginError,
    ScenarioError,
    TwinError,
)
from twin.lab import prepare, run, run_async
from twin.campaign import CampaignCore
from twin.runtime import FastCampaign, LiveCampaign
from twin.scenario import Scenario, json_schema
from twin.scenario import load as load_scenario
from twin.summary import Summary

__all__ = [
    "AccountingError", "Assignment", "Bus", "BusError", "Clock", "ClockError", "DeviceActor", "Driver",
    "DriverError", "DriverSetup", "FreeDevice", "LabClock", "LabView", "MemoryBus", "CampaignCore", "FastCampaign", "LiveCampaign",
    "Outcome", "Planner", "PluginError", "Proposal", "ReadyStep", "Scenario", "ScenarioError", "Scheduler",
    "StepContext", "StepResult", "Summary", "TwinError", "json_schema", "load_scenario", "open_bus",
    "prepare", "run", "run_async",
]
