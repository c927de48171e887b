"""labtwin's kernel: a flat public API over private sub-packages.

Drivers (``devices/``), decision makers (``agents/``), the docs and the
driver scaffold import from here only; the layers below are private
(``pyproject.toml``'s import-linter contracts keep it so):

    cli → tools → learning → runtime → view → campaign | device → scenario → core
"""

from twin.campaign import CampaignCore
from twin.campaign.decisions import (Assignment, CampaignState, DeviceState, FreeDevice, LabView, Outcome, Planner,
                                     Proposal, ReadyStep, RouteStep, Scheduler, capable)
from twin.campaign.summary import LabSummary, Summary
from twin.core.bus import Bus, MemoryBus, open_bus
from twin.core.clock import Clock, LabClock, sleep_wall, wall_on_loop
from twin.core.errors import (AccountingError, BusError, ClockError, DriverError, PluginError, Refused,
                              ScenarioError, TwinError)
from twin.core.plugins import CHECKS_LOGGER as PLUGIN_CHECKS_LOGGER
from twin.core.plugins import load as load_plugin
from twin.core.streams import keyed_uniforms, seeded
from twin.core.telling import tells_progress
from twin.core.whole_files import written_whole
from twin.device.actor import DeviceActor
from twin.device.driver import Driver, DriverFeatures, DriverSetup, StepContext, StepResult
from twin.learning.policies import load_policy, read_meta, save_policy, write_description
from twin.learning.stepper import SteppedCampaign, SteppedLab, stepped
from twin.learning.workcell import open_workcell
from twin.runtime import FastCampaign, LiveCampaign
from twin.runtime.lab import prepare, run, run_async
from twin.runtime.resume import resume
from twin.runtime.shared_run import run_lab
from twin.scenario import Scenario, expected_duration, json_schema, why_runs_vary
from twin.scenario import load as load_scenario
from twin.scenario.files import not_a_file, parse_yaml
from twin.scenario.jobshop import as_lab as jobshop_as_lab
from twin.scenario.jobshop import generate as random_jobshop
from twin.scenario.sharing import campaign_scenarios
from twin.scenario.objective import time_scale, weighted_objective
from twin.scenario.random_labs import ANY_WORKFLOW, drawn_at_random, random_lab
from twin.scenario.targets import score
from twin.tools.testing import driver_setup, run_scenario, run_step
from twin.view.report import lab_span
from twin.view.watch import RecordOptions

__all__ = [
    "ANY_WORKFLOW", "AccountingError", "Assignment", "Bus", "BusError", "CampaignCore", "CampaignState", "Clock", "ClockError", "DeviceActor",
    "DeviceState", "Driver", "DriverError", "DriverFeatures", "DriverSetup", "FastCampaign", "FreeDevice",
    "LabClock", "LabSummary", "LabView", "LiveCampaign", "MemoryBus", "Outcome", "PLUGIN_CHECKS_LOGGER", "Planner",
    "PluginError", "Proposal",
    "ReadyStep", "RecordOptions", "Refused", "RouteStep", "Scenario", "ScenarioError", "Scheduler", "StepContext", "StepResult",
    "SteppedCampaign", "SteppedLab", "Summary", "TwinError", "campaign_scenarios", "time_scale", "weighted_objective", "capable", "drawn_at_random", "driver_setup", "expected_duration", "jobshop_as_lab", "tells_progress",
    "json_schema", "keyed_uniforms", "lab_span", "load_plugin", "load_policy", "load_scenario", "open_bus", "open_workcell",
    "not_a_file", "parse_yaml",
    "prepare", "random_jobshop", "random_lab", "read_meta", "resume", "run", "run_async", "run_lab", "run_scenario", "run_step",
    "save_policy", "score", "seeded", "sleep_wall", "stepped", "wall_on_loop", "why_runs_vary", "write_description",
    "written_whole",
]
