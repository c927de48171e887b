"""Does a device served by another process (`twin device serve`) run as this lab's file says?

A served device reads its own copy of the scenario: its durations, faults, options and (for a simulated one) the
chemistry it measures come from there, while the lab plans and sets each step's deadline by its own copy. Copies
that drifted apart (the lab's file edited on one host, not the other) give steps that time out attempt after
attempt, or results from another model, with nothing to say why. So each device reports, in its health answer, the
parts of its scenario it runs by; the lab asks every external device that joins and names what differs. And a
device served with another lab file's ``lab`` joins that lab, not this one: the lab names it if it sees it there.
"""

from __future__ import annotations

import asyncio
import difflib
import json
import re
from collections.abc import Callable, Collection
from pathlib import PurePath
from typing import Any

from twin.core import keys
from twin.core.bus.base import Bus, Closable
from twin.core.clock import LabClock
from twin.core.tasks import kept
from twin.core.errors import BusError
from twin.core.messages import json_from_wire
from twin.scenario import Scenario

#: what of a device type decides how a served device behaves (cost, envelope and instances are the lab's concern)
DEVICE_FIELDS = ("driver", "steps", "duration", "setup_s", "clean_s", "faults", "options")
CHEMISTRY_FIELDS = ("model", "noise", "stability_s", "options")
#: wall seconds a joining device has to answer the lab's health request
ASK_WALL_S = 5.0
SHOWN = 6


def served_as(s: Scenario, device_type: str, instrument: bool = False) -> dict[str, Any]:
    """The parts of ``s`` a device of ``device_type`` runs by, as JSON: its device type's and (a lab of one
    campaign, whose drivers simulate that campaign's chemistry) the chemistry's. ``instrument``: its driver talks to
    a real instrument, whose options (a broker, a port) name what this host reaches it by, and may differ from the
    lab host's on purpose: they are left out, and so not compared."""
    spec = s.devices[device_type].model_dump(mode="json")
    out: dict[str, Any] = {"device_type": {k: spec[k] for k in DEVICE_FIELDS if not (instrument and k == "options")}}
    if not s.campaigns:
        chemistry = s.chemistry.model_dump(mode="json")
        out["chemistry"] = {k: chemistry[k] for k in CHEMISTRY_FIELDS}
    return out


def differences(ours: dict[str, Any], theirs: dict[str, Any], device_type: str) -> list[str]:
    """What ``theirs`` (a device's report) says otherwise than ``ours``, as the scenario's fields: ``devices.
    spectrometer.duration.mean_s: 5000 there, 300 here``. A path differs only by its file's name (each host's copy
    names files beside it by its own absolute path)."""
    prefix = {"device_type": f"devices.{device_type}", "chemistry": "chemistry"}
    out: list[str] = []
    for part, name in prefix.items():
        if part in ours and isinstance(theirs.get(part), dict):
            for field in theirs[part].keys() & ours[part].keys():  # what the device left out is not compared
                _compare(ours[part][field], theirs[part][field], f"{name}.{field}", out)
    return sorted(out, key=lambda line: (not line.startswith("devices."), line))


def reported_differences(s: Scenario, device_type: str, report: Any) -> list[str] | None:
    """What a device's health ``report`` says it runs by otherwise than ``s``; None for a device of another make,
    which reports no scenario."""
    theirs = report.get("scenario") if isinstance(report, dict) else None
    return differences(served_as(s, device_type), theirs, device_type) if isinstance(theirs, dict) else None


def _compare(ours: Any, theirs: Any, where: str, out: list[str]) -> None:
    if isinstance(ours, dict) and isinstance(theirs, dict):
        for key in sorted(set(ours) | set(theirs), key=str):
            _compare(ours.get(key), theirs.get(key), f"{where}.{key}", out)
    elif ours != theirs and not _same_file(ours, theirs):
        out.append(f"{where}: {_shown(theirs)} there, {_shown(ours)} here")


def _same_file(a: Any, b: Any) -> bool:
    return isinstance(a, str) and isinstance(b, str) and "/" in a + b and PurePath(a).name == PurePath(b).name


def _shown(value: Any) -> str:
    text = "(not set)" if value is None else json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


class ServedCheck:
    """Asks each of ``external`` devices, as it joins the bus, how it is served, and ``report(kind, device,
    detail)`` tells of one that runs by another scenario (``device.mismatch``; ``detail``: its type and the
    differences) and, ``missing_after_s`` lab seconds after the start, of one still not on this lab's bus that is on
    another lab's (``device.elsewhere``: served with another lab file's ``lab``) or whose name is like one on this
    lab's bus that is no device of the lab (``device.misnamed``: a device of a stranger's, named ``spectrometer-1``
    where the lab's one spectrometer is ``spectrometer``)."""

    def __init__(self, bus: Bus, s: Scenario, clock: LabClock, external: Collection[str],
                 report: Callable[[str, str, dict[str, Any]], None], missing_after_s: float | None = None) -> None:
        self._bus, self._s, self._clock, self._report = bus, s, clock, report
        self._type = {name: dtype for dtype in s.devices for name in s.instance_names(dtype) if name in external}
        self._told: set[str] = set()
        self._asking: set[asyncio.Task] = set()
        self._here: set[str] = set()
        self._there: dict[str, set[str]] = {}  # a device -> the other labs it is on the bus as a device of
        self._known = {name for dtype in s.devices for name in s.instance_names(dtype)}
        self._strangers: set[str] = set()  # names on this lab's bus that are none of its devices'
        self._missing_after_s = missing_after_s
        self._watches: list[Closable] = []
        self._timer: asyncio.TimerHandle | None = None

    def start(self) -> ServedCheck:
        # this lab's tokens on a watch of their own: a secure router lets the lab see no other lab's
        self._watches = [self._bus.watch_tokens(keys.alive(self._s.lab), self._on_presence),
                         self._bus.watch_tokens(keys.alive("*"), self._on_any_lab)]
        if self._missing_after_s is not None:
            self._timer = self._clock.call_later(self._missing_after_s, self._elsewhere)
        return self

    def close(self) -> None:
        for watch in self._watches:
            watch.close()
        if self._timer is not None:
            self._timer.cancel()
        for task in self._asking:
            task.cancel()

    def _on_any_lab(self, key: str, alive: bool) -> None:
        device, lab = keys.device_of(key), keys.lab_of(key)
        if device in self._type and lab != self._s.lab:
            (self._there.setdefault(device, set()).add if alive else self._there.get(device, set()).discard)(lab)

    def _on_presence(self, key: str, alive: bool) -> None:
        device = keys.device_of(key)
        if device not in self._known and len(self._strangers) < 1000 or device in self._strangers:
            (self._strangers.add if alive else self._strangers.discard)(device)
        if device not in self._type:
            return
        (self._here.add if alive else self._here.discard)(device)
        if alive and device not in self._told:
            kept(self._asking, self._ask(device))

    def _elsewhere(self) -> None:
        for device in sorted(set(self._type) - self._here):
            like = self._like(device)
            if self._there.get(device):
                self._report("device.elsewhere", device, {"labs": sorted(self._there[device]), "lab": self._s.lab})
            elif like:
                self._report("device.misnamed", device, {"names": like, "lab": self._s.lab,
                                                         "type": self._type[device]})

    def _like(self, device: str) -> list[str]:
        """The names on this lab's bus that are no device of it and look meant for ``device``: of its type (with
        or without an instance number), or close to its name."""
        dtype = self._type[device]
        typed = {n for n in self._strangers if re.sub(r"-\d+$", "", n) == dtype}
        close = difflib.get_close_matches(device, sorted(self._strangers), n=SHOWN, cutoff=0.75)
        return [name[:80] for name in sorted(typed | set(close))[:SHOWN]]

    async def _ask(self, device: str) -> None:
        try:
            answer = await self._bus.request(keys.health(self._s.lab, device), b"",
                                             ASK_WALL_S * self._clock.speed)
            report = json_from_wire(answer)
        except (BusError, ValueError):
            return  # no answer now: the campaign's own deadlines and presence say what matters
        dtype = self._type[device]
        found = reported_differences(self._s, dtype, report)
        if found:  # None: a device of another make (its own client on the bus), with no scenario to compare
            self._told.add(device)
            self._report("device.mismatch", device,
                         {"type": dtype, "differences": found[:SHOWN], "more": max(0, len(found) - SHOWN)})
