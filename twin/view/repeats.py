"""Which messages a watcher has drawn, so that it draws none twice in bounded memory."""

from __future__ import annotations

import math
from typing import Any


class Repeats:
    """A watcher hears some messages twice: in a campaign's history and live, and all of the history again when a
    lab comes back. A message is known by its id and lab time (a sender started again counts its ids from 1 again,
    at later lab times).

    Only the last ``keep`` or so messages are remembered (two generations, each closed where lab time moves on), so
    a watcher following a lab for weeks does not grow without end. A message no later than every one forgotten is
    a repeat: a history read again repeats it, and nothing live comes that late. A message stamped far off (a
    device keeping another clock) neither stops the forgetting nor makes the present count as forgotten."""

    def __init__(self, keep: int = 200_000) -> None:
        self.keep = keep
        self._recent: set[tuple[Any, float | None]] = set()
        self._older: set[tuple[Any, float | None]] = set()
        self._recent_span = (math.inf, -math.inf)  # the earliest and latest lab time in each generation
        self._older_span = (math.inf, -math.inf)
        self._last: float | None = None  # the lab time of the message before
        self.floor = -math.inf  # lab time: what is no later was forgotten, and counts as drawn

    def fresh(self, id: Any, t_lab: Any) -> bool:
        """True the first time a message is offered; False for a repeat."""
        try:
            t: float | None = float(t_lab)
        except (TypeError, ValueError):
            t = None  # no lab time: known by its id alone
        key = (id, t)
        if key in self._recent or key in self._older or (t is not None and t <= self.floor):
            return False
        if t is not None:
            if len(self._recent) >= self.keep and t != self._last:
                # forget the older generation: all of it no later than its latest, unless the one kept starts earlier
                self.floor = max(self.floor, min(self._older_span[1], self._recent_span[0]))
                self._older, self._older_span = self._recent, self._recent_span
                self._recent, self._recent_span = set(), (math.inf, -math.inf)
            low, high = self._recent_span
            self._recent_span = (min(low, t), max(high, t))
            self._last = t
        self._recent.add(key)
        return True

    def __len__(self) -> int:
        return len(self._recent) + len(self._older)
