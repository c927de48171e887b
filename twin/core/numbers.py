"""What counts as a number that came from outside (a device, a planner, the wire)."""

from __future__ import annotations

import math
from typing import Any


def finite(x: Any) -> bool:
    """A finite int or float, and not a boolean (``True`` is an int to Python, not a measurement)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
