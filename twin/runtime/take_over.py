"""What a campaign that takes over a killed or stopped one reads of it: its devices' reports on the steps it had in
the lab, and the timers it left pending."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from twin.campaign.events import TimerKey
from twin.core.clock import LabClock
from twin.core.messages import Kind, json_from_wire


def reported(report: Any, task: str, attempt: int, stopped: str = "") -> tuple[bool, str | None]:
    """What a device's health report says of attempt ``task#attempt``: whether it still runs it, and the message it
    ended it with (its JSON text, to take), if it has one; a step a stop (``stopped``) cancelled ended with nothing to
    take. A report of another shape (a device that is not ours) says nothing of it."""
    if not isinstance(report, dict):
        return False, None
    if report.get("running") == [task, attempt]:
        return True, None
    recent = report.get("recent")
    for entry in recent if isinstance(recent, list) else ():
        if (isinstance(entry, list) and len(entry) == 3 and entry[:2] == [task, attempt] and isinstance(entry[2], str)
                and not (stopped and _cancelled(entry[2]))):
            return False, entry[2]
    return False, None


def _cancelled(payload: str) -> bool:
    """A device's answer that it cancelled its step (the stop's cancel): not a result to adopt."""
    try:
        env = json_from_wire(payload)
        return env.get("kind") == Kind.FAULT and env.get("body", {}).get("code") == "cancelled"
    except (ValueError, AttributeError):
        return False


def rearm(clock: LabClock, timers: dict[TimerKey, Any], key: TimerKey, due: float,
          fire: Callable[[TimerKey], None]) -> None:
    """A timer the killed process left pending, due at lab time ``due``, set again — unless what the resumed
    campaign heard since (the answers about its steps in the lab) set it already (a retry's back-off)."""
    if key not in timers:
        timers[key] = clock.call_later(max(0.0, due - clock.now()), functools.partial(fire, key))
