"""The one versioned envelope every message travels in, JSON on the wire.

Envelopes and bodies are msgspec Structs: decoding validates as it parses
(several times faster than pydantic + json, which stay for scenario files).
``decode`` validates the envelope and then the body for its kind; anything
that fails raises ``InvalidMessage`` naming the sender (when it can be read)
and the reason, so a receiver can log it and drop it without crashing.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from enum import StrEnum
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta, Struct

from twin.core import log_floods
from twin.core.errors import TwinError

VERSION = 1
#: The largest message accepted, checked before any decoding (a spectrum is ~3 KB).
MAX_MESSAGE_BYTES = 1 << 20


class Kind(StrEnum):
    COMMAND = "command"
    ACCEPTED = "accepted"
    REJECTED = "rejected"
    PROGRESS = "progress"
    RESULT = "result"
    FAULT = "fault"
    CANCEL = "cancel"
    TELEMETRY = "telemetry"
    DECISION = "decision"


class _Body(Struct, forbid_unknown_fields=True):
    def to_dict(self) -> dict[str, Any]:
        return {f: getattr(self, f) for f in self.__struct_fields__}


class CommandBody(_Body):
    step: str
    expected_s: Annotated[float, Meta(ge=0)]
    params: dict[str, Any] = {}
    sample: dict[str, Any] | None = None
    deadline_s: Annotated[float, Meta(ge=0)] | None = None  # lab seconds from dispatch until the lab gives up


class AcceptedBody(_Body):
    pass


class RejectedBody(_Body):
    reason: str
    infeasible: bool = False  # never with these parameters (else: only now)
    began: bool = False  # the step had begun: what it used stays used (else: it is given back)


class ProgressBody(_Body):
    fraction: Annotated[float, Meta(ge=0, le=1)]
    note: str = ""


class ResultBody(_Body):
    outputs: dict[str, Any] = {}
    sample: dict[str, Any] | None = None


class FaultBody(_Body):
    code: str  # failed | hung | cancelled | crashed | driver_error | timed_out | device_lost
    reason: str


class CancelBody(_Body):
    reason: str


class TelemetryBody(_Body):
    readings: dict[str, float]


class DecisionBody(_Body):
    what: str
    detail: dict[str, Any] = {}


BODIES: dict[Kind, type[_Body]] = {
    Kind.COMMAND: CommandBody,
    Kind.ACCEPTED: AcceptedBody,
    Kind.REJECTED: RejectedBody,
    Kind.PROGRESS: ProgressBody,
    Kind.RESULT: ResultBody,
    Kind.FAULT: FaultBody,
    Kind.CANCEL: CancelBody,
    Kind.TELEMETRY: TelemetryBody,
    Kind.DECISION: DecisionBody,
}


class Envelope(Struct, forbid_unknown_fields=True, kw_only=True):
    v: Literal[1] = 1  # VERSION
    kind: Kind
    id: str
    campaign: str = ""
    task: str = ""
    attempt: Annotated[int, Meta(ge=0)] = 0
    sender: str
    t_lab: float
    body: dict[str, Any] = {}
    token: str = ""  # the attempt's token: put in a command by the orchestrator, echoed by the device


class _Sender(Struct):
    sender: Any = None


#: How a device's "busy" ends while its driver's safe_state() runs after a step (the lab's advice differs)
SAFING = ": its safe_state() has not returned"


class InvalidMessage(TwinError):
    def __init__(self, sender: str, reason: str) -> None:
        self.sender, self.reason = sender, reason
        super().__init__(f"invalid message from {sender}: {reason}")


class Dropped:
    """Messages that failed the wire's checks, said as a receiver says them: the first ten, then every thousandth
    (a flood of them must not flood the log too)."""

    def __init__(self, log: Any) -> None:
        """``log``: the receiver's logger (a bench quietens its workers' runtimes by theirs)."""
        self.log, self.count = log, 0

    def said(self, where: str, exc: InvalidMessage) -> None:
        self.count += 1
        if log_floods.said(self.count):
            self.log.warning("dropped a message %s: %s (%d so far; the journal has the first 1,000, then one row in 1,000)", where, exc, self.count)


def envelope(kind: Kind, body: dict[str, Any], *, id: str, sender: str, t_lab: float,
             campaign: str = "", task: str = "", attempt: int = 0, token: str = "") -> dict[str, Any]:
    """An envelope as a plain dict, in wire order: what the fast runtime passes around in-process.

    The token is left out when empty: what the journal keeps of a message never holds it."""
    env = {"v": VERSION, "kind": kind, "id": id, "campaign": campaign, "task": task,
           "attempt": attempt, "sender": sender, "t_lab": t_lab, "body": body}
    if token:
        env["token"] = token
    return env


def plain_value(obj: Any) -> Any:
    """What msgspec cannot encode by itself: numpy scalars and arrays (a driver's outputs often are)."""
    item, tolist = getattr(obj, "item", None), getattr(obj, "tolist", None)
    if tolist is not None and callable(tolist):
        return tolist()
    if item is not None and callable(item):
        return item()
    if obj is None or isinstance(obj, bool):  # values msgspec writes itself: here only as a mapping's key
        raise TypeError(f"cannot send a mapping whose key is {obj!r} in a message: keys are text (or numbers, "
                        "written as text)")
    raise TypeError(f"cannot send an object of type {type(obj).__name__} in a message: use numbers, strings, "
                    "lists and dicts")


_encode = msgspec.json.Encoder(enc_hook=plain_value).encode
_decode_envelope = msgspec.json.Decoder(Envelope).decode
_decode_sender = msgspec.json.Decoder(_Sender).decode


def to_wire(env: dict[str, Any]) -> bytes:
    """Compact JSON (msgspec: several times faster than ``json``; a NaN or infinity becomes null)."""
    return _encode(env)


def pack(kind: Kind, body: dict[str, Any], *, id: str, sender: str, t_lab: float,
         campaign: str = "", task: str = "", attempt: int = 0, token: str = "") -> bytes:
    """The wire form of an envelope, built without a model: the receiver validates."""
    return to_wire(envelope(kind, body, id=id, sender=sender, t_lab=t_lab, campaign=campaign, task=task,
                            attempt=attempt, token=token))


class TooLarge(ValueError):
    """A device's message over ``MAX_MESSAGE_BYTES``, refused where it is made: its step fails with this reason
    at once, rather than every receiver dropping the message and the step waiting out its deadline."""


def within_limit(kind: Kind, payload: bytes) -> bytes:
    if len(payload) > MAX_MESSAGE_BYTES:
        raise TooLarge(f"the {kind} message would be {len(payload):,} bytes, over the {MAX_MESSAGE_BYTES:,} of one "
                       "message: send less (a summary of the data, or the data in a file and its path as an output)")
    return payload


def without_token(env: Envelope) -> bytes:
    """The wire form of a received envelope less its token: what a journal keeps (tokens are secrets)."""
    return to_wire(envelope(env.kind, env.body, id=env.id, sender=env.sender, t_lab=env.t_lab,
                            campaign=env.campaign, task=env.task, attempt=env.attempt))


def kept(env: Envelope, payload: bytes) -> bytes:
    """A received message as a journal keeps it: less its token, if it carries one; else as it came."""
    return without_token(env) if env.token else payload


def fingerprint(kept_payload: bytes) -> str:
    """How the decisions stream names a result its campaign accepted (``accepted``), from the message as kept: a
    watcher in another process, which cannot tell tokens, draws a result it heard only once it is named."""
    return hashlib.blake2b(kept_payload, digest_size=8).hexdigest()


def decode(payload: bytes, sender_hint: str = "?") -> tuple[Envelope, _Body]:
    """Validate ``payload``; raises ``InvalidMessage`` with the sender and the reason."""
    if len(payload) > MAX_MESSAGE_BYTES:
        raise InvalidMessage(sender_hint, f"{len(payload):,} bytes, over the limit of {MAX_MESSAGE_BYTES:,}: "
                                          "not decoded, not journalled")
    try:
        env = _decode_envelope(payload)
    except msgspec.DecodeError as exc:
        raise InvalidMessage(_sender_of(payload, sender_hint), _reason(exc)) from None
    except RecursionError:
        raise InvalidMessage(sender_hint, "JSON nested too deep") from None
    except UnicodeDecodeError as exc:  # msgspec checks UTF-8 only where it builds a str
        raise InvalidMessage(sender_hint, f"not UTF-8 at byte {exc.start}") from None
    try:
        body = msgspec.convert(env.body, BODIES[env.kind])
    except msgspec.ValidationError as exc:
        raise InvalidMessage(env.sender, f"{env.kind} body: {_named(_reason(exc), env.body)}") from None
    return env, body


def json_from_wire(payload: bytes | str) -> Any:
    """JSON from another process (a reply, a request, a report); whatever cannot be read raises ``ValueError`` —
    JSON nested deeper than Python recurses too, which ``json.loads`` raises as ``RecursionError`` (a reply of
    100,000 ``[`` from a scheduler agent failed the lab's decision instead of being overruled)."""
    try:
        return json.loads(payload)
    except RecursionError:
        raise ValueError("JSON nested too deep") from None


def _named(reason: str, body: Any) -> str:
    """``reason`` with the reading it is about named (msgspec says ``readings[...]`` of a mapping's value), and a
    progress given as a percentage said to be one."""
    if reason.startswith("fraction: Expected `float` <= 1.0"):
        return reason + " (a fraction of the step, 0 to 1: not a percentage)"
    readings = body.get("readings") if isinstance(body, dict) else None
    if not reason.startswith("readings[...]") or not isinstance(readings, dict):
        return reason
    bad = next((k for k, v in readings.items()
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)), None)
    return reason if bad is None else f"readings[{str(bad)[:64]!r}]" + reason[len("readings[...]"):]


def excerpt(payload: bytes, limit: int = 200) -> str:
    """The start of a payload as text, for a journal row about a message that was refused."""
    text = payload[:limit].decode("utf-8", errors="replace")
    return text + f"… ({len(payload):,} bytes)" if len(payload) > limit else text


def _sender_of(payload: bytes, hint: str) -> str:
    try:
        sender = _decode_sender(payload).sender
    except (msgspec.DecodeError, TypeError, RecursionError, UnicodeDecodeError):
        return hint
    return str(sender) if sender is not None else hint


_MISSING = re.compile(r"Object missing required field `(\w+)`(?: - at `\$\.?(.*)`)?")
_AT = re.compile(r"(.*) - at `\$\.?(.*)`")


def _reason(exc: Exception) -> str:
    """msgspec's message as 'field.path: problem'."""
    text = str(exc)
    m = _MISSING.fullmatch(text)
    if m:
        return f"{'.'.join(p for p in (m.group(2), m.group(1)) if p)}: Field required"
    m = _AT.fullmatch(text)
    if m:
        return f"{m.group(2) or '(root)'}: {m.group(1)}"
    return text
