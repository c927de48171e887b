"""Scenarios: the model, reading files, job shops as labs, and targets."""

from twin.scenario.loading import json_schema, load, load_mapping, parse, parse_overridden, plain, set_dotted
from twin.scenario.campaign import Campaign
from twin.scenario.model import (BusSpec, Chemistry, ClockSpec, Condition, DeviceType, Duration, Faults,
                                 JobShop, Parameter, Scenario, Target, WorkflowStep, expected_duration,
                                 why_runs_vary)
from twin.scenario.operations import Orchestration, Retry
from twin.scenario.training import Training

__all__ = [
    "BusSpec", "Campaign", "Chemistry", "ClockSpec", "Condition", "DeviceType", "Duration", "Faults", "JobShop",
    "Orchestration", "Parameter", "Retry", "Scenario", "Target", "Training", "WorkflowStep", "expected_duration",
    "json_schema", "load", "load_mapping", "parse", "parse_overridden", "plain", "set_dotted", "why_runs_vary",
]
