"""Tasks started and not awaited where they start: kept in a set until they end, since the event loop holds only a
weak reference to a task, and one that nothing else refers to may be collected while it waits ("Task was destroyed
but it is pending!")."""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any


def kept(tasks: set[asyncio.Task], coro: Coroutine[Any, Any, Any]) -> asyncio.Task:
    """``coro`` as a task of the running loop, in ``tasks`` until it ends."""
    task = asyncio.ensure_future(coro)
    tasks.add(task)
    task.add_done_callback(tasks.discard)
    return task
