"""Asking a scheduler one question: its answer may come at once or as an awaitable (an agent on the bus)."""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Callable
from typing import Any

from twin.campaign import Ask, Decided


def ask_scheduler(scheduler: Any, ask: Ask, answer: Callable[[Decided, bool], None],
                  fail: Callable[[BaseException], None]) -> asyncio.Future | None:
    """Ask ``scheduler`` the question: ``answer(decided, later)`` gets its answer — at once, or (``later``) when
    an awaitable answer resolves — and ``fail(exc)`` its error. Returns the pending answer's future (cancel it to
    drop the answer), or None."""
    started = time.perf_counter()
    decided = scheduler.decide(ask.view)
    if not inspect.isawaitable(decided):
        answer(Decided(list(decided), time.perf_counter() - started), False)
        return None
    pending = asyncio.ensure_future(decided)

    def answered(fut: asyncio.Future) -> None:
        if fut.cancelled():
            return
        if fut.exception() is not None:
            fail(fut.exception())
        else:
            answer(Decided(list(fut.result()), time.perf_counter() - started), True)

    pending.add_done_callback(answered)
    return pending
