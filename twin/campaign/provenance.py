"""Whether a device's message can be that device's word on the attempt it names.

A message counts only if it arrived on the key of the device the attempt was
dispatched to, names that device, and carries the attempt's token — an HMAC
of the run's secret, put in the command by the orchestrator and echoed by
the device. Anything else is rejected with the reason (docs/security.md).
"""

from __future__ import annotations

import hmac
from typing import Any

from twin.campaign.events import DeviceMessage
from twin.campaign.ledger import Attempt
from twin.core import keys
from twin.core.messages import Kind


def attempt_token(secret: bytes, campaign_id: str, task: str, attempt: int) -> str:
    """Unguessable without the secret, the same for the same secret (a resumed campaign's)."""
    return hmac.digest(secret, f"{campaign_id}|{task}|{attempt}".encode(), "sha256")[:16].hex()


def problem(m: DeviceMessage, att: Attempt | None, devices: dict[str, Any]) -> str:
    """Why ``m`` cannot be the device's word on the attempt it names ('' when it can)."""
    if m.key and m.key != m.device:
        return f"signed {m.device!r} but arrived on {m.key!r}'s key: a device speaks only on its own key"
    if m.device not in devices:
        return f"{m.device!r} is not a device of this lab"
    if m.kind == Kind.TELEMETRY:
        return ""
    if att is None:
        return f"no attempt {m.task}#{m.attempt} was dispatched"
    if att.device != m.device:
        return f"{m.task}#{m.attempt} was dispatched to {att.device}, not {m.device}"
    if not hmac.compare_digest(m.token, att.token):
        return f"{'no' if not m.token else 'a wrong'} attempt token (the command's token must be echoed)"
    if m.kind == Kind.RESULT:
        sample, mine = m.body.get("sample"), att.task.experiment.sample
        if isinstance(sample, dict) and mine is not None and sample.get("id", mine["id"]) != mine["id"]:
            return f"its sample {str(sample.get('id'))[:40]!r} is not the one it was given ({mine['id']!r})"
    return ""


def rejection(m: DeviceMessage, why: str, lab: str) -> dict[str, Any]:
    """The ``message.rejected`` row's detail: where it came from, who it claimed to be, why, how it began."""
    payload = m.payload if isinstance(m.payload, (bytes, str)) else repr(m.payload)
    excerpt = (payload.decode(errors="replace") if isinstance(payload, bytes) else payload)[:200]
    key = (keys.telemetry if m.kind == Kind.TELEMETRY else keys.evt)(lab, m.key or m.device)
    return {"key": key, "sender": m.device, "kind": str(m.kind), "task": m.task, "attempt": m.attempt,
            "reason": why, "excerpt": excerpt}
