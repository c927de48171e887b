"""Where a training's rollouts run: spawned worker processes that Ctrl-C stops cleanly, or, for one worker, the
trainer's own process (a spawned worker spends seconds importing torch before its first task)."""

from __future__ import annotations

from typing import Any


class _InProcess:
    """One worker: the tasks run in the trainer's process, in the order given, as a pool of one would run them —
    without a process to start (seconds of imports, longer than a short training's rounds)."""

    def __enter__(self) -> "_InProcess":
        return self

    def __exit__(self, *exc: Any) -> None:
        return None

    @staticmethod
    def imap_unordered(task, jobs):
        return map(task, jobs)


def workers_for(workers: int) -> Any:
    """A pool with ``imap_unordered``: spawned processes, or for one worker the trainer's own process."""
    return _InProcess() if workers <= 1 else spawn_pool(workers)


def spawn_pool(workers: int) -> Any:
    """Spawned workers, started with Ctrl-C held back until all are: one landing while a worker is handed its
    start-up data leaves the worker reading half of it (a traceback after "interrupted"), and a pool half-built
    is not stopped (``Pool`` cleans up only on ``Exception``)."""
    import multiprocessing
    import signal
    import threading

    start = multiprocessing.get_context("spawn").Pool
    if threading.current_thread() is not threading.main_thread():
        return start(workers, initializer=_quiet_worker)
    held: list[Any] = []
    previous = signal.signal(signal.SIGINT, lambda *sig: held.append(sig))
    try:
        pool = start(workers, initializer=_quiet_worker)
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)
    if held:
        pool.terminate()
        pool.join()
        raise KeyboardInterrupt
    return pool


def _quiet_worker() -> None:
    """Ctrl-C reaches the whole process group: the trainer stops the workers and says what it kept."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
