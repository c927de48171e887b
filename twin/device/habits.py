"""A driver's habits that hurt the lab, said once per device on either runtime.

- **Blocking.** A ``run`` that calls something blocking — ``time.sleep``, a vendor SDK's synchronous call — holds
  the process between two of its awaits: every other device, the orchestrator's deadlines and the bus wait
  meanwhile, and on a virtual clock no lab time passes for it. The runtimes time each stretch a driver runs
  between awaits and warn when one passes ``BLOCKING_S`` of wall time.
- **Holding.** A blocking call that does not return (a vendor SDK waiting on a socket without a timeout, a loop
  that never awaits) holds the lab for good, and the warning above would never come. One daemon thread per
  process looks at which driver is running every second, and when one has held the process past ``HELD_S`` of wall
  time, says so while it still does: the device, where its code is, and what to do.
- **Chatter.** Telemetry or progress reported in a loop that does not wait: every report is a message and a
  journal row (100,000 readings in a step made a 97 MB journal for three experiments). The runtimes warn when
  ``SAME_INSTANT`` reports come at one lab instant.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
import types
from collections.abc import Awaitable, Generator
from typing import Any

log = logging.getLogger(__name__)
BLOCKING_S = 2.0  # wall seconds between two awaits: past this a driver is said to block the lab
SAME_INSTANT = 100  # telemetry or progress reports at one lab instant: past this a driver reports in a loop
HELD_S = 30.0  # wall seconds a driver may hold the process before the log says so while it still does
_TWIN = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # a frame in here is the lab's, not the driver's

#: the driver running now, as (its Habits, since when (time.perf_counter), its thread), or None: set around each
#: stretch it runs, read by the watcher thread
held: tuple[Habits, float, int] | None = None
_watcher: threading.Thread | None = None


class Habits:
    def __init__(self, device: str) -> None:
        self.device = device
        self.blocking_s = BLOCKING_S
        _watch()
        self._blocking_said = False
        self._chatter_said = False
        self._instant: float | None = None
        self._readings = 0

    def reported(self, t_lab: float, what: str) -> None:
        """A telemetry reading or a progress report (``what``) at lab time ``t_lab``."""
        if t_lab != self._instant:
            self._instant, self._readings = t_lab, 0
        self._readings += 1
        if self._readings == SAME_INSTANT and not self._chatter_said:
            self._chatter_said = True
            log.warning("%s: its driver made %d reports at one lab instant (lab time %.0f s; the last by "
                        "ctx.%s), in a loop that does not wait; each is a message and a journal row: report "
                        "between awaits of ctx.clock.sleep, every few lab-seconds (docs/drivers.md); said once per "
                        "device", self.device, SAME_INSTANT, t_lab, what)

    def ran(self, since: float) -> None:
        """A driver's stretch that began at ``since`` (``time.perf_counter``) has ended."""
        took = time.perf_counter() - since
        if took > self.blocking_s and not self._blocking_said:
            self._blocking_said = True
            log.warning("%s: its driver ran %.1f s of wall time without awaiting (a blocking call: time.sleep, a "
                        "vendor SDK?); every other device and the orchestrator waited meanwhile. Wait for the "
                        "instrument with `await ctx.clock.sleep(...)` and run a blocking call in a thread, `await "
                        "asyncio.to_thread(call)` (docs/drivers.md); said once per device", self.device, took)


class Interrupted(Exception):
    """Raised inside a driver's call by SIGINT or SIGTERM while it holds the lab: the lab is stopping, and only an
    exception ends a call that does not return (its step fails as the driver's error)."""


def interrupt_held(why: str) -> None:
    """Called by a signal handler: if a driver holds this thread, end its call with ``Interrupted``."""
    now = held
    if now is not None and now[2] == threading.get_ident():
        raise Interrupted(f"{why} while {now[0].device}'s driver held the lab for {time.perf_counter() - now[1]:.0f} "
                          "s of wall time without awaiting")


def holding(watch: Habits, since: float) -> None:
    """``watch``'s driver runs from ``since`` until ``released``."""
    global held
    held = (watch, since, threading.get_ident())


def released() -> None:
    global held
    held = None


def _watch() -> None:
    """Start the one watcher thread of this process, if it is not running."""
    global _watcher
    if _watcher is None or not _watcher.is_alive():
        _watcher = threading.Thread(target=_watching, name="labtwin-driver-watch", daemon=True)
        _watcher.start()


def _watching() -> None:
    said = None
    while True:
        time.sleep(min(1.0, HELD_S / 4))
        now = held
        if now is None or now is said or time.perf_counter() - now[1] < HELD_S:
            continue
        said = now
        watch, since, thread = now
        watch._blocking_said = True  # this says more than the warning at the stretch's end would
        log.warning("%s: its driver has held the lab for %.0f s of wall time without awaiting, at %s; nothing else "
                    "runs until it returns (no device, no deadline, no message). A call to the instrument needs a "
                    "timeout, and a blocking one a thread: `await asyncio.to_thread(call)` (docs/drivers.md). "
                    "Ctrl-C ends the call (an exception in the driver) and stops the lab; its journal keeps every "
                    "experiment (`twin run --resume JOURNAL`)",
                    watch.device, time.perf_counter() - since, _where(thread))


def _where(thread: int) -> str:
    """The innermost line of ``thread``'s stack outside labtwin and the standard library: the driver's."""
    frame = sys._current_frames().get(thread)
    first = None
    while frame is not None:
        name = frame.f_code.co_filename
        if first is None:
            first = frame
        if not name.startswith((_TWIN, os.path.dirname(os.__file__))):
            return f"{name}:{frame.f_lineno} in {frame.f_code.co_name}"
        frame = frame.f_back
    return f"{first.f_code.co_filename}:{first.f_lineno}" if first is not None else "an unknown line"


@types.coroutine
def timed(step: Awaitable[Any], watch: Habits) -> Generator[Any, Any, Any]:
    """``step`` awaited as it is, each stretch between its awaits timed for ``watch``; a cancel goes in as it
    would."""
    inner = step.__await__()
    sent: Any = None
    thrown: BaseException | None = None
    while True:
        since = time.perf_counter()
        try:
            holding(watch, since)
            asked = inner.send(sent) if thrown is None else inner.throw(thrown)
        except StopIteration as done:
            watch.ran(since)
            return done.value
        finally:
            released()
        watch.ran(since)
        sent, thrown = None, None
        try:
            sent = yield asked
        except GeneratorExit:
            inner.close()
            raise
        except BaseException as exc:  # a cancel (CancelledError) thrown in at the await: passed on to the driver
            thrown = exc
