"""The fast runtime's event queue: lab time and one time-ordered queue of plain callbacks.

SimPy's ``Environment`` in miniature. Callbacks due now run first-in
first-out; when none is left the owner gets its idle point, then time jumps
to the next timer's own time, and every timer due within ``RESOLUTION`` of
it runs at that instant (asyncio's rule, so both runtimes see the same
times to the bit).
"""

from __future__ import annotations

import heapq
import itertools
from collections import deque
from collections.abc import Callable
from typing import Any

from twin.core.clock import lab_seconds

RESOLUTION = 1e-6  # LabEventLoop._clock_resolution


class Timer:
    __slots__ = ("when", "fn", "args", "cancelled")

    def __init__(self, when: float, fn: Callable[..., Any], args: tuple) -> None:
        self.when, self.fn, self.args, self.cancelled = when, fn, args, False

    def cancel(self) -> None:
        self.cancelled = True


class EventQueue:
    def __init__(self) -> None:
        self.now = 0.0
        self._ready: deque[tuple[Callable[..., Any], tuple]] = deque()
        self._timers: list[tuple[float, int, Timer]] = []
        self._seq = itertools.count()

    def call_soon(self, fn: Callable[..., Any], *args: Any) -> None:
        self._ready.append((fn, args))

    def call_later(self, delay: float, fn: Callable[..., Any], *args: Any) -> Timer:
        t = Timer(self.now + max(0.0, delay), fn, args)
        heapq.heappush(self._timers, (t.when, next(self._seq), t))
        return t

    def run_ready(self) -> None:
        """Run every callback due at this instant, including those they schedule and timers set for now."""
        ready, timers = self._ready, self._timers
        while True:
            while ready:
                fn, args = ready.popleft()
                fn(*args)
            if not timers or timers[0][0] > self.now:
                return
            t = heapq.heappop(timers)[2]
            if not t.cancelled:
                ready.append((t.fn, t.args))

    def jump(self) -> bool:
        """Move to the next timer's time and queue what is due; False when no timer is left."""
        timers = self._timers
        while timers and timers[0][2].cancelled:
            heapq.heappop(timers)
        if not timers:
            return False
        self.now = max(self.now, timers[0][0])
        end = self.now + RESOLUTION
        while timers and timers[0][0] < end:
            t = heapq.heappop(timers)[2]
            if not t.cancelled:
                self._ready.append((t.fn, t.args))
        return True


class Sleep:
    """What ``await clock.sleep(s)`` yields to the fast runtime's driver loop."""

    __slots__ = ("seconds",)

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def __await__(self):
        yield self


class Park:
    """Awaited by a hung step: only a cancel ends it."""

    def __await__(self):
        yield self


class QueueClock:
    """The ``Clock`` drivers see in the fast runtime: lab time from the queue, sleeps as requests."""

    mode = "virtual"
    is_virtual = True

    def __init__(self, queue: EventQueue) -> None:
        self._q = queue
        self.made = 0  # sleeps asked for; the driver loop counts those awaited (one never awaited waited no time)

    def now(self) -> float:
        return self._q.now

    def sleep(self, seconds: float) -> Sleep:
        self.made += 1
        return Sleep(lab_seconds(seconds))

    def sleep_until(self, t_lab: float) -> Sleep:
        self.made += 1
        return Sleep(lab_seconds(t_lab, "sleep_until") - self._q.now)

    def timeout(self, seconds: float | None) -> Any:
        from twin.core.errors import ClockError

        raise ClockError("clock.timeout() is not available in the fast runtime: a driver takes no timeouts "
                         "(the orchestrator owns them); run with --runtime asyncio if it must")
