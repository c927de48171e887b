"""A file written whole or not at all."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
from collections.abc import Callable, Iterator
from typing import IO
from pathlib import Path

from twin.core.errors import TwinError


FULL_BYTES = 1 << 16  # free space under which a disk counts as full


def free_bytes(path: Path) -> int:
    """The free space of the disk a file at ``path`` is (to be) written on."""
    return shutil.disk_usage(Path(path).resolve().parent).free


@contextlib.contextmanager
def written_whole(path: Path) -> Iterator[Path]:
    """Yields ``.<name>.<pid>.partial`` beside ``path`` to write into; renamed to ``path`` when the block ends,
    removed if it raises (Ctrl-C, a full disk): no half-written file is ever left under the name, nor over an earlier
    one. The process's own: two writing one file at once each write theirs, and the last to end is the file."""
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        yield partial
        os.replace(partial, path)
    except OSError as exc:
        partial.unlink(missing_ok=True)
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise TwinError(f"cannot write {path}: {exc.strerror}; free some space, or write it on another disk "
                            "(a file written before it is whole)") from None
        raise
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def locked(path: Path, refusal: str, on_wait: Callable[[], None] | None = None) -> IO[bytes]:
    """``path`` opened (made if need be, never emptied) and locked by this process until closed; if another process
    holds it now, ``refusal`` raised as a TwinError — or, given ``on_wait``, that called and the lock waited for."""
    f = open(path, "ab")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        if on_wait is None:
            f.close()
            raise TwinError(refusal) from None
        on_wait()
        fcntl.flock(f, fcntl.LOCK_EX)
    return f


@contextlib.contextmanager
def kept_from_others(path: Path, refusal: str) -> Iterator[None]:
    """While the block runs, every other process that asks the same of ``path`` is refused with ``refusal``, and so
    is this one if another holds it now: a hidden ``.NAME.lock`` beside it, locked, and removed at the end (a
    killed process's lock holds nothing)."""
    lock_path = path.with_name(f".{path.name}.lock")
    lock = locked(lock_path, refusal)
    try:
        yield
    finally:
        lock_path.unlink(missing_ok=True)  # before unlocking: one waiting for the name then makes a new lock
        lock.close()
