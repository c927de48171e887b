"""A scheduler whose decisions take wall time, asked off the event loop on a scaled or wall clock.

There, wall time is lab time: a CP-SAT solve of 0.3 s on the loop is 1,080 lab-s at 3600× in which no device
is heard, and healthy devices time out. A scheduler that says ``runs_long = True`` (CP-SAT), or one whose
decision once took longer than ``ON_LOOP_LIMIT_S`` on the loop, is asked in a worker thread from then on, with
the deadline ``campaign.scheduler_deadline_ms``; when it is late (or still busy with the last question) the
fallback rule decides that time, the reason is noted once per change, and its late answer is dropped (it was
about a lab that has moved on). A thread, not a process: ``bench/bench_offload.py`` measured the loop's worst
stall at ~5 ms in a worker thread for CP-SAT, GP-BO and pure-Python decisions alike (the GIL's switch
interval), against 150–310 ms on the loop, and a thread shares the scheduler's state.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
from typing import Any

from twin.campaign.decisions import Assignment, LabView
from twin.runtime.remote_scheduler import Fallback

log = logging.getLogger(__name__)

#: A decision slower than this on the loop (wall seconds) moves the scheduler to the worker thread.
ON_LOOP_LIMIT_S = 0.005


class OffLoopScheduler:
    def __init__(self, inner: Any, fallback: Fallback, deadline_s: float) -> None:
        """``deadline_s``: lab seconds a decision in the worker may take."""
        self.inner, self.fallback, self.deadline_s = inner, fallback, deadline_s
        self.offloaded = bool(getattr(inner, "runs_long", False))
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="labtwin-scheduler")
        self._busy: asyncio.Future | None = None

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

    def decide(self, view: LabView):
        if self.offloaded:
            return self._in_worker(view)
        started = time.perf_counter()
        decided = self.inner.decide(view)
        took = time.perf_counter() - started
        if took > ON_LOOP_LIMIT_S:
            self.offloaded = True
            log.info("the scheduler took %.0f ms of wall time on the event loop; it decides in a worker thread "
                     "from now on", took * 1000)
        return decided

    async def _in_worker(self, view: LabView) -> list[Assignment]:
        if self._busy is not None:
            return self.fallback.decide(view, "busy", "the scheduler is still deciding an earlier question")
        fut = asyncio.get_running_loop().run_in_executor(self._pool, self.inner.decide, view)
        done, _ = await asyncio.wait({fut}, timeout=self.deadline_s)
        if not done:
            self._busy = fut
            fut.add_done_callback(self._late_answer)
            return self.fallback.decide(view, "late", f"the scheduler did not decide within {self.deadline_s:g} lab-s")
        self.fallback.recovered("the scheduler decides in time again")
        return list(fut.result())

    def _late_answer(self, fut: asyncio.Future) -> None:
        self._busy = None
        if not fut.cancelled() and fut.exception() is not None:
            log.error("the scheduler failed on a question it answered late: %r", fut.exception())
