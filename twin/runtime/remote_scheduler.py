"""A scheduler that is an actor on the bus, and the orchestrator's side of it, with its fallback.

The agent serves ``labtwin/<lab>/agent/scheduler/decide`` (a request carries
the ``LabView`` as JSON, the reply the assignments) and holds a liveliness
token at ``labtwin/<lab>/agent/scheduler/alive``. ``RemoteScheduler`` is what
the orchestrator calls: while the agent is present it asks it, with a
deadline; when the agent is absent, late, or answers something the view does
not allow, the fallback rule decides instead and the reason is reported once
per change (never a stall, never a lost step).
"""

from __future__ import annotations

import asyncio
import dataclasses
import inspect
import json
import logging
from collections.abc import Callable
from typing import Any

import msgspec

from twin.core.bus import Bus
from twin.core.bus.base import NoReplyError
from twin.core.errors import BusError
from twin.campaign.decisions import Assignment, LabView, capable, unfit
from twin.core.keys import PREFIX, lab_of
from twin.core.messages import json_from_wire

log = logging.getLogger(__name__)


def decide_key(lab: str) -> str:
    return f"{PREFIX}/{lab}/agent/scheduler/decide"


def alive_key(lab: str) -> str:
    return f"{PREFIX}/{lab}/agent/scheduler/alive"


# -- the wire -----------------------------------------------------------------------
# msgspec writes the view's dataclasses as the JSON docs/wire.md shows (sets sorted) ~30 × faster than
# dataclasses.asdict + json, which took 1.7 ms of a 50-job shop's decision; it reads a view back checked field by
# field, a field it does not know ignored
_VIEW_ENCODER = msgspec.json.Encoder(order="deterministic")
_VIEW_DECODER = msgspec.json.Decoder(LabView)


def encode_view(view: LabView) -> bytes:
    return _VIEW_ENCODER.encode(view)


def decode_view(payload: bytes) -> LabView:
    """The view a request carries; a malformed one raises ``ValueError`` saying which field (``$.ready[0].expected_s``)."""
    return _VIEW_DECODER.decode(payload)


def agent_error(reply: bytes) -> str:
    """Why the agent could not decide, where its answer says so (``{"error": "why"}``), else ''."""
    try:
        answer = json_from_wire(reply)
    except ValueError:
        return ""
    why = answer.get("error") if isinstance(answer, dict) and "assign" not in answer else None
    return why[:500] if isinstance(why, str) else ""


def check(view: LabView, reply: bytes) -> tuple[list[Assignment], str]:
    """The assignments in ``reply``, or why they cannot be carried out on ``view``."""
    try:
        items = [Assignment(str(a["task"]), str(a["device"])) for a in json_from_wire(reply)["assign"]]
    except (ValueError, KeyError, TypeError) as exc:
        return [], f"unreadable decision ({exc!r})"
    ready = {r.task: r for r in view.ready}
    free, used = {f.name: f for f in view.free}, set()
    for a in items:
        step, dev = ready.get(a.task), free.get(a.device)
        why = unfit(a, step, dev) or (f"{a.task} → {a.device}: {a.device} is assigned twice" if a.device in used else
                                      f"{a.task} → {a.device}: the step avoids {a.device}"
                                      if step and dev and dev not in capable(step, (dev,)) else "")
        if why:
            return [], f"invalid decision {why}"
        used.add(a.device)
    return items, ""


# -- the agent's side ---------------------------------------------------------------------
class SchedulerService:
    """Serves any scheduler's decisions on the bus (in this process or in its own)."""

    def __init__(self, bus: Bus, lab: str, scheduler: Any) -> None:
        self.bus, self.lab, self.scheduler = bus, lab, scheduler
        self._handles: list[Any] = []
        self._shown: set[str] = set()  # failures logged with their traceback: each once (the lab journals them all)

    def start(self) -> None:
        self._handles = [self.bus.serve(decide_key(self.lab), self._reply), self.bus.declare_token(alive_key(self.lab))]

    def stop(self) -> None:
        for h in self._handles:
            h.close()
        self._handles = []

    async def _reply(self, key: str, payload: bytes) -> bytes:
        view = decode_view(payload)
        try:
            decided = self.scheduler.decide(view)
            if inspect.isawaitable(decided):
                decided = await decided
            assign = [dataclasses.asdict(a) for a in decided]
        except Exception as exc:  # the lab's fallback decides this time, told why; the agent stays up
            why = f"{type(exc).__name__}: {exc}"
            if why not in self._shown and len(self._shown) < 10:
                log.exception("the scheduler failed (%s); the lab's fallback rule decides until it answers again",
                              why)
                self._shown.add(why)
            return json.dumps({"error": why}).encode()
        return json.dumps({"assign": assign}).encode()


# -- the orchestrator's side -----------------------------------------------------------
class Fallback:
    """The rule that decides when the chosen scheduler cannot (absent, late, wrong): it counts its decisions
    and says why once per change of reason, through ``on_fallback``, and when the chosen one decides again,
    through ``on_recovered`` (the campaign journals both)."""

    def __init__(self, rule: Any, name: str) -> None:
        self.rule, self.name, self.count = rule, name, 0
        self.on_fallback: Callable[[str], None] = lambda reason: None
        self.on_recovered: Callable[[str], None] = lambda message: None
        self._kind = ""

    def decide(self, view: LabView, kind: str, reason: str) -> list[Assignment]:
        self.count += 1
        if kind != self._kind:
            log.warning("%s: %s decides instead", reason, self.name)
            self.on_fallback(reason)
            self._kind = kind
        return list(self.rule.decide(view))

    def recovered(self, message: str) -> None:
        """The chosen scheduler answered properly again."""
        if self._kind:
            log.warning("%s", message)
            self.on_recovered(message)
            self._kind = ""


class RemoteScheduler:
    def __init__(self, bus: Bus, lab: str, fallback: Fallback, deadline_s: float) -> None:
        self.bus, self.lab, self.fallback = bus, lab, fallback
        self.deadline_s = deadline_s
        self.present = False
        self.answered = 0  # decisions the agent made
        self._arrived = asyncio.Event()
        self._watch = bus.watch_tokens(alive_key(lab), self._presence)
        #: the labs another agent is on the bus for (its process given another lab file; an agent of one's own
        #: putting another lab in its keys): a secure router shows a lab no other lab's
        self.elsewhere: set[str] = set()
        self._others = bus.watch_tokens(alive_key("*"), self._other_lab)

    def close(self) -> None:
        self._watch.close()
        self._others.close()

    def _other_lab(self, key: str, alive: bool) -> None:
        lab = lab_of(key)
        if lab != self.lab and (len(self.elsewhere) < 100 or not alive):
            (self.elsewhere.add if alive else self.elsewhere.discard)(lab[:80])

    def _presence(self, key: str, alive: bool) -> None:
        self.present = alive
        if alive:
            self._arrived.set()

    async def wait_present(self, timeout_s: float) -> bool:
        """Wait (lab time) for an agent served elsewhere to join; False if it did not."""
        try:
            async with asyncio.timeout(timeout_s):
                await self._arrived.wait()
        except TimeoutError:
            return False
        return True

    def decide(self, view: LabView):
        return self._decide(view)

    async def _decide(self, view: LabView) -> list[Assignment]:
        if not self.present:
            return self.fallback.decide(view, "absent", "the scheduler agent is not on the bus")
        try:
            reply = await self.bus.request(decide_key(self.lab), encode_view(view), self.deadline_s)
        except NoReplyError:
            return self.fallback.decide(view, "late",
                                        f"the scheduler agent did not answer within {self.deadline_s:g} lab-s")
        except BusError as exc:  # it answered with an error (a Zenoh error reply)
            return self.fallback.decide(view, "failed", f"the scheduler agent failed: {exc}")
        failed = agent_error(reply)
        if failed:
            return self.fallback.decide(view, "failed", f"the scheduler agent failed: {failed}")
        assignments, problem = check(view, reply)
        if problem:
            return self.fallback.decide(view, "invalid", f"the scheduler agent sent an {problem}")
        self.fallback.recovered("scheduler agent is back; it decides again")
        self.answered += 1
        return assignments
