"""The campaign core: a pure, deterministic state machine (events in, actions out).

No asyncio, no bus, no SQLite, no wall time in here: ``twin.runtime`` drives
it fast in virtual time or live over a bus.
"""

from twin.campaign.core import CampaignCore
from twin.campaign.events import (Ask, CancelTimer, DeviceMessage, Finished, InvalidInput, Note, Operator,
                                  Presence, Proposed, Decided, RecordExperiment, RecordMessage, Send, SetTimer, Stop,
                                  TimerFired)

__all__ = [
    "Ask", "CampaignCore", "CancelTimer", "Decided", "DeviceMessage", "Finished", "InvalidInput", "Note",
    "Operator", "Presence", "Proposed", "RecordExperiment", "RecordMessage", "Send", "SetTimer", "Stop", "TimerFired",
]
