"""A live campaign's core, rebuilt from the inputs its journal recorded.

A live runtime journals, before each ``advance``, what the core was given
(``Journal.inputs``): the core is deterministic, so feeding the same batches
again rebuilds the same state. ``rebuild`` also says what the dead process
left pending: its timers (with their lab-time due dates) and a question it
had asked and not had answered.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from twin.campaign import operator
from twin.campaign.core import CampaignCore
from twin.campaign.events import (Ask, CancelTimer, Decided, DeviceMessage, InvalidInput, Operator, Presence,
                                  Proposed, SetTimer, Stop, TimerFired, TimerKey, TimerKind)
from twin.core.errors import TwinError
from twin.core.messages import InvalidMessage, decode
from twin.campaign.decisions import Assignment, Proposal, RouteStep
from twin.scenario.model import Scenario


def encode(event: Any) -> list[Any]:
    """One input as JSON-able data."""
    t = type(event)
    if t is DeviceMessage:
        payload = event.payload
        return ["msg", payload.decode() if isinstance(payload, bytes) else payload, event.key, event.token]
    if t is Presence:
        return ["presence", event.device, event.alive]
    if t is TimerFired:
        return ["timer", str(event.key.kind), event.key.ref]
    if t is InvalidInput:
        return ["invalid", event.sender, event.reason, event.key, event.excerpt, *([event.count] if event.count > 1
                                                                                   else [])]
    if t is Stop:
        return ["stop", event.reason, *([] if event.outside else [False])]
    if t is Operator:
        return ["operator", event.command, event.who, event.ref, event.experiment, event.now, event.reason,
                event.question, event.option, event.item, event.amount, event.task]
    if t is Proposed:
        return ["proposed", [[p.params, None if p.route is None else [[r.step, r.device, r.params] for r in p.route],
                              *([p.cost] if p.cost else [])] for p in event.proposals],
                *([event.failed] if event.failed or event.why else []), *([event.why] if event.why else [])]
    if t is Decided:
        return ["decided", [[a.task, a.device] for a in event.assignments], event.wall_s]
    raise TypeError(f"not a core input: {event!r}")


def encode_all(events: list[Any]) -> list[list[Any]]:
    """Inputs as JSON-able data, the undecodable messages of each sender as one entry with their count, where the
    first was (a flood of them made a journal entry each): they change nothing but the count, which the core keeps
    the same replayed; it notes them as floods.py says."""
    out: list[list[Any]] = []
    invalid: dict[str, list[Any]] = {}  # sender -> its entry
    for event in events:
        if type(event) is not InvalidInput:
            out.append(encode(event))
        elif event.sender in invalid:
            merged(invalid[event.sender], event.count)
        else:
            out.append(entry := encode(event))
            invalid[event.sender] = entry
    return out


def merged(entry: list[Any], count: int) -> None:
    """``entry`` (an encoded undecodable message, or a run of them) standing for ``count`` more."""
    if len(entry) == 5:
        entry.append(1)
    entry[5] += count


def decode_input(data: list[Any]) -> Any:
    kind = data[0]
    if kind == "msg":
        raw = data[1].encode() if isinstance(data[1], str) else data[1]
        try:
            env, body = decode(raw)
        except InvalidMessage as exc:
            return InvalidInput(exc.sender, exc.reason)
        return DeviceMessage(env.kind, env.sender, env.task, env.attempt, body.to_dict(), raw, data[2], data[3],
                             env.campaign or "")
    if kind == "presence":
        return Presence(data[1], data[2])
    if kind == "timer":
        return TimerFired(TimerKey(TimerKind(data[1]), data[2]))
    if kind == "invalid":
        return InvalidInput(*data[1:6])
    if kind == "stop":
        return Stop(data[1], data[2] if len(data) > 2 else True)  # only a stop from outside is an input
    if kind == "operator":
        return Operator(*data[1:12])
    if kind == "proposed":
        return Proposed([Proposal(item[0], None if item[1] is None else tuple(RouteStep(*r) for r in item[1]),
                                  *item[2:3]) for item in data[1]], *data[2:4])
    if kind == "decided":
        return Decided([Assignment(task, device) for task, device in data[1]], data[2])
    raise ValueError(f"unknown input {kind!r} in the journal")


@dataclass(frozen=True, slots=True)
class PlannerAsk:
    """A question the planner answered, kept small: its history was the first ``known`` outcomes of the core's
    (which only grows), so a long campaign's rebuild does not hold a copy of it per question."""

    n: int
    known: int
    pending: tuple[dict[str, Any], ...]

    @staticmethod
    def of(ask: Ask) -> PlannerAsk:
        return PlannerAsk(ask.n, len(ask.history), ask.pending)


@dataclass
class Rebuilt:
    core: CampaignCore
    now: float  # the lab time of the last input (of the stop left out, if later)
    timers: dict[TimerKey, float] = field(default_factory=dict)  # pending timers: due lab time
    asked: Ask | None = None  # a question the core still waits on
    stopped: str = ""  # the stop the run ended with, left out (``unstopped``): its steps in the lab were cancelled
    planner_asks: list[PlannerAsk] = field(default_factory=list)  # the planner's questions answered, in order
    plan_asked: Ask | None = None  # the planner's question not answered yet


class ReplayError(TwinError):
    """A journal's inputs cannot be replayed: damaged, or written by another version."""


def rebuild(s: Scenario, batches: list[tuple[float, dict[str, Any]]], campaign_id: str = "c1",
            secret: bytes | None = None) -> Rebuilt:
    """Feed a recorded campaign's inputs to a new core, batch by batch; its actions are not performed again.
    ``secret``: the one the campaign's attempt tokens came from (journalled as ``attempt_secret``)."""
    out = Rebuilt(CampaignCore(s, campaign_id, secret), 0.0)
    batches, out.stopped, stopped_at = unstopped(batches)
    replay_batches(batches, lambda now, batch: _replay(out, now, batch), "input batch", "the campaign")
    out.now = max(out.now, stopped_at)  # lab time went on to the stop: the resumed clock starts there
    return out


#: the batch a resumed campaign journals first when it continues a stopped run: the stop before it was undone
RESUMED = "resumed"


def unstopped(batches: list[tuple[float, Any]], items: str = "events",
              stop: Callable[[Any], str] | None = None) -> tuple[list[tuple[float, Any]], str, float]:
    """The inputs without the stops ``twin resume`` undid: from a stop from outside (a signal's, an operator's) to
    the ``RESUMED`` batch after it, or to the end, nothing is replayed (the cancels the stop sent and what came
    back are moot: the resumed campaign asks its devices again). Also: the last stop left out with no resume after
    it ("" if none), whose steps in the lab were cancelled, and its lab time (0.0 if none). ``items``: the key of a
    batch's inputs; ``stop``: why an input stopped the run from outside, or "" (a campaign's own, by default; a
    lab's are ``lab_replay``'s)."""
    stop = stop or _stop_of
    out: list[tuple[float, Any]] = []
    stopped, stopped_at = "", 0.0
    for now, batch in batches:
        if stopped:
            if isinstance(batch, dict) and RESUMED in batch:
                stopped = ""
            continue
        inputs = batch.get(items) if isinstance(batch, dict) else None
        inputs = inputs if isinstance(inputs, list) else None  # damage: the replay names it
        why = ""
        at = next((i for i, item in enumerate(inputs or ()) if (why := stop(item))), None)
        if at is None:
            if not (isinstance(batch, dict) and RESUMED in batch):
                out.append((now, batch))
            continue
        stopped, stopped_at = why, now
        if at:
            out.append((now, {**batch, items: inputs[:at]}))
    return out, stopped, stopped_at if stopped else 0.0


def _stop_of(item: Any) -> str:
    """Why a journalled input stopped the campaign from outside (a signal's ``stop``, an operator's), or "". One
    malformed did not: the replay names it as damage."""
    if not isinstance(item, list) or not item:
        return ""
    if item[0] == "stop" and len(item) in (2, 3) and isinstance(item[1], str) and item[-1] is not False:
        return item[1]
    if item[0] == "operator" and len(item) >= 7 and item[1] == "stop":
        return operator.stop_reason(str(item[2]), str(item[6] or ""))
    return ""


def replay_batches(batches: list[tuple[float, Any]], replay: Any, what: str, who: str) -> None:
    """``replay(now, batch)`` for each batch in turn; a batch that cannot be replayed is named, with its lab time,
    instead of crashing (a damaged journal, or one from another version)."""
    for i, (now, batch) in enumerate(batches, 1):
        try:
            replay(now, batch)
        except TwinError:
            raise
        except Exception as exc:
            raise ReplayError(f"{what} {i} of {len(batches)} (lab time {now:.1f} s) cannot be replayed: "
                              f"{type(exc).__name__}: {exc}. The journal is damaged or from another version; "
                              f"run {who} again (twin run)") from None


def _replay(out: Rebuilt, now: float, batch: dict[str, Any]) -> None:
    out.now = now
    if "start" in batch:
        actions = out.core.start(now)
    else:
        for item in batch["events"]:
            event = decode_input(item)
            if type(event) is TimerFired:
                out.timers.pop(event.key, None)
            if type(event) in (Proposed, Decided):
                out.asked = None
            if type(event) is Proposed and out.plan_asked is not None:
                out.planner_asks.append(PlannerAsk.of(out.plan_asked))
                out.plan_asked = None
            out.core.feed(event)
        actions = out.core.advance(now)
    for a in actions:
        if type(a) is SetTimer:
            out.timers[a.key] = now + a.delay
        elif type(a) is CancelTimer:
            out.timers.pop(a.key, None)
        elif type(a) is Ask:
            out.asked = a
            if a.what == "plan":
                out.plan_asked = a
