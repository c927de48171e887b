"""The files a scenario's plugins are given (a policy, a route planner's stock, a driver's certificate, a chemistry
model's data), found as its job-shop file is: beside the scenario first, else where the command runs.

The kernel does not know which option of a plugin is a file, so a string is taken for one only where it looks like
a file's path (a suffix, or a folder in it) and such a file lies beside the scenario; it is then given as that
file's absolute path. Anything else (a name, a number, a file only the working directory has) is left as written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from twin.scenario.campaign import Campaign
from twin.scenario.model import Scenario


def found_beside(s: Scenario, base: Path) -> Scenario:
    """``s`` with each file its plugins are given that lies beside it (under ``base``) named by its absolute
    path."""
    update: dict[str, Any] = {}
    devices = {name: _device(d, base) for name, d in s.devices.items()}
    if any(devices[name] is not d for name, d in s.devices.items()):
        update["devices"] = devices
    campaign = _campaign(s.campaign, base)
    if campaign is not s.campaign:
        update["campaign"] = campaign
    if (chemistry := _chemistry(s.chemistry, base)) is not s.chemistry:
        update["chemistry"] = chemistry
    campaigns = [_shared(c, base) for c in s.campaigns]
    if any(a is not b for a, b in zip(campaigns, s.campaigns)):
        update["campaigns"] = campaigns
    lab_scheduler = s.orchestrator.lab_scheduler
    if lab_scheduler and (spec := _spec(lab_scheduler, base)) != lab_scheduler:
        update["orchestrator"] = s.orchestrator.model_copy(update={"lab_scheduler": spec})
    return s.model_copy(update=update) if update else s


def _shared(c: Any, base: Path) -> Any:
    """One campaign of a lab several share: its own campaign section and chemistry."""
    update: dict[str, Any] = {}
    if c.campaign is not None and (campaign := _campaign(c.campaign, base)) is not c.campaign:
        update["campaign"] = campaign
    if c.chemistry is not None and (chemistry := _chemistry(c.chemistry, base)) is not c.chemistry:
        update["chemistry"] = chemistry
    return c.model_copy(update=update) if update else c


def _chemistry(c: Any, base: Path) -> Any:
    return c.model_copy(update={"options": options}) if (options := _walk(c.options, base)) != c.options else c


def _device(d: Any, base: Path) -> Any:
    update: dict[str, Any] = {}
    if (options := _walk(d.options, base)) != d.options:
        update["options"] = options
    if d.twin is not None and (twin_options := _walk(d.twin.options, base)) != d.twin.options:
        update["twin"] = d.twin.model_copy(update={"options": twin_options})
    return d.model_copy(update=update) if update else d


def _campaign(c: Campaign, base: Path) -> Campaign:
    update: dict[str, Any] = {}
    for field in ("planner", "scheduler", "fallback_scheduler"):  # rl:POLICY.zip
        if (spec := _spec(getattr(c, field), base)) != getattr(c, field):
            update[field] = spec
    for field in ("planner_options", "scheduler_options"):
        if (options := _walk(getattr(c, field), base)) != getattr(c, field):
            update[field] = options
    return c.model_copy(update=update) if update else c


def _spec(spec: str, base: Path) -> str:
    """``rl:POLICY.zip`` with the policy beside the scenario: ``rl:/its/absolute/path``."""
    name, sep, rest = spec.partition(":")
    return f"{name}:{found}" if sep and rest and (found := _file(rest, base)) else spec


def _walk(value: Any, base: Path) -> Any:
    if isinstance(value, str):
        return _file(value, base) or value
    if isinstance(value, dict):
        return {k: _walk(v, base) for k, v in value.items()}
    if isinstance(value, list):
        return [_walk(v, base) for v in value]
    return value


def _file(value: str, base: Path) -> str | None:
    """The absolute path of the file ``value`` names beside the scenario, or None."""
    if len(value) > 4096 or not value.strip():
        return None
    try:
        path = Path(value)
        if path.is_absolute() or not (path.suffix or len(path.parts) > 1):
            return None
        beside = base / path
        return str(beside.resolve()) if beside.exists() else None
    except (OSError, ValueError, RuntimeError):  # a NUL in it, a name too long for the file system
        return None
