"""Is a lab already on the bus this process joins? Asked before it serves the lab's campaign or devices.

Two campaigns of one lab name on one router would send commands to each other's devices: the attempt tokens
keep either from taking the other's results, but both lose their experiments to devices that are busy with, or
answer for, the other. So a process that joins a network (``bus.connect``) first looks for the lab's tokens —
its orchestrator's, and those of the devices it is about to serve itself — and refuses to start beside them;
a scheduler agent (``twin scheduler serve``) looks for another agent of its lab.
A lab that only listens cannot meet another at start: one that joins it later finds it.
"""

from __future__ import annotations

from collections.abc import Collection

from twin.core import keys
from twin.core.bus.base import Bus
from twin.core.bus.presence import present
from twin.core.errors import TwinError
from twin.runtime.remote_scheduler import alive_key
from twin.scenario import Scenario


class LabTaken(TwinError):
    """The lab (or one of the devices this process would serve) is already on the bus, served by another
    process."""


async def refuse_if_taken(bus: Bus, s: Scenario, devices: Collection[str], orchestrator: bool = True,
                          agent: bool = False) -> None:
    """Raise ``LabTaken`` if another process holds the orchestrator token of ``s``'s lab (when this process
    would be its orchestrator), the token of one of ``devices`` (which this process would serve), or (``agent``)
    the lab's scheduler agent's."""
    if s.bus.kind == "memory" or not s.bus.connect:
        return
    lab = s.lab
    wanted = [keys.alive(lab, d) for d in sorted(devices)] + ([keys.orchestrator(lab)] if orchestrator else [])
    found = await present(bus, wanted + ([alive_key(lab)] if agent else []))
    if agent and alive_key(lab) in found:
        raise LabTaken(f"lab {lab!r} already has a scheduler agent on this bus ({alive_key(lab)} is held by another "
                       "process): two agents would each answer the lab's requests. Stop that one first")
    if orchestrator and keys.orchestrator(lab) in found:
        raise LabTaken(f"lab {lab!r} already has a campaign running on this bus ({keys.orchestrator(lab)} is held by "
                       f"another process): two campaigns of one lab would dispatch to each other's devices. Stop "
                       f"that one, run this one as another lab (--set lab={lab}-2), or share the lab's devices "
                       "between campaigns (twin lab serve, then twin submit); if it stopped just now, its token "
                       f"lasts one link lease ({s.bus.lease_ms} ms): try again then")
    taken = [keys.device_of(k) for k in found if k.startswith(keys.alive(lab, ""))]
    if taken and not orchestrator:  # twin device serve: the device is someone else's already
        raise LabTaken(f"device(s) {taken} of lab {lab!r} are already on this bus, served by another process: stop "
                       "that one first")
    if taken:
        raise LabTaken(f"device(s) {taken} of lab {lab!r} are already on this bus, served by another process: "
                       "stop that one, or let this run use them (twin run --external NAME for each) instead of "
                       f"serving its own, or run this one as another lab (--set lab={lab}-2)")
