"""The MQTT instrument protocol's payloads (docs/mqtt.md): what the adapter sends, and what it accepts back.

Every check here names what is wrong, because the reason becomes the fault the
lab journals when an instrument says something it should not.
"""

from __future__ import annotations

import json
import math
from typing import Any

VERSION = 1
#: the topics under an instrument's prefix, and whether the instrument retains them
TOPICS = {"command": False, "result": False, "status": True, "progress": False, "telemetry": False, "health": True}
MAX_PAYLOAD = 1 << 20


class InvalidPayload(ValueError):
    """An instrument's message does not follow docs/mqtt.md."""


def command(job: str, step: str, params: dict[str, Any], sample: dict | None, *, expected_s: float,
            deadline_s: float | None, speed: float, t_lab: float) -> str:
    """A run command: ``id`` first and ``sample`` last, on one line, so a line-oriented instrument (a shell
    script, say) can pick them apart without a JSON parser."""
    return json.dumps({"id": job, "v": VERSION, "step": step, "params": params, "expected_s": round(expected_s, 3),
                       "deadline_s": None if deadline_s is None else round(deadline_s, 3), "speed": speed,
                       "t_lab": round(t_lab, 3), "sample": sample}, separators=(", ", ": "))


def cancel(job: str) -> str:
    return json.dumps({"id": job, "cancel": True})


def ping(job: str) -> str:
    return json.dumps({"id": job, "ping": True})


def parse(payload: bytes | str) -> dict[str, Any]:
    """A JSON object from an instrument, or :class:`InvalidPayload`."""
    if len(payload) > MAX_PAYLOAD:
        raise InvalidPayload(f"{len(payload)} bytes, over the {MAX_PAYLOAD}-byte limit")
    try:
        data = json.loads(payload)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise InvalidPayload(f"not JSON ({str(exc)[:80]}): {_excerpt(payload)}") from None
    if not isinstance(data, dict):
        raise InvalidPayload(f"not a JSON object: {_excerpt(payload)}")
    return data


def job_of(data: dict[str, Any]) -> str:
    job = data.get("id")
    if not isinstance(job, str) or not job:
        raise InvalidPayload(f"no \"id\" (the command's id, a string): {_excerpt(json.dumps(data))}")
    return job


def result_kind(data: dict[str, Any]) -> str:
    """Which final answer a result is: ``done``, ``error``, ``refused`` or ``cancelled``; checked."""
    kinds = [k for k in ("outputs", "error", "refused", "cancelled") if k in data]
    if len(kinds) != 1:
        raise InvalidPayload("a result holds exactly one of \"outputs\", \"error\", \"refused\" or \"cancelled\", "
                             f"not {kinds or 'none'}")
    kind = kinds[0]
    if kind == "outputs":
        if not isinstance(data["outputs"], dict):
            raise InvalidPayload("\"outputs\" is not an object")
        if "sample" not in data:
            raise InvalidPayload("a result with \"outputs\" must also hand back \"sample\" (the sample after the "
                                 "step: the one it was sent, if the step did not change it)")
        if data["sample"] is not None and not isinstance(data["sample"], dict):
            raise InvalidPayload("\"sample\" is neither an object nor null")
        return "done"
    if kind in ("error", "refused") and not isinstance(data[kind], str):
        raise InvalidPayload(f"\"{kind}\" is not a string (the reason)")
    if kind == "refused" and not isinstance(data.get("infeasible", False), bool):
        raise InvalidPayload("\"infeasible\" is not true or false")
    return kind


def progress(data: dict[str, Any]) -> tuple[float, str]:
    f = data.get("fraction")
    if isinstance(f, bool) or not isinstance(f, int | float) or not 0 <= f <= 1:
        raise InvalidPayload("\"fraction\" is not a number from 0 to 1")
    return float(f), str(data.get("note", ""))[:200]


def readings(data: dict[str, Any]) -> dict[str, float]:
    r = data.get("readings")
    if not isinstance(r, dict) or not r:
        raise InvalidPayload("\"readings\" is not a non-empty object")
    out = {}
    for name, value in r.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InvalidPayload(f"reading {str(name)[:40]!r} is not a finite number")
        out[str(name)[:64]] = float(value)
    return out


def _excerpt(payload: bytes | str) -> str:
    text = payload.decode(errors="replace") if isinstance(payload, bytes) else payload
    return repr(text[:120])
