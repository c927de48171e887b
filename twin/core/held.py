"""A plugin's call that does not return holds the lab: a driver's blocking call to an instrument (a vendor SDK
reading a socket with no timeout), a scheduler's or planner's search with no end. Every device, deadline and
message waits meanwhile, and nothing says why.

Each such call is run between ``holding`` and ``released`` (a stretch of a driver's step between two awaits, one
``decide`` or ``propose``). One daemon thread per process looks every second at what is held, and when a call has
held its thread past ``HELD_S`` of wall time it says so while it still does: who, where its code is, and what to
do. A signal handler calls ``interrupt_held``: SIGINT or SIGTERM then raises ``Interrupted`` inside such a call on
the handler's thread, which is the only way to end it, so that the stop the handler asked for can run.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time

from twin.core.errors import Interrupted

log = logging.getLogger(__name__)
HELD_S = 30.0  # wall seconds a call may hold its thread before the log says so while it still does
#: wall seconds a call must have held its thread for a signal to end it: a shorter one (a GP fit, a stretch of a
#: driver's step) is let finish, and the stop runs when it returns
INTERRUPT_AFTER_S = 1.0
_TWIN = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # a frame in here is the lab's, not the plugin's
_STDLIB = os.path.dirname(os.__file__)


class Holder:
    """Who holds the lab while its call runs (``who``: "spectrometer's driver"), what to do about it (``advice``),
    and whether it was said (its owner then need not say it again when the call returns). Its calls hold the lab
    when they run on the thread it was made on, the lab's: one its owner hands to another thread (a planner asked
    off the loop on a scaled clock) leaves the lab going on without its answer."""

    __slots__ = ("who", "advice", "said", "thread")

    def __init__(self, who: str, advice: str) -> None:
        self.who, self.advice, self.said = who, advice, False
        self.thread = threading.get_ident()


#: each thread's call that holds it now: thread id -> (its Holder, since when (time.perf_counter))
_held: dict[int, tuple[Holder, float]] = {}
_watcher: threading.Thread | None = None


def holding(holder: Holder, since: float) -> None:
    """``holder``'s call runs on this thread from ``since`` until ``released``."""
    thread = threading.get_ident()
    if thread == holder.thread:
        _held[thread] = (holder, since)


def released() -> None:
    _held.pop(threading.get_ident(), None)


def interrupt_held(why: str) -> None:
    """Called by a signal handler: if a call has held this thread for ``INTERRUPT_AFTER_S`` (or ``HELD_S``, if
    shorter), end it with ``Interrupted``."""
    now = _held.get(threading.get_ident())
    if now is not None and time.perf_counter() - now[1] >= min(INTERRUPT_AFTER_S, HELD_S):
        raise Interrupted(f"{why} while {now[0].who} held the lab for {time.perf_counter() - now[1]:.0f} s of wall "
                          "time")


def watch() -> None:
    """Start this process's watcher thread, if it is not running."""
    global _watcher
    if _watcher is None or not _watcher.is_alive():
        _watcher = threading.Thread(target=_watching, name="labtwin-held-watch", daemon=True)
        _watcher.start()


def _watching() -> None:
    said: dict[int, float] = {}  # thread -> the start of the call last said on it
    while True:
        time.sleep(min(1.0, HELD_S / 4))
        now = time.perf_counter()
        for thread, (holder, since) in list(_held.items()):
            if now - since < HELD_S or said.get(thread) == since:
                continue
            said[thread] = since
            holder.said = True
            log.warning("%s has held the lab for %.0f s of wall time without returning, at %s; nothing else runs "
                        "until it returns (no device, no deadline, no message). %s. Ctrl-C ends the call (an "
                        "exception in it) and stops the lab cleanly, its journal written (`twin report JOURNAL`)",
                        holder.who, now - since, _where(thread), holder.advice)


def _where(thread: int) -> str:
    """The innermost line of ``thread``'s stack outside labtwin and the standard library: the plugin's, or its
    library's."""
    frame = sys._current_frames().get(thread)
    first = frame
    while frame is not None:
        name = frame.f_code.co_filename
        if not name.startswith((_TWIN, _STDLIB)):
            return f"{name}:{frame.f_lineno} in {frame.f_code.co_name}"
        frame = frame.f_back
    return f"{first.f_code.co_filename}:{first.f_lineno}" if first is not None else "an unknown line"
