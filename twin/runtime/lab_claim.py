"""Is a lab already on the bus this process joins? Asked before it serves the lab's campaign or devices.

Two campaigns of one lab name on one router would send commands to each other's devices: the attempt tokens
keep either from taking the other's results, but both lose their experiments to devices that are busy with, or
answer for, the other. So a process that joins a network (``bus.connect``) first looks for the lab's tokens —
its orchestrator's, and those of the devices it is about to serve itself — and refuses to start beside them;
a scheduler agent (``twin scheduler serve``) looks for another agent of its lab.

Those tokens come only once a process has started, so two processes started at the same moment would each find
none. Each therefore first declares a *claim* on every part it would take (``labtwin/<lab>/claim/<part>/<stamp>``,
held while it runs) and then looks for other claims too: one older than its own means another process got there
first, and it stands down; one younger is given ``STAND_DOWN_S`` to see this one's and stand down, and if it is
still there after that it went ahead, and this one stands down instead. Whatever order the router sees the claims
and looks in, the last to look sees the other's claim, so at most one goes ahead.
A lab that only listens cannot meet another at start: one that joins it later finds it.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Collection

from twin.core import keys
from twin.core.bus.base import Bus, Closable
from twin.core.bus.presence import SETTLE_S, present
from twin.core.clock import sleep_wall
from twin.core.errors import TwinError
from twin.runtime.remote_scheduler import alive_key
from twin.scenario import Scenario

#: wall seconds a younger claimant is given to see this one's claim and stand down: its look lasts SETTLE_S
STAND_DOWN_S = 3 * SETTLE_S


class LabTaken(TwinError):
    """The lab (or one of the devices this process would serve) is already on the bus, served by another
    process."""


class Claims:
    """This process's claims on the parts of a lab it serves; closing them lets another process take the parts."""

    def __init__(self, handles: list[Closable]) -> None:
        self._handles = handles

    def close(self) -> None:
        for h in self._handles:
            h.close()
        self._handles = []


def _stamp() -> str:
    """When the claim was made (nanoseconds, fixed width so that text order is time order) and a random tail."""
    return f"{time.time_ns():020d}-{secrets.token_hex(4)}"


async def refuse_if_taken(bus: Bus, s: Scenario, devices: Collection[str], orchestrator: bool = True,
                          agent: bool = False) -> Claims:
    """Raise ``LabTaken`` if another process holds, or is taking at this moment, the orchestrator of ``s``'s lab
    (when this process would be its orchestrator), one of ``devices`` (which this process would serve), or
    (``agent``) the lab's scheduler agent; else this process's claims on them, to keep while it serves them."""
    if s.bus.kind == "memory" or not s.bus.connect:
        return Claims([])
    lab = s.lab
    parts = [f"dev/{d}" for d in sorted(devices)] + (["orchestrator"] if orchestrator else []) + \
        (["agent"] if agent else [])
    stamp = _stamp()
    claims = Claims([bus.declare_token(keys.claim(lab, part, stamp)) for part in parts])
    try:
        await _refuse_if_held(bus, s, devices, orchestrator, agent, parts, stamp)
    except BaseException:
        claims.close()
        raise
    return claims


async def _refuse_if_held(bus: Bus, s: Scenario, devices: Collection[str], orchestrator: bool, agent: bool,
                          parts: list[str], stamp: str) -> None:
    lab = s.lab
    held = [keys.alive(lab, d) for d in sorted(devices)] + ([keys.orchestrator(lab)] if orchestrator else []) + \
        ([alive_key(lab)] if agent else [])
    found = await present(bus, held + [keys.claim(lab, part) for part in parts])
    _refuse_held(s, set(found), orchestrator, agent)
    others = {k: k.rsplit("/", 1)[1] for k in found if "/claim/" in k and not k.endswith("/" + stamp)}
    if any(theirs < stamp for theirs in others.values()):
        raise LabTaken(_starting(s, [k for k, theirs in others.items() if theirs < stamp]))
    if not others:
        return
    await sleep_wall(STAND_DOWN_S)  # the younger ones see this claim and stand down, or went ahead without seeing it
    again = set(await present(bus, held + list(others)))
    _refuse_held(s, again, orchestrator, agent)
    if again & set(others):
        raise LabTaken(_starting(s, sorted(again & set(others))))


def _part_of(key: str) -> str:
    """``labtwin/<lab>/claim/dev/<device>/<stamp>`` → ``dev/<device>``."""
    return key.split("/claim/", 1)[1].rsplit("/", 1)[0]


def _starting(s: Scenario, claims: list[str]) -> str:
    lab = s.lab
    parts = {_part_of(k) for k in claims}
    devices = sorted(p.split("/", 1)[1] for p in parts if p.startswith("dev/"))
    named = (["its campaign"] if "orchestrator" in parts else []) + \
        (["its scheduler agent"] if "agent" in parts else []) + ([_devices(devices)] if devices else [])
    more = f" and {len(claims) - 1} more" if len(claims) > 1 else ""
    return (f"lab {lab!r}: another process is starting {' and '.join(named)} on this bus at this same moment "
            f"(its claim {min(claims)}{more}): two processes serving one lab would dispatch to, or answer for, each "
            f"other. This one stands down; run it when that one has ended, or as another lab ({_another(lab)})")


def _devices(names: list[str]) -> str:
    return f"{'device' if len(names) == 1 else 'devices'} {', '.join(names)}"


def _are_held(names: list[str], lab: str) -> str:
    return (f"{_devices(names)} of lab {lab!r} {'is' if len(names) == 1 else 'are'} already on this bus, served by "
            "another process")


def _another(lab: str) -> str:
    """How to name this one another lab: `twin lab serve` takes no --set."""
    return f"--set lab={lab}-2, or lab: {lab}-2 in its file"


def _refuse_held(s: Scenario, found: set[str], orchestrator: bool, agent: bool) -> None:
    lab = s.lab
    if agent and alive_key(lab) in found:
        raise LabTaken(f"lab {lab!r} already has a scheduler agent on this bus ({alive_key(lab)} is held by another "
                       "process): two agents would each answer the lab's requests. Stop that one first")
    if orchestrator and keys.orchestrator(lab) in found:
        raise LabTaken(f"lab {lab!r} already has a campaign running on this bus ({keys.orchestrator(lab)} is held by "
                       f"another process): two campaigns of one lab would dispatch to each other's devices. Stop "
                       f"that one, run this one as another lab ({_another(lab)}), or share the lab's devices "
                       "between campaigns (twin lab serve, then twin submit); if it stopped just now, its token "
                       f"lasts one link lease ({s.bus.lease_ms} ms): try again then")
    taken = sorted(keys.device_of(k) for k in found if k.startswith(keys.alive(lab, "")))
    if taken and not orchestrator:  # twin device serve: the device is someone else's already
        raise LabTaken(f"{_are_held(taken, lab)}: stop that one first")
    if taken:
        raise LabTaken(f"{_are_held(taken, lab)}: stop that one, or let this run use them (twin run --external NAME "
                       "for each) instead of "
                       f"serving its own, or run this one as another lab ({_another(lab)})")
