"""Two runtimes drive the campaign core: ``fast`` (virtual time, in-process) and ``live`` (asyncio, any bus)."""

from twin.runtime.fast import FastCampaign
from twin.runtime.live import LiveCampaign

__all__ = ["FastCampaign", "LiveCampaign"]
