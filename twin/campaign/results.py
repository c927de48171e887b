"""Whether a device's result can be used: its outputs an object, its sample an object made at a lab time.

A result that fails this came from the device itself (provenance vouched for it), so it is the driver's
fault: the attempt fails as ``driver_error`` with the reason, and is retried as any other failure.
"""

from __future__ import annotations

from typing import Any

from twin.core.numbers import finite


#: How far after the lab's time a sample may say it was made (lab seconds): processes' clocks agree only so far.
FUTURE_SLACK_S = 60.0


def problem(body: dict[str, Any], now: float) -> str:
    """Why the lab cannot use this result, received at lab time ``now`` ('' when it can)."""
    outputs, sample = body.get("outputs", {}), body.get("sample")
    if not isinstance(outputs, dict):
        return f"its outputs must be a JSON object, not {type(outputs).__name__}"
    if sample is None:
        return ""
    if not isinstance(sample, dict):
        return f"its sample must be a JSON object or null, not {type(sample).__name__}"
    made = sample.get("t_made", 0.0)
    if not finite(made):
        return (f"its sample's t_made must be the lab time it was made, in seconds (ctx.clock.now()), "
                f"not {str(made)[:40]!r}")
    if made > now + FUTURE_SLACK_S:
        return f"its sample's t_made ({made:.6g} s) is after the lab's time now ({now:.1f} s): use ctx.clock.now()"
    return ""
