"""Who writes a journal: ``<journal>-lock``, held by the one process that writes it."""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from twin.core.errors import TwinError


def claim(path: Path) -> Any:
    """``<journal>-lock``, locked while this process writes the journal: a second run given the same journal
    (``--journal`` twice, a resume of a run still going) is refused, where it replaced the file under the first,
    which then died of a disk I/O error with its campaign lost. Released when the journal closes or the process
    ends (a lock left by a killed run holds nothing)."""
    lock = open(f"{path}-lock", "a+")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        holder = lock.read().strip()
        lock.close()
        raise TwinError(f"{path} is being written by another run{f' (process {holder})' if holder else ''}: wait "
                        "for that run to end, or give --journal another file (nothing has run yet)") from None
    lock.seek(0)
    lock.truncate()
    lock.write(str(os.getpid()))
    lock.flush()
    return lock


def writer(path: str | Path) -> str | None:
    """The process writing the journal at ``path`` now (its pid as text, "" if it did not say), or None if no run
    holds it: a killed run's lock file holds nothing. Asked with a shared lock that is let go at once (a run
    starting on the journal in that instant is refused, as if this were a run: nothing is lost)."""
    try:
        lock = open(f"{path}-lock")
    except OSError:
        return None
    with lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return lock.read().strip()
        fcntl.flock(lock, fcntl.LOCK_UN)
    return None


@contextmanager
def held(path: Path) -> Iterator[None]:
    """The journal at ``path`` kept from every other writer while the block runs (``twin resume``, which reads it
    and then replaces it); refused, naming the process, if a run is writing it now."""
    lock = claim(path)
    try:
        yield
    finally:
        release(lock)


def release(lock: Any) -> None:
    try:
        os.unlink(lock.name)  # before unlocking: a run waiting for the name then makes a new lock, not this one
    except OSError:
        pass
    lock.close()
