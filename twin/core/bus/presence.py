"""Which presence tokens a bus holds now: asked before a process takes a part in a lab, or to name the labs on it."""

from __future__ import annotations

from collections.abc import Iterable

from twin.core import keys
from twin.core.bus.base import Bus
from twin.core.clock import sleep_wall

#: wall seconds to collect the tokens a router or peer reports: it sends those it knows within milliseconds of
#: being asked, but a session opened an instant ago may not have asked yet (measured: half the asks made at once
#: after opening found nothing, every one 50 ms later found the token)
SETTLE_S = 0.3


async def present(bus: Bus, keyexprs: Iterable[str], wait_s: float = SETTLE_S) -> list[str]:
    """The tokens on ``bus`` matching any of ``keyexprs``, as reported within ``wait_s`` wall seconds."""
    seen: set[str] = set()

    def note(key: str, alive: bool) -> None:
        (seen.add if alive else seen.discard)(key)

    watches = [bus.watch_tokens(k, note) for k in keyexprs]
    try:
        await sleep_wall(wait_s)
    finally:
        for w in watches:
            w.close()
    return sorted(seen)


async def labs_on(bus: Bus, wait_s: float = SETTLE_S) -> list[str]:
    """The labs with a campaign or a device on ``bus`` now (by their tokens)."""
    found = await present(bus, [keys.orchestrator("*"), keys.alive("*")], wait_s)
    return sorted({keys.lab_of(key) for key in found})


def elsewhere(labs: list[str]) -> str:
    """The labs a bus has, as a clause for a message about a lab it does not have."""
    return f"labs on it now: {', '.join(labs)}" if labs else "no lab is on it now"
