"""Settings a user gives labtwin through the environment (``LABTWIN_…``): read where they are used, and refused,
naming the variable and its value, when they are not what they must be."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import TypeVar

from twin.core.errors import TwinError

T = TypeVar("T", int, float)


def number_setting(name: str, default: T, parse: Callable[[str], T], fits: Callable[[T], bool], wanted: str,
                   unset: str) -> T:
    """``name``'s value read by ``parse`` if it is set and ``fits``, ``default`` if it is not set; else a TwinError:
    ``NAME='value': give WANTED, or unset it for UNSET``."""
    given = os.environ.get(name)
    if given is None:
        return default
    try:
        value = parse(given)
    except ValueError:
        value = None
    if value is None or not fits(value):
        raise TwinError(f"{name}={given!r}: give {wanted}, or unset it for {unset}")
    return value
