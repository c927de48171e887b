"""A live campaign's control desk: an operator's requests on ``labtwin/<lab>/control/<command>`` (``twin ctl``).

``status`` is answered from the core's state. Every other command becomes an ``Operator`` event for the core
(journalled with its inputs, so a resumed campaign replays it); the answer is the note it ended in, sent
once the journal holds it. A request that is not a JSON object of the expected fields is refused here, with
the field named, and never reaches the core.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import time
from collections.abc import Callable
from typing import Any

from twin.campaign import CampaignCore, Note, Operator
from twin.campaign.events import OPERATOR_COMMANDS
from twin.campaign.operator import status
from twin.core.clock import LabClock, wall_on_loop
from twin.core.messages import json_from_wire

MAX_REQUEST = 4096
MAX_EXPERIMENT = 2**31  # the journal keeps an experiment in a 64-bit column: a larger one failed every later write
WHO = re.compile(r"^[A-Za-z0-9_.@-]{1,64}$")
ANSWER_S = 5.0  # wall seconds for the core to take an act (it takes milliseconds; a stuck loop is reported)


class ControlDesk:
    def __init__(self, core: CampaignCore, clock: LabClock, feed: Callable[[Any], None],
                 flush: Callable[[], None]) -> None:
        self.core, self.clock, self._feed, self._flush = core, clock, feed, flush
        self._waiting: dict[str, asyncio.Future] = {}
        self._answering = 0
        self._quiet: asyncio.Event | None = None  # set while no answer is being written

    async def serve(self, key: str, payload: bytes) -> bytes:
        command = key.rsplit("/", 1)[-1]
        self._answering += 1
        try:
            answer = await self._answer(command, payload)
        except ValueError as exc:
            answer = {"ok": False, "error": str(exc)}
        finally:
            self._answering -= 1
            if not self._answering and self._quiet is not None:
                self._quiet.set()
        return json.dumps(answer).encode()

    async def drain(self, seconds: float = 2.0) -> None:
        """Before the campaign closes its bus: let the answers being written go out (a ``stop`` ends the
        campaign before its own answer has left). Each is a reply once its coroutine returns, so this waits for
        the count of them to reach 0, at most ``seconds`` of wall time (lab time on a virtual clock)."""
        if not self._answering:
            return
        self._quiet = asyncio.Event()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._quiet.wait(), wall_on_loop(seconds))
        await asyncio.sleep(0)  # the last reply is sent as its coroutine returns: one more turn of the loop

    def noted(self, note: Note) -> None:
        """The runtime's hook for the core's notes: an operator's act has ended in ``note``."""
        ref = note.detail.get("ref") if isinstance(note.detail, dict) else None
        fut = self._waiting.pop(ref, None) if ref else None
        if fut is not None and not fut.done():
            fut.set_result(note)

    async def _answer(self, command: str, payload: bytes) -> dict[str, Any]:
        request = _request(payload)
        named, mine = request.pop("campaign"), self.core.s.name
        if named is not None and named != mine:
            raise ValueError(f"this lab runs one campaign, {mine!r}, not {str(named)[:64]!r}: leave --campaign out "
                             "(it names one of the campaigns of a lab several share, `twin lab serve`)")
        if command == "status":
            return {"ok": True, "status": status(self.core, self.clock.now())}
        if command not in OPERATOR_COMMANDS:
            raise ValueError(f"unknown command {command!r}: use status or one of {', '.join(OPERATOR_COMMANDS)}")
        if self.clock.is_virtual:
            raise ValueError("this campaign runs in virtual time, faster than anyone could act on it: "
                             "control it on a scaled or wall clock (clock.mode)")
        if self.core.finished:
            raise ValueError("the campaign has finished")
        ref = f"{time.time_ns():020d}"  # sorts as the requests arrived: acts of one instant keep their order
        fut = asyncio.get_running_loop().create_future()
        self._waiting[ref] = fut
        self._feed(Operator(command, request["who"], ref, request["experiment"], request["now"], request["reason"],
                            request["question"], request["option"], request["item"], request["amount"],
                            request["task"]))
        try:
            note = await asyncio.wait_for(fut, wall_on_loop(ANSWER_S))
        except asyncio.TimeoutError:
            self._waiting.pop(ref, None)
            raise ValueError(f"the campaign did not take the {command} within {ANSWER_S:.0f} s; "
                             "is it stuck? `twin ctl status` shows what it is doing") from None
        self._flush()  # on disk before the operator hears it: a kill now cannot undo it
        detail, lab_hours = dict(note.detail), round((note.t_lab - self.core.t0) / 3600, 4)
        if note.kind == "operator.refused":
            return {"ok": False, "error": detail["why"], "lab_hours": lab_hours}
        return {"ok": True, "done": note.kind, "who": detail["who"], "lab_hours": lab_hours,
                "status": status(self.core, self.clock.now())}


def _request(payload: bytes) -> dict[str, Any]:
    """The request's fields, checked: who (a name), experiment (an int), now (a bool), reason (a short text)."""
    if len(payload) > MAX_REQUEST:
        raise ValueError(f"a request of {len(payload)} bytes: at most {MAX_REQUEST}")
    try:
        data = json_from_wire(payload or b"{}")
    except ValueError as exc:
        raise ValueError(f"the request is not JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError("the request must be a JSON object")
    fields = ("who", "experiment", "now", "reason", "question", "option", "item", "amount", "task", "campaign")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(f"unknown field(s) {unknown}: a request has {', '.join(fields)}")
    who = data.get("who", "operator")
    if not isinstance(who, str) or not WHO.match(who):
        raise ValueError(f"who: {who!r} is not a name (1-64 letters, digits, '_', '.', '@', '-')")
    experiment = data.get("experiment")
    if experiment is not None and (isinstance(experiment, bool) or not isinstance(experiment, int)
                                   or not 0 <= experiment < MAX_EXPERIMENT):
        raise ValueError(f"experiment: {str(experiment)[:40]!r} is not an experiment number")
    now = data.get("now", False)
    if not isinstance(now, bool):
        raise ValueError(f"now: {now!r} is not true or false")
    reason = data.get("reason", "")
    if not isinstance(reason, str) or len(reason) > 500:
        raise ValueError("reason: a text of at most 500 characters")
    words = {}
    amount = data.get("amount")
    if amount is not None and (isinstance(amount, bool) or not isinstance(amount, (int, float))
                               or not 0 < amount < 1e15):
        raise ValueError(f"amount: {str(amount)[:80]!r} is not a positive number below 1e15")
    for name in ("question", "option", "item", "task"):
        value = data.get(name, "")
        if not isinstance(value, str) or len(value) > 64:
            raise ValueError(f"{name}: {str(value)[:80]!r} is not a short text")
        words[name] = value
    return {"who": who, "experiment": experiment, "now": now, "reason": reason, "amount": amount,
            "campaign": data.get("campaign"), **words}
