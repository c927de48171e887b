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
    """Spawned workers, started with Ctrl-C (and a SIGTERM that unwinds, as `twin train`'s does) held back until
    all are: one landing while a worker is handed its start-up data leaves the worker reading half of it (a
    traceback after "interrupted"), and a pool half-built is not stopped (``Pool`` cleans up only on
    ``Exception``). The signal held is then handled as it would have been, once the workers are stopped."""
    import multiprocessing
    import signal
    import threading

    start = multiprocessing.get_context("spawn").Pool
    if threading.current_thread() is not threading.main_thread():
        return start(workers, initializer=_quiet_worker)
    held: list[Any] = []
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    saved = {sig: h for sig, h in saved.items() if sig == signal.SIGINT or callable(h)}  # SIGTERM's default: dies
    for sig in saved:
        signal.signal(sig, lambda *got: held.append(got))
    try:
        pool = start(workers, initializer=_quiet_worker)
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler if handler is not None else signal.default_int_handler)
    if held:
        pool.terminate()
        pool.join()
        signum, frame = held[0]
        handler = saved[signum]
        if callable(handler):
            handler(signum, frame)  # raises what it would have (KeyboardInterrupt, or `twin train`'s Terminated)
        raise KeyboardInterrupt
    return pool


def _quiet_worker() -> None:
    """Ctrl-C reaches the whole process group: the trainer stops the workers and says what it kept."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
