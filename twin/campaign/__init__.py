"""The campaign core: a pure, deterministic state machine (events in, actions out).

No asyncio, no bus, no SQLite, no wall time in here: ``twin.runtime`` drives
it fast in virtual time or live over a bus. Each name below is imported when
first asked for: a module of this package (the journal's settings, say) is
imported without the core.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from twin.campaign.core import CampaignCore
    from twin.campaign.events import (Ask, CancelTimer, DeviceMessage, Finished, InvalidInput, Note, Operator,
                                      Presence, Proposed, Decided, RecordExperiment, RecordMessage, Send, SetTimer,
                                      Stop, TimerFired)

__all__ = [
    "Ask", "CampaignCore", "CancelTimer", "Decided", "DeviceMessage", "Finished", "InvalidInput", "Note",
    "Operator", "Presence", "Proposed", "RecordExperiment", "RecordMessage", "Send", "SetTimer", "Stop", "TimerFired",
]


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module 'twin.campaign' has no attribute {name!r}")
    value = getattr(importlib.import_module("twin.campaign.core" if name == "CampaignCore" else
                                            "twin.campaign.events"), name)
    globals()[name] = value
    return value
