"""Worker processes for benches and `twin whatif` that Ctrl-C stops at once.

Ctrl-C reaches the whole process group. A worker of a plain ``ProcessPoolExecutor`` took it as an error of the
run it was in and went on to the next, and the pool's exit waited for every run submitted: a bench went on for
its whole length, silently. Here the workers ignore SIGINT; the pool, left by an exception (KeyboardInterrupt
among them), drops the runs not started and stops the running ones with SIGTERM, which a worker turns into
``SystemExit`` so that its run's temporary files are removed on the way out. The executor's worker loop catches
that ``SystemExit`` as the run's failure and would take the next run already queued to it (half-started, then
killed when ``STOP_S`` ran out, leaving its files; or a traceback from a queue closed under it): a stopped worker
leaves as soon as its run has unwound.

A run's temporary files go in a directory the pool makes and removes when it ends, whatever its workers were
doing: a stop that lands inside ``tempfile.TemporaryDirectory()`` itself (the directory made, its removal not yet
arranged) or during that removal, or a worker killed when ``STOP_S`` ran out, would otherwise leave them behind.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any

STOP_S = 10.0  # how long the stopped workers have to clean up before they are killed


class WorkerPool(ProcessPoolExecutor):
    def __init__(self, workers: int, initializer: Callable[[], None] | None = None) -> None:
        self.scratch = tempfile.mkdtemp(prefix="labtwin-workers-")
        super().__init__(max_workers=max(1, workers), initializer=_start_worker, initargs=(initializer, self.scratch))

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        return super().submit(_run, fn, *args, **kwargs)

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> bool:
        try:
            if exc_type is None:
                return bool(super().__exit__(exc_type, exc, tb))
            self._stop()
            return False
        finally:
            shutil.rmtree(self.scratch, ignore_errors=True)

    def _stop(self) -> None:
        workers = list((self._processes or {}).values())
        manager = getattr(self, "_executor_manager_thread", None)  # shutdown forgets it (typeshed mistypes it)
        self.shutdown(wait=False, cancel_futures=True)
        for p in workers:
            p.terminate()
        deadline = time.monotonic() + STOP_S  # wall time of OS processes, not lab time; one wait for them all
        for p in workers:
            p.join(max(0.0, deadline - time.monotonic()))
        for p in workers:
            if p.is_alive():
                p.kill()
        # the executor's manager thread closes its wake-up pipe when it sees the workers gone; at exit, Python
        # 3.11 writes to that pipe unlocked, and a close in between is a traceback ("Bad file descriptor")
        if manager is not None:
            manager.join(STOP_S)


def _start_worker(then: Callable[[], None] | None, scratch: str) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit)
    tempfile.tempdir = os.environ["TMPDIR"] = scratch  # SQLite's own temporary files too
    if then is not None:
        then()


_stopped = False  # this worker was sent SIGTERM
_running = False  # this worker is in a run (a SIGTERM unwinds it)


def _run(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    global _running
    try:
        _running = True  # inside the try: a stop that lands here still leaves through the finally
        return fn(*args, **kwargs)
    finally:
        _running = False
        if _stopped:  # the run has unwound (its files removed): leave, not on to the next run queued here
            _leave()


def _exit(*_: Any) -> None:
    global _stopped
    _stopped = True
    if not _running:  # starting (the executor would print its SystemExit as a failed initializer) or between runs
        _leave()
    sys.exit(143)


def _leave() -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(143)
