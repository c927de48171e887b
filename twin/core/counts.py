"""A count said with the noun its number takes: 1 device loss, 2 device losses."""

from __future__ import annotations

from typing import Any


def counted(n: Any, one: str, many: str) -> str:
    """``n`` and the noun for it (anything but 1 takes ``many``)."""
    return f"{n} {one if n == 1 else many}"
