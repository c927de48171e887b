"""The one versioned envelope every message travels in, JSON on the wire.

``decode`` validates the envelope and then the body for its kind; anything that
fails raises ``InvalidMessage`` naming the sender (when it can be read) and the
reason, so a receiver can log it and drop it without crashing.
"""

from __future__ import annotations

import json
from enum import StrEnum
from typing import Any, Literal

import msgspec
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from twin.core.errors import TwinError

VERSION = 1


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


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CommandBody(_Body):
    step: str
    params: dict[str, Any] = {}
    sample: dict[str, Any] | None = None
    expected_s: float = Field(ge=0)


class AcceptedBody(_Body):
    pass


class RejectedBody(_Body):
    reason: str


class ProgressBody(_Body):
    fraction: float = Field(ge=0, le=1)
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


class Envelope(BaseModel):
    model_config = ConfigDict(extra="forbid")

    v: Literal[1] = 1  # VERSION
    kind: Kind
    id: str
    campaign: str = ""
    task: str = ""
    attempt: int = Field(default=0, ge=0)
    sender: str
    t_lab: float
    body: dict[str, Any] = {}


class InvalidMessage(TwinError):
    def __init__(self, sender: str, reason: str) -> None:
        self.sender, self.reason = sender, reason
        super().__init__(f"invalid message from {sender}: {reason}")


def encode(env: Envelope) -> bytes:
    return env.model_dump_json().encode()


def envelope(kind: Kind, body: dict[str, Any], *, id: str, sender: str, t_lab: float,
             campaign: str = "", task: str = "", attempt: int = 0) -> dict[str, Any]:
    """An envelope as a plain dict, in wire order: what the fast runtime passes around in-process."""
    return {"v": VERSION, "kind": kind, "id": id, "campaign": campaign, "task": task,
            "attempt": attempt, "sender": sender, "t_lab": t_lab, "body": body}


_encode = msgspec.json.Encoder().encode


def to_wire(env: dict[str, Any]) -> bytes:
    """Compact JSON (msgspec: several times faster than ``json``; a NaN or infinity becomes null)."""
    return _encode(env)


def pack(kind: Kind, body: dict[str, Any], *, id: str, sender: str, t_lab: float,
         campaign: str = "", task: str = "", attempt: int = 0) -> bytes:
    """The wire form of an envelope, built without a model: the receiver validates."""
    return to_wire(envelope(kind, body, id=id, sender=sender, t_lab=t_lab, campaign=campaign, task=task,
                            attempt=attempt))


def decode(payload: bytes, sender_hint: str = "?") -> tuple[Envelope, _Body]:
    """Validate ``payload``; raises ``InvalidMessage`` with the sender and the reason."""
    try:
        env = Envelope.model_validate_json(payload)
    except ValidationError as exc:
        raise InvalidMessage(_sender_of(payload, sender_hint), _first_error(exc)) from None
    try:
        body = BODIES[env.kind].model_validate(env.body)
    except ValidationError as exc:
        raise InvalidMessage(env.sender, f"{env.kind} body: {_first_error(exc)}") from None
    return env, body


def _sender_of(payload: bytes, hint: str) -> str:
    try:
        data = json.loads(payload)
        return str(data.get("sender", hint)) if isinstance(data, dict) else hint
    except ValueError:
        return hint


def _first_error(exc: ValidationError) -> str:
    errs = exc.errors()
    parts = [f"{'.'.join(str(p) for p in e['loc']) or '(root)'}: {e['msg']}" for e in errs[:3]]
    more = f" (+{len(errs) - 3} more)" if len(errs) > 3 else ""
    return "; ".join(parts) + more
