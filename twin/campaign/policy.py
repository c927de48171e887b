"""The orchestration policy as pure functions: deadlines, back-off, fail-over, quarantine.

Random draws come from streams keyed by what they are about (seed, task,
attempt), so a decision never depends on how events interleaved.
"""

from __future__ import annotations

import math
from typing import Any

from twin.core.streams import keyed_uniforms


def deadline_s(expected_s: float, o: Any) -> float:
    """Lab seconds an attempt may take before it is cancelled (``o``: the scenario's orchestrator)."""
    return expected_s * o.timeout_factor + o.timeout_slack_s


def may_retry(attempts: int, retrying_s: float, retry: Any) -> bool:
    """Whether a step that has used ``attempts`` and been retried for ``retrying_s`` lab-s may go again."""
    return attempts < retry.max_attempts and retrying_s < retry.max_delay_s


def retried_too_long(attempts: int, retrying_s: float, retry: Any) -> str:
    """Why a step with attempts left is not retried — its first failure or refusal was longer ago than
    ``retry.max_delay_s`` — or '' (also when its attempts are used up: its count of failures says that)."""
    if attempts >= retry.max_attempts or retrying_s < retry.max_delay_s:
        return ""
    return (f" and is not retried: it has been retried for {retrying_s / 3600:.1f} lab-h, past "
            f"orchestrator.retry.max_delay_s ({retry.max_delay_s:g} s; raise it to retry longer)")


def backoff_s(retry: Any, attempts: int, seed: int, task: str) -> float:
    """Exponential back-off with jitter, drawn from the (seed, task, attempt) stream."""
    base = min(retry.backoff_max_s, retry.backoff_s * 2 ** (attempts - 1))
    u = keyed_uniforms(f"{seed}:backoff:{task}:{attempts}")[0]
    return base * (1 + retry.jitter * (2 * u - 1))


def avoid(failed_on: list[str], usable: set[str]) -> frozenset[str]:
    """Fail over: skip the devices that failed this step while another usable instance exists."""
    if not failed_on:
        return frozenset()
    every = frozenset(failed_on)
    if usable - every:
        return every
    last = frozenset(failed_on[-1:])
    return last if usable - last else frozenset()


def should_quarantine(consecutive_failures: int, quarantine_after: int, already: bool) -> bool:
    return not already and consecutive_failures >= quarantine_after


def outside_envelope(route: Any, params: dict[str, Any], devices: dict[str, Any]) -> str:
    """Why a step of ``route`` would ask its device type for a parameter outside its safe ``envelope``
    ('' if none): such an experiment is infeasible before anything is sent."""
    for step in route:
        values = {**params, **step.params}
        for name, box in devices[step.device].envelope.items():
            v = values.get(name)
            if isinstance(v, (int, float)) and not box.low <= v <= box.high:
                return f"{name} {v:.6g} is outside devices.{step.device}.envelope.{name} [{box.low:g}, {box.high:g}]"
    return ""


def unusable_params(params: dict[str, Any], box: dict[str, Any]) -> str:
    """Why a planner's proposal cannot be sent ('' if it can): a parameter of the scenario's
    ``chemistry.parameters`` missing, not a finite number, or outside its [low, high]."""
    for name, p in box.items():
        v = params.get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return (f"{name} is missing" if name not in params else f"{name} = {str(v)[:40]!r} is not a number") + \
                f" (chemistry.parameters.{name} is a number in [{p.low:g}, {p.high:g}])"
        if not math.isfinite(v):
            return f"{name} = {v} is not a finite number (chemistry.parameters.{name} is in [{p.low:g}, {p.high:g}])"
        if not p.low <= v <= p.high:
            return f"{name} = {v:.6g} is outside chemistry.parameters.{name} [{p.low:g}, {p.high:g}]"
    return ""


def unusable_route(route: Any, devices: dict[str, Any]) -> str:
    """Why a planner's route cannot be run in this lab ('' if it can): a step on a device type the lab does not
    have, or one its type does not run."""
    for i, r in enumerate(route):
        if r.device not in devices:
            return f"route step {i}: no device type {r.device[:40]!r} in the lab (it has {', '.join(devices)})"
        if r.step not in devices[r.device].steps:
            return f"route step {i}: {r.device} runs {', '.join(devices[r.device].steps)}, not {r.step[:40]!r}"
    return ""
