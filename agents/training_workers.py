"""Where a training's rollouts run: spawned worker processes that Ctrl-C stops cleanly, or, for one worker, the
trainer's own process (a spawned worker spends seconds importing torch before its first task)."""

from __future__ import annotations

import os
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


def numbered(job: tuple) -> tuple[int, Any]:
    """Worker: ``(task, i, args)`` -> ``(i, task(args))``, so that results taken as they come can be put in order."""
    task, i, args = job
    return i, task(args)


def workers_for(workers: int) -> Any:
    """A pool with ``imap_unordered``: spawned processes, no more than the machine has cores (what is asked of the
    pool, and so what is learnt, is the caller's, whatever the number: four on two cores took 104 s where two took
    94, for the same policy), or for one the trainer's own process."""
    processes = min(workers, os.cpu_count() or workers)
    return _InProcess() if processes <= 1 else spawn_pool(processes)


def spawn_pool(workers: int) -> Any:
    """Spawned workers, started with Ctrl-C (and a SIGTERM that unwinds, as `twin train`'s does) held back until
    all are: one landing while a worker is handed its start-up data leaves the worker reading half of it (a
    traceback after "interrupted"), and a pool half-built is not stopped (``Pool`` cleans up only on
    ``Exception``). The signal held is then handled as it would have been, once the workers are stopped."""
    import multiprocessing

    with _Held() as held:
        pool = multiprocessing.get_context("spawn").Pool(workers, initializer=_quiet_worker)
    if held.got:
        pool.terminate()
        pool.join()
        held.handle()
    return _Spawned(pool)


class _Held:
    """Ctrl-C and SIGTERM (where something handles it: `twin train` unwinds on it) held back while inside, on the
    main thread; ``handle`` then handles the first as it would have been (it raises)."""

    def __init__(self) -> None:
        self.got: list[tuple[int, Any]] = []
        self._saved: dict[int, Any] = {}

    def __enter__(self) -> "_Held":
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
            self._saved = {sig: h for sig, h in saved.items() if sig == signal.SIGINT or callable(h)}
            for sig in self._saved:  # SIGTERM's default (the process dies) is left as it is
                signal.signal(sig, lambda *got: self.got.append(got))
        return self

    def __exit__(self, *exc: Any) -> None:
        import signal

        for sig, handler in self._saved.items():
            signal.signal(sig, handler if handler is not None else signal.default_int_handler)

    def handle(self) -> None:
        if not self.got:
            return
        signum, frame = self.got[0]
        handler = self._saved[signum]
        if callable(handler):
            handler(signum, frame)  # raises what it would have (KeyboardInterrupt, or `twin train`'s Terminated)
        raise KeyboardInterrupt


_END = object()
CHECK_S = 0.1  # how often a wait for results looks for a signal held meanwhile


class _Spawned:
    """The spawned pool, whose waits for results hold Ctrl-C and SIGTERM back and handle them between results.
    Raised inside the wait (``IMapIterator.next``), one could land between its condition's lock taken and the block
    that releases it: the pool's result thread, then the pool's terminate, waited on that lock for good."""

    def __init__(self, pool: Any) -> None:
        self._pool = pool

    def __enter__(self) -> "_Spawned":
        return self

    def __exit__(self, *exc: Any) -> None:
        self._pool.__exit__(*exc)  # terminates the workers

    def imap_unordered(self, task: Any, jobs: Any) -> Any:
        results = self._pool.imap_unordered(task, jobs)
        while True:
            with _Held() as held:
                item = _next(results, held)
            held.handle()
            if item is _END:
                return
            yield item


def _next(results: Any, held: _Held) -> Any:
    """The next result, ``_END``, or None as soon as a signal is held."""
    import multiprocessing

    while not held.got:
        try:
            return results.next(timeout=CHECK_S)
        except multiprocessing.TimeoutError:
            continue
        except StopIteration:
            return _END
    return None


def _quiet_worker() -> None:
    """Ctrl-C reaches the whole process group: the trainer stops the workers and says what it kept."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
