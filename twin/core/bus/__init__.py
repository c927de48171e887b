"""The message bus: one protocol, an in-memory and a Zenoh implementation."""

from twin.core.bus.base import Bus, Closable, Handler, NoReplyError, TokenHandler, key_matches
from twin.core.bus.memory import MemoryBus, MemoryHub

__all__ = [
    "Bus",
    "Closable",
    "Handler",
    "MemoryBus",
    "MemoryHub",
    "NoReplyError",
    "TokenHandler",
    "key_matches",
    "open_bus",
]


def open_bus(kind: str, clock, **zenoh_options) -> Bus:
    """A bus of ``kind`` ("zenoh" or "memory"), not yet started."""
    if kind == "memory":
        return MemoryBus()
    if kind == "zenoh":
        from twin.core.bus.zenoh_bus import ZenohBus
        from twin.core.bus.zenoh_config import ZenohOptions

        return ZenohBus(clock, ZenohOptions(**zenoh_options))
    from twin.core.errors import BusError

    raise BusError(f"unknown bus {kind!r}: use 'zenoh' (the default) or 'memory'")
