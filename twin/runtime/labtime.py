"""One lab time across processes (DESIGN.md, "Clock").

The lab (the process that runs the campaign) owns lab time. It answers queries on
``labtwin/<lab>/clock`` with its clock's anchor — mode, speed, and the lab time it
read at a Unix time — and publishes the anchor when it starts and every few wall
seconds. A process that joins the lab (``twin device serve``, ``twin scheduler
serve``) asks for the anchor before it serves, again whenever the lab's campaign
comes on the bus, and re-anchors its own clock on every one it hears, so a lab
that restarts (``twin resume``) or runs again carries its devices along. Both
sides read the same Unix time: one host, or hosts kept in step by NTP.
A device that has not heard the lab's clock refuses commands ("not now"); one
whose operator asked for another mode or speed than the lab's stops, saying so.
While the campaign whose time a process keeps stays on the bus, its time runs on as
it began: an anchor then of another mode or speed, or one that would move lab time
further than a device may stamp from it, cannot be that lab's (another process's on a
bus without security, docs/security.md) and is ignored, said once.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from collections.abc import Callable
from typing import Any

from twin.core import keys
from twin.core.bus import Bus, Closable, NoReplyError
from twin.core.clock import LabClock
from twin.core.numbers import finite
from twin.core.errors import BusError, ClockError
from twin.runtime.event_decoder import CLOCK_OFF_S, CLOCK_OFF_WALL_S

log = logging.getLogger(__name__)

#: How often the lab re-publishes its anchor: a joiner's Unix and monotonic clocks drift apart slowly.
REPUBLISH_WALL_S = 5.0
#: A re-anchoring that moves lab time by more than this much wall time is logged.
NOTICEABLE_WALL_S = 0.05


def parse_anchor(payload: bytes, lab: str) -> dict[str, Any]:
    """A clock anchor from the bus, checked; :class:`ClockError` names what is wrong with it."""
    try:
        data = json.loads(payload)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise ClockError(f"lab {lab!r}'s clock message is not JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ClockError(f"lab {lab!r}'s clock message is not an object")
    mode, speed, lab_s, wall_s = (data.get(k) for k in ("mode", "speed", "lab_s", "wall_s"))
    if mode not in ("virtual", "scaled", "wall"):
        raise ClockError(f"lab {lab!r}'s clock message has mode {str(mode)[:20]!r}: expected virtual, scaled or wall")
    for name, value in (("speed", speed), ("lab_s", lab_s), ("wall_s", wall_s)):
        if not finite(value):
            raise ClockError(f"lab {lab!r}'s clock message has a {name} that is not a finite number")
    if speed <= 0:
        raise ClockError(f"lab {lab!r}'s clock message has speed {speed}: must be > 0")
    return {"mode": mode, "speed": float(speed), "lab_s": float(lab_s), "wall_s": float(wall_s)}


class LabTimeSource:
    """The lab's side: answer and publish its clock's anchor."""

    def __init__(self, bus: Bus, lab: str, clock: LabClock) -> None:
        self._bus, self._lab, self._clock = bus, lab, clock
        self._handles: list[Closable] = []
        self._ticker: asyncio.Task | None = None

    def start(self) -> None:
        key = keys.clock(self._lab)
        self._handles.append(self._bus.serve(key, self._answer))
        if not self._clock.is_virtual:  # a virtual lab only answers, so that a joiner can refuse it clearly
            self._publish()
            self._ticker = asyncio.ensure_future(self._republish())

    def close(self) -> None:
        if self._ticker is not None:
            self._ticker.cancel()
        for h in self._handles:
            h.close()

    async def _answer(self, key: str, payload: bytes) -> bytes:
        return json.dumps(self._clock.anchor()).encode()

    def _publish(self) -> None:
        self._bus.publish(keys.clock(self._lab), json.dumps(self._clock.anchor()).encode())

    async def _republish(self) -> None:
        while True:
            await self._clock.sleep(REPUBLISH_WALL_S * self._clock.speed)
            self._publish()


class LabTimeFollower:
    """A joining process's side: its clock keeps the lab's time.

    ``mode``/``speed``: what the operator asked for (``None``: whatever the lab runs). ``on_error`` is
    called with the reason when the lab turns out to run a clock this process may not follow.
    """

    def __init__(self, bus: Bus, lab: str, clock: LabClock, mode: str | None = None, speed: float | None = None,
                 on_error: Callable[[str], None] = lambda reason: None) -> None:
        self._bus, self._lab, self._clock = bus, lab, clock
        self._mode, self._speed, self._on_error = mode, speed, on_error
        self._sub: Closable | None = None
        self._campaigns: Closable | None = None
        self._asking: asyncio.Future | None = None
        self.error = ""
        clock.anchored = False
        self._lab_on_bus = False  # the campaign's token, as last heard
        self._steady = False  # anchored while the campaign was on the bus, and it has stayed on since
        self._ignored = 0

    async def start(self, wait_s: float) -> bool:
        """Ask the lab for its clock (up to ``wait_s`` wall seconds) and listen for it; whether it answered.
        Raises :class:`ClockError` if it runs a clock this process cannot follow."""
        self._sub = self._bus.subscribe(keys.clock(self._lab), self._on_anchor)
        self._campaigns = self._bus.watch_tokens(keys.orchestrator(self._lab), self._on_campaign)
        try:
            payload = await self._bus.request(keys.clock(self._lab), b"", wait_s * self._clock.speed)
        except (NoReplyError, BusError):
            return self._clock.anchored  # the lab is not running yet: its first publication anchors us
        self._adopt(parse_anchor(payload, self._lab))
        if self.error:
            raise ClockError(self.error)
        return True

    def close(self) -> None:
        for handle in (self._sub, self._campaigns):
            if handle is not None:
                handle.close()
        if self._asking is not None:
            self._asking.cancel()

    def _on_campaign(self, key: str, alive: bool) -> None:
        """The lab's campaign came on the bus: a lab started after this process, another run of it (its time starts
        again) or a resume. Its time is asked at once: its first publication may have gone out before this process
        was linked to it, and the next comes REPUBLISH_WALL_S later (meanwhile a device refused work for want of a
        clock, or stamped the new run's work in the last run's time)."""
        self._lab_on_bus, self._steady = alive, False
        if alive and not self.error:
            if self._asking is not None:  # a question still out is of an earlier campaign's coming
                self._asking.cancel()
            self._asking = asyncio.ensure_future(self._ask_again())

    async def _ask_again(self) -> None:
        try:
            payload = await self._bus.request(keys.clock(self._lab), b"", 2.0 * self._clock.speed)
        except (NoReplyError, BusError):
            return  # gone again, or not answering yet: its publications still anchor us
        self._on_anchor(keys.clock(self._lab), payload)

    def _on_anchor(self, key: str, payload: bytes) -> None:
        try:
            self._adopt(parse_anchor(payload, self._lab))
        except ClockError as exc:
            log.warning("ignored: %s", exc)

    def _adopt(self, a: dict[str, Any]) -> None:
        if self.error:
            return
        if self._steady:
            unlike = self._unlike_running(a)
            if unlike:
                self._ignored += 1
                if self._ignored == 1 or self._ignored % 100 == 0:
                    log.warning("ignored a clock message for lab %s: %s, while its campaign has been on the bus "
                                "since this process took its time; not the lab's own (another process on a bus "
                                "without security?) (%d so far)", self._lab, unlike, self._ignored)
                return
        problem = self._cannot_follow(a)
        if problem:
            self.error = problem
            self._clock.anchored = False
            self._on_error(problem)
            return
        first = not self._clock.anchored
        jump = self._clock.follow(a["mode"], a["speed"], a["lab_s"], a["wall_s"])
        self._steady = self._lab_on_bus
        if first or abs(jump) > NOTICEABLE_WALL_S * a["speed"]:
            log.info("following lab %s's %s clock at %g×: lab time %.1f s (moved %+.1f lab-s)", self._lab,
                     a["mode"], a["speed"], self._clock.now(), jump)

    def _unlike_running(self, a: dict[str, Any]) -> str:
        """How anchor ``a`` differs from the time of the campaign still running ('' where it does not)."""
        clock = self._clock
        if a["mode"] != clock.mode or (a["mode"] == "scaled" and not math.isclose(a["speed"], clock.speed)):
            return f"a {a['mode']} clock at {a['speed']:g}×, where it runs a {clock.mode} one at {clock.speed:g}×"
        jump = clock.now_by(a["speed"], a["lab_s"], a["wall_s"]) - clock.now()
        if abs(jump) > max(CLOCK_OFF_S, CLOCK_OFF_WALL_S * clock.speed):
            return f"lab time moved by {jump:+.1f} s"
        return ""

    def _cannot_follow(self, a: dict[str, Any]) -> str:
        lab = self._lab
        if a["mode"] == "virtual":
            return (f"lab {lab!r} runs on a virtual clock, which a process outside it cannot follow: run the lab "
                    "with --clock scaled or --clock wall")
        if self._mode is not None and (a["mode"] != self._mode or (
                self._speed is not None and a["mode"] == "scaled" and not math.isclose(a["speed"], self._speed))):
            asked = self._mode + (f" at {self._speed:g}×" if self._mode == "scaled" and self._speed else "")
            return (f"lab {lab!r} runs a {a['mode']} clock at {a['speed']:g}×, but this process was started with "
                    f"--clock {asked}: start it without --clock/--speed to follow the lab's")
        return ""
