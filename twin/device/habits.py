"""A driver's habits that hurt the lab, said once per device on either runtime.

- **Blocking.** A ``run`` that calls something blocking — ``time.sleep``, a vendor SDK's synchronous call — holds
  the process between two of its awaits: every other device, the orchestrator's deadlines and the bus wait
  meanwhile, and on a virtual clock no lab time passes for it. The runtimes time each stretch a driver runs
  between awaits and warn when one passes ``BLOCKING_S`` of wall time.
- **Holding.** A blocking call that does not return holds the lab for good, and the warning above would never come:
  each stretch is run as ``twin.core.held`` holding, which says it while it lasts and lets Ctrl-C end it.
- **Chatter.** Telemetry or progress reported in a loop that does not wait: every report is a message and a
  journal row (100,000 readings in a step made a 97 MB journal for three experiments). The runtimes warn when
  ``SAME_INSTANT`` reports come at one lab instant.
- **A sleep not awaited.** ``ctx.clock.sleep(s)`` without ``await`` waits nothing: the step takes no lab time, and
  on a virtual clock nothing else says so. The fast runtime counts the sleeps a step asked for against those it
  awaited (on the asyncio runtime Python itself warns of a coroutine never awaited).
"""

from __future__ import annotations

import logging
import time
import types
from collections.abc import Awaitable, Generator
from typing import Any

from twin.core import held

log = logging.getLogger(__name__)
BLOCKING_S = 2.0  # wall seconds between two awaits: past this a driver is said to block the lab
SAME_INSTANT = 100  # telemetry or progress reports at one lab instant: past this a driver reports in a loop
DRIVER_ADVICE = ("A call to the instrument needs a timeout, and a blocking one a thread: `await "
                 "asyncio.to_thread(call)` (docs/drivers.md)")


class Habits:
    def __init__(self, device: str) -> None:
        self.device = device
        self.blocking_s = BLOCKING_S
        self.holder = held.Holder(f"{device}'s driver", DRIVER_ADVICE)  # said blocking: once per device
        held.watch()
        self._chatter_said = False
        self._unawaited_said = False
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

    def sleep_not_awaited(self, step: str) -> None:
        """The driver asked the clock for a sleep during ``step`` and never awaited it: it waited no lab time."""
        if not self._unawaited_said:
            self._unawaited_said = True
            log.warning("%s: its driver called ctx.clock.sleep(...) during %s and did not await it, so the step "
                        "waited no lab time for it: write `await ctx.clock.sleep(...)` (docs/drivers.md); said once "
                        "per device", self.device, step)

    def ran(self, since: float) -> None:
        """A driver's stretch that began at ``since`` (``time.perf_counter``) has ended."""
        took = time.perf_counter() - since
        if took > self.blocking_s and not self.holder.said:
            self.holder.said = True
            log.warning("%s: its driver ran %.1f s of wall time without awaiting (a blocking call: time.sleep, a "
                        "vendor SDK?); every other device and the orchestrator waited meanwhile. Wait for the "
                        "instrument with `await ctx.clock.sleep(...)` and run a blocking call in a thread, `await "
                        "asyncio.to_thread(call)` (docs/drivers.md); said once per device", self.device, took)


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
            held.holding(watch.holder, since)
            asked = inner.send(sent) if thrown is None else inner.throw(thrown)
        except StopIteration as done:
            watch.ran(since)
            return done.value
        finally:
            held.released()
        watch.ran(since)
        sent, thrown = None, None
        try:
            sent = yield asked
        except GeneratorExit:
            inner.close()
            raise
        except BaseException as exc:  # a cancel (CancelledError) thrown in at the await: passed on to the driver
            thrown = exc
