"""A count said with the noun its number takes: 1 device loss, 2 device losses; 1 vial, 2 vials."""

from __future__ import annotations

from typing import Any


def counted(n: Any, one: str, many: str) -> str:
    """``n`` and the noun for it (anything but 1 takes ``many``)."""
    return f"{n} {one if n == 1 else many}"


def quantity(value: float, unit: str) -> str:
    """``value`` in ``unit``, where a unit written as a plural of letters ("vials", "boxes") takes its singular
    for exactly 1: 1 vial, 2 vials, 1 box, 1 mL, 0.5 L."""
    return f"{value:g} {singular(unit) if value == 1 else unit}".rstrip()


def singular(unit: str) -> str:
    if len(unit) < 3 or not (unit.isalpha() and unit.islower()) or not unit.endswith("s") or unit.endswith("ss"):
        return unit
    return unit[:-2] if unit.endswith(("xes", "ches", "shes", "sses")) else unit[:-1]
