"""Progress on stderr: rich's live bar on a terminal; on a pipe or a log file, where a live bar shows nothing until
it ends, a plain line when work starts, every ``every_s`` seconds (or a sixth of the time so far, if longer) while
it moves, and when it ends. A move with no update after it (two runs done quickly, then one that takes minutes) is
said when it is due, by a timer, not when the next update comes."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

from rich.console import Console
from rich.text import Text

from twin.core.environment import number_setting

PLAIN_EVERY_S = 10.0


def plain_every_s() -> float:
    """Seconds between progress lines off a terminal: ``LABTWIN_PROGRESS_S`` if set (a script that acts on the
    first line of progress need not wait 10 s for it), else 10."""
    return number_setting("LABTWIN_PROGRESS_S", PLAIN_EVERY_S, float, lambda s: math.isfinite(s) and s > 0,
                          "the seconds between progress lines off a terminal as a positive number "
                          "(e.g. LABTWIN_PROGRESS_S=1)", f"every {PLAIN_EVERY_S:g} s")


def bar_progress(console: Console, transient: bool = False, fields: tuple[str, ...] = (), disable: bool = False,
                 every_s: float | None = None, remaining: bool = True) -> Any:
    """What a long command does, its bar, done of total and time taken, then ``fields``: rich format strings
    such as ``"lab {task.fields[lab]}"`` (each task's own values, given to ``add_task`` and ``update``).
    ``remaining``: also the time left at the pace so far (not for work that may end before its total: a campaign
    that stops when its targets are met). ``every_s``: between lines off a terminal (``plain_every_s()``)."""
    if not console.is_interactive and not disable:
        return PlainProgress(console, fields, plain_every_s() if every_s is None else every_s, remaining=remaining)
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    left = (TextColumn("left"), TimeRemainingColumn()) if remaining else ()
    return Progress(TextColumn("{task.description}", style="bold", markup=False), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), *left, *(TextColumn(f) for f in fields), console=console,
                    transient=transient, disable=disable)


class PlainProgress:
    """The part of rich's ``Progress`` the commands use, written as lines: ``description: done/total  fields  0:01:05``."""

    def __init__(self, console: Console, fields: tuple[str, ...] = (), every_s: float = PLAIN_EVERY_S,
                 clock: Callable[[], float] = time.monotonic,
                 timer: Callable[[float, Callable[[], None]], Any] = threading.Timer, remaining: bool = False) -> None:
        self.console, self.remaining = console, remaining
        self._fields, self._every_s, self._clock, self._timer = fields, every_s, clock, timer
        self._tasks: list[dict[str, Any]] = []
        self._lock = threading.RLock()  # the timer's thread says lines too
        self._pending: Any = None  # the timer that will say a move not said yet

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **fields: Any) -> int:
        with self._lock:
            now = self._clock()
            self._tasks.append({"description": description, "total": total, "completed": completed, "fields": fields,
                                "started": now, "said": now, "said_what": None, "stopped": False})
            self._say(self._tasks[-1], now)
            return len(self._tasks) - 1

    def update(self, task_id: int, *, completed: float | None = None, total: float | None = None,
               advance: float | None = None, description: str | None = None, **fields: Any) -> None:
        with self._lock:
            task = self._tasks[task_id]
            if total is not None:
                task["total"] = total
            if completed is not None:
                task["completed"] = completed
            if advance is not None:
                task["completed"] += advance
            if description is not None:
                task["description"] = description
            task["fields"].update(fields)
            self._due(task, self._clock())

    def _due(self, task: dict[str, Any], now: float) -> None:
        """Say the task if it moved and a line is due; if it moved and none is due yet, say it when one is."""
        if task["stopped"] or not self._moved(task):
            return
        # every every_s at first, then less often as the work goes on: a few dozen lines for a night's campaign
        wait = task["said"] + max(self._every_s, (now - task["started"]) / 6) - now
        if wait <= 0:
            self._say(task, now)
        elif self._pending is None:
            self._pending = self._timer(wait, self._overdue)
            self._pending.daemon = True
            self._pending.start()

    def _overdue(self) -> None:
        with self._lock:
            self._pending = None
            now = self._clock()
            for task in self._tasks:
                self._due(task, now)

    def advance(self, task_id: int, advance: float = 1) -> None:
        self.update(task_id, advance=advance)

    def stop(self) -> None:
        """Say where each task ended (once), unless the last line already did."""
        with self._lock:
            if self._pending is not None:
                self._pending.cancel()
                self._pending = None
            now = self._clock()
            for task in self._tasks:
                if not task["stopped"] and self._moved(task):
                    self._say(task, now)
                task["stopped"] = True

    @staticmethod
    def _moved(task: dict[str, Any]) -> bool:
        return (task["completed"], task["fields"]) != task["said_what"]

    def _say(self, task: dict[str, Any], now: float) -> None:
        done = _count(task["completed"]) + ("" if task["total"] is None else f"/{_count(task['total'])}")
        elapsed = int(now - task["started"])
        view = SimpleNamespace(fields=task["fields"], description=task["description"])
        extra = "  ".join(s for s in (Text.from_markup(f.format(task=view)).plain.strip() for f in self._fields) if s)
        clock = _hms(elapsed)
        total, completed = task["total"], task["completed"]
        if self.remaining and total and 0 < completed < total and elapsed > 0:  # at the pace so far
            clock += f"  about {_hms(int(elapsed * (total - completed) / completed))} left"
        self.console.print("  ".join(s for s in (f"{task['description']}: {done}", extra, clock) if s),
                           highlight=False, markup=False)
        task["said"], task["said_what"] = now, (task["completed"], dict(task["fields"]))


def _count(x: float) -> str:
    return f"{x:.0f}" if float(x).is_integer() else f"{x:.1f}"


def _hms(seconds: int) -> str:
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"
