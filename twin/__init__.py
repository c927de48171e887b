"""labtwin's kernel: a flat public API over private sub-packages.

Drivers (``devices/``), decision makers (``agents/``), the docs and the
driver scaffold import from here only; the layers below are private
(``pyproject.toml``'s import-linter contracts keep it so):

    cli → tools → learning → runtime → view → campaign | device → scenario → core

Each name is imported when first asked for (``from twin import Driver`` imports the driver's module, not
the runtime): a command that needs only the bus starts in a fraction of the whole kernel's import.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
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
    from twin.scenario.bottleneck import bottleneck
    from twin.scenario.random_labs import ANY_WORKFLOW, drawn_at_random, random_lab
    from twin.scenario.targets import score
    from twin.tools.testing import driver_setup, run_scenario, run_step
    from twin.view.report import lab_span
    from twin.view.watch import RecordOptions

#: Where each public name lives: (module, name there); the same imports as above, which the type checker reads.
_WHERE = {
    "ANY_WORKFLOW": ("twin.scenario.random_labs", "ANY_WORKFLOW"),
    "AccountingError": ("twin.core.errors", "AccountingError"),
    "Assignment": ("twin.campaign.decisions", "Assignment"),
    "Bus": ("twin.core.bus", "Bus"),
    "BusError": ("twin.core.errors", "BusError"),
    "CampaignCore": ("twin.campaign", "CampaignCore"),
    "CampaignState": ("twin.campaign.decisions", "CampaignState"),
    "Clock": ("twin.core.clock", "Clock"),
    "ClockError": ("twin.core.errors", "ClockError"),
    "DeviceActor": ("twin.device.actor", "DeviceActor"),
    "DeviceState": ("twin.campaign.decisions", "DeviceState"),
    "Driver": ("twin.device.driver", "Driver"),
    "DriverError": ("twin.core.errors", "DriverError"),
    "DriverFeatures": ("twin.device.driver", "DriverFeatures"),
    "DriverSetup": ("twin.device.driver", "DriverSetup"),
    "FastCampaign": ("twin.runtime", "FastCampaign"),
    "FreeDevice": ("twin.campaign.decisions", "FreeDevice"),
    "LabClock": ("twin.core.clock", "LabClock"),
    "LabSummary": ("twin.campaign.summary", "LabSummary"),
    "LabView": ("twin.campaign.decisions", "LabView"),
    "LiveCampaign": ("twin.runtime", "LiveCampaign"),
    "MemoryBus": ("twin.core.bus", "MemoryBus"),
    "Outcome": ("twin.campaign.decisions", "Outcome"),
    "PLUGIN_CHECKS_LOGGER": ("twin.core.plugins", "CHECKS_LOGGER"),
    "Planner": ("twin.campaign.decisions", "Planner"),
    "PluginError": ("twin.core.errors", "PluginError"),
    "Proposal": ("twin.campaign.decisions", "Proposal"),
    "ReadyStep": ("twin.campaign.decisions", "ReadyStep"),
    "RecordOptions": ("twin.view.watch", "RecordOptions"),
    "Refused": ("twin.core.errors", "Refused"),
    "RouteStep": ("twin.campaign.decisions", "RouteStep"),
    "Scenario": ("twin.scenario", "Scenario"),
    "ScenarioError": ("twin.core.errors", "ScenarioError"),
    "Scheduler": ("twin.campaign.decisions", "Scheduler"),
    "StepContext": ("twin.device.driver", "StepContext"),
    "StepResult": ("twin.device.driver", "StepResult"),
    "SteppedCampaign": ("twin.learning.stepper", "SteppedCampaign"),
    "SteppedLab": ("twin.learning.stepper", "SteppedLab"),
    "Summary": ("twin.campaign.summary", "Summary"),
    "TwinError": ("twin.core.errors", "TwinError"),
    "campaign_scenarios": ("twin.scenario.sharing", "campaign_scenarios"),
    "capable": ("twin.campaign.decisions", "capable"),
    "bottleneck": ("twin.scenario.bottleneck", "bottleneck"),
    "drawn_at_random": ("twin.scenario.random_labs", "drawn_at_random"),
    "driver_setup": ("twin.tools.testing", "driver_setup"),
    "expected_duration": ("twin.scenario", "expected_duration"),
    "jobshop_as_lab": ("twin.scenario.jobshop", "as_lab"),
    "json_schema": ("twin.scenario", "json_schema"),
    "keyed_uniforms": ("twin.core.streams", "keyed_uniforms"),
    "lab_span": ("twin.view.report", "lab_span"),
    "load_plugin": ("twin.core.plugins", "load"),
    "load_policy": ("twin.learning.policies", "load_policy"),
    "load_scenario": ("twin.scenario", "load"),
    "not_a_file": ("twin.scenario.files", "not_a_file"),
    "open_bus": ("twin.core.bus", "open_bus"),
    "open_workcell": ("twin.learning.workcell", "open_workcell"),
    "parse_yaml": ("twin.scenario.files", "parse_yaml"),
    "prepare": ("twin.runtime.lab", "prepare"),
    "random_jobshop": ("twin.scenario.jobshop", "generate"),
    "random_lab": ("twin.scenario.random_labs", "random_lab"),
    "read_meta": ("twin.learning.policies", "read_meta"),
    "resume": ("twin.runtime.resume", "resume"),
    "run": ("twin.runtime.lab", "run"),
    "run_async": ("twin.runtime.lab", "run_async"),
    "run_lab": ("twin.runtime.shared_run", "run_lab"),
    "run_scenario": ("twin.tools.testing", "run_scenario"),
    "run_step": ("twin.tools.testing", "run_step"),
    "save_policy": ("twin.learning.policies", "save_policy"),
    "score": ("twin.scenario.targets", "score"),
    "seeded": ("twin.core.streams", "seeded"),
    "sleep_wall": ("twin.core.clock", "sleep_wall"),
    "stepped": ("twin.learning.stepper", "stepped"),
    "tells_progress": ("twin.core.telling", "tells_progress"),
    "time_scale": ("twin.scenario.objective", "time_scale"),
    "wall_on_loop": ("twin.core.clock", "wall_on_loop"),
    "weighted_objective": ("twin.scenario.objective", "weighted_objective"),
    "why_runs_vary": ("twin.scenario", "why_runs_vary"),
    "write_description": ("twin.learning.policies", "write_description"),
    "written_whole": ("twin.core.whole_files", "written_whole"),
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'twin' has no attribute {name!r}")
    module, attr = _WHERE[name]
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value  # asked once
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_WHERE})
