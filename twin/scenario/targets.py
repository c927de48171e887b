"""Whether measured outputs meet a scenario target, and how far they are from it."""

from __future__ import annotations

from typing import Any


def score(outputs: dict[str, Any], target: Any) -> float:
    """0 when every condition of ``target`` holds; else the largest violation in tolerance units."""
    worst = 0.0
    for name, cond in target.outputs.items():
        x = outputs.get(name)
        if not isinstance(x, (int, float)):
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
