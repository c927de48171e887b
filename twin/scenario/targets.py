"""Whether measured outputs meet a scenario target, and how far they are from it."""

from __future__ import annotations

from typing import Any

from twin.core.numbers import finite


def measured(x: Any) -> bool:
    """Whether an output is a number a target can be scored on (not a string, a boolean, or a NaN sent as null)."""
    return finite(x)


def score(outputs: dict[str, Any], target: Any) -> float:
    """0 when every condition of ``target`` holds; else the largest violation in tolerance units (infinite when
    an output it reads is missing or not a number)."""
    worst = 0.0
    for name, cond in target.outputs.items():
        x = outputs.get(name)
        if not measured(x):
            return float("inf")
        if cond.value is not None:
            worst = max(worst, max(0.0, abs(x - cond.value) - cond.tol) / cond.tol)
        scale = max(abs(cond.min or cond.max or 1.0) * 0.05, 1e-9)
        if cond.min is not None and x < cond.min:
            worst = max(worst, (cond.min - x) / scale)
        if cond.max is not None and x > cond.max:
            worst = max(worst, (x - cond.max) / scale)
    return worst


def scores(outputs: dict[str, Any], targets: list[Any]) -> dict[str, float]:
    return {t.name: score(outputs, t) for t in targets}


def unscorable(outputs: dict[str, Any], targets: list[Any]) -> dict[str, Any]:
    """The outputs targets read that a device sent but not as a number: name -> value (a missing one is not
    listed: some workflows do not measure everything)."""
    return {name: outputs[name] for t in targets for name in t.outputs
            if name in outputs and not measured(outputs[name])}


def missing_outputs(outputs: dict[str, Any], targets: list[Any]) -> list[str]:
    """The outputs targets read that ``outputs`` lacks altogether, each once, in the targets' order."""
    return list(dict.fromkeys(name for t in targets for name in t.outputs if name not in outputs))
