"""Worker processes for benches and `twin whatif` that Ctrl-C stops at once.

Ctrl-C reaches the whole process group. A worker of a plain ``ProcessPoolExecutor`` took it as an error of the
run it was in and went on to the next, and the pool's exit waited for every run submitted: a bench went on for
its whole length, silently. Here the workers ignore SIGINT; the pool, left by an exception (KeyboardInterrupt
among them), drops the runs not started and stops the running ones with SIGTERM, which a worker turns into
``KeyboardInterrupt`` so that its run's temporary files are removed on the way out. (Not ``SystemExit``: the lab
takes that, raised in a planner or a driver, as the plugin's failure, and runs on; a bench's runs also leave
SIGTERM to the pool, ``run(handle_signals=False)``, or the campaign would take it as a clean stop.) The executor's
worker loop catches the interrupt as the run's failure and would take the next run already queued to it
(half-started, then killed when ``STOP_S`` ran out, leaving its files; or a traceback from a queue closed under
it): a stopped worker leaves as soon as its run has unwound.

What every worker would say of its runs (the fast runtime refusing a driver, each run then going on the asyncio
runtime) is said once, by the command: the records of the loggers named in ``once`` go from the workers to the
pool's process, which logs each distinct message once, where each worker would have printed it for every run.

A run's temporary files go in a directory the pool makes and removes when it ends, whatever its workers were
doing: a stop that lands inside ``tempfile.TemporaryDirectory()`` itself (the directory made, its removal not yet
arranged) or during that removal, or a worker killed when ``STOP_S`` ran out, would otherwise leave them behind.
A pool's process killed by SIGKILL cannot remove it: its workers, told by a signal of their own (SIGUSR1, where the
pool's stop is SIGTERM), do as they leave.

While the pool is open, Ctrl-C and SIGTERM are only noted, and raised where the command waits for its runs
(``completed``, ``map``). Raised wherever the main thread happened to be, they could land inside the executor's
own locking (``submit`` holding its queue's lock, ``as_completed`` taking each future's lock in turn) and leave a
lock held for good: the executor's thread then waited on it, and so did the command's exit, forever (one SIGTERM
in a few hundred did it: a whatif said it had stopped and never ended).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Collection, Iterable, Iterator
from concurrent.futures import ALL_COMPLETED, FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from logging.handlers import QueueHandler
from types import FrameType
from typing import Any

from twin.core.parent_death import ends_with_parent

STOP_S = 10.0  # how long the stopped workers have to clean up before they are killed
CHECK_S = 0.1  # how often a wait for runs looks for a Ctrl-C or SIGTERM noted meanwhile


class WorkerPool(ProcessPoolExecutor):
    def __init__(self, workers: int, initializer: Callable[[], None] | None = None, once: Collection[str] = ()) -> None:
        self.scratch = tempfile.mkdtemp(prefix="labtwin-workers-")
        self._said: Any = multiprocessing.Queue() if once else None
        super().__init__(max_workers=max(1, workers), initializer=_start_worker,
                         initargs=(initializer, self.scratch, os.getpid(), tuple(once), self._said))
        self._signals = _NotedSignals()
        self._listener = _SaidOnce(self._said) if once else None

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        try:
            return super().submit(_run, fn, *args, **kwargs)
        except BrokenProcessPool:  # a stop sent to the whole process group (`timeout`, `kill -TERM -PGID`) ended
            self._signals.raise_noted()  # the idle workers before this process raised its own: raise that
            raise

    def completed(self, futures: Iterable[Future]) -> Iterator[Future]:
        """``concurrent.futures.as_completed``, raising a Ctrl-C or SIGTERM noted while it waits."""
        pending = set(futures)
        while pending:
            done, pending = self._wait(pending, FIRST_COMPLETED)
            yield from done

    def map(self, fn: Callable[..., Any], *iterables: Iterable[Any], timeout: float | None = None,
            chunksize: int = 1) -> Iterator[Any]:
        """The results in the order of the arguments, raising a Ctrl-C or SIGTERM noted while it waits."""
        futures = [self.submit(fn, *args) for args in zip(*iterables)]

        def in_order() -> Iterator[Any]:
            for future in futures:
                self._wait({future}, ALL_COMPLETED)
                yield future.result()
        return in_order()

    def _wait(self, futures: set[Future], until: str) -> tuple[set[Future], set[Future]]:
        while True:
            done, pending = wait(futures, CHECK_S, until)
            self._signals.raise_noted()
            if done:
                return done, pending

    def __enter__(self) -> WorkerPool:
        self._signals.note()
        if self._listener is not None:
            self._listener.start()
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        try:
            if exc_type is None:
                super().__exit__(exc_type, exc, tb)
            else:
                self._stop()
        finally:
            if self._listener is not None:  # after the workers: what they said is in the queue, before its end
                self._listener.stop()
            shutil.rmtree(self.scratch, ignore_errors=True)
            self._signals.restore()
        if exc_type is None:
            self._signals.raise_noted()  # came after the last wait

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


class _NotedSignals:
    """Ctrl-C and SIGTERM noted, to be raised by ``raise_noted`` as their handlers before would have raised them (a
    SIGTERM left to the default becomes ``SystemExit(143)``, so that the pool stops its workers on the way out). A
    worker forked before its own handlers are set leaves at a SIGTERM and ignores a Ctrl-C (the pool stops it)."""

    def __init__(self) -> None:
        self._before: dict[int, Any] = {}
        self._noted: list[int] = []
        self._pid = os.getpid()

    def note(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # only the main thread takes signals, and sets their handlers
        self._before = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            before = signal.getsignal(sig)
            if callable(before) or (sig == signal.SIGTERM and before == signal.SIG_DFL):
                self._before[sig] = before
                signal.signal(sig, self._noting)

    def _noting(self, sig: int, _: FrameType | None) -> None:
        if os.getpid() != self._pid:
            if sig == signal.SIGTERM:
                _leave()
            return
        self._noted.append(sig)

    def raise_noted(self) -> None:
        if not self._noted:
            return
        sig = self._noted[0]
        self._noted.clear()
        before = self._before.get(sig, signal.SIG_DFL)
        if callable(before):
            before(sig, None)  # raises KeyboardInterrupt, or the command's Terminated
            return
        raise SystemExit(128 + sig)

    def restore(self) -> None:
        for sig, before in self._before.items():
            signal.signal(sig, before)


class _SaidOnce(threading.Thread):
    """Logs each distinct message the workers hand over once, through its own logger in this process. It only
    reads the queue (polling, and stopped by an event): a worker killed while it wrote holds the queue's write
    lock for good, and a sentinel put here would wait on that lock for ever."""

    def __init__(self, said: Any) -> None:
        super().__init__(daemon=True)
        self._said, self._stopping = said, threading.Event()
        self._seen: set[tuple[str, str]] = set()

    def run(self) -> None:
        while not self._stopping.is_set():
            self._take(timeout=0.1)
        while self._take(timeout=0.0):  # what came before the stop
            pass

    def _take(self, timeout: float) -> bool:
        try:
            record = self._said.get(timeout=timeout) if timeout else self._said.get_nowait()
        except queue.Empty:
            return False
        key = (record.name, record.getMessage())
        if key not in self._seen:
            self._seen.add(key)
            logging.getLogger(record.name).handle(record)
        return True

    def stop(self) -> None:
        self._stopping.set()
        self.join(1.0)


def _start_worker(then: Callable[[], None] | None, scratch: str, pool: int, once: tuple[str, ...], said: Any) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit)
    signal.signal(signal.SIGUSR1, _orphaned)
    sys.unraisablehook = _unraisable
    global _scratch
    _scratch = scratch
    _ends_with(pool)
    tempfile.tempdir = os.environ["TMPDIR"] = scratch  # SQLite's own temporary files too
    _one_thread_each()
    for name in once:
        logger = logging.getLogger(name)
        logger.handlers = [QueueHandler(said)]
        logger.propagate = False
    if then is not None:
        then()


def _one_thread_each() -> None:
    """One thread for each numerical library, as many workers as cores: with two workers on two cores, the BLAS of
    one (two threads, spinning a while after each call) took the core where the other was deciding, and a rule's
    decision, 0.04 ms at the median, took 4 ms at the 99th percentile (the rl policy's 16 ms). Numpy's BLAS came
    with the fork (limited here); scipy's and OpenMP, loaded later, read the environment."""
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = "1"
    try:
        from threadpoolctl import threadpool_limits  # scikit-learn's dependency: absent, numpy's BLAS keeps two
    except ImportError:
        return
    threadpool_limits(1)


def _ends_with(pool: int) -> None:
    """SIGUSR1 when the pool's process dies, even by SIGKILL (Linux): the worker holds a copy of its work queue's
    write end, so the queue never tells it, and an orphaned worker waited for work for good."""
    if not ends_with_parent(pool, signal.SIGUSR1):  # it died before that was set
        _orphaned()


_scratch = ""  # the pool's directory for its runs' files
_pool_gone = False  # the pool's process ended (its directory is the workers' to remove)
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
    if not _running:  # starting (the executor would print the interrupt as a failed initializer) or between runs
        _leave()
    raise KeyboardInterrupt


def _orphaned(*_: Any) -> None:
    global _pool_gone
    _pool_gone = True
    _exit()


def _unraisable(what: Any) -> None:
    """A SIGTERM that lands in code Python cannot raise from (a weakref's callback, as an import's module lock is
    freed) was printed as 'Exception ignored in ...' with a traceback, and the run went on: the worker leaves at once
    instead (the pool removes the run's files)."""
    if _stopped and isinstance(what.exc_value, KeyboardInterrupt):
        _leave()
    sys.__unraisablehook__(what)


def _leave() -> None:
    if _pool_gone:  # each worker tries, as its run has unwound; another's may still be ending
        shutil.rmtree(_scratch, ignore_errors=True)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(143)


def keep_done(stop: BaseException, done: Any) -> None:
    """What a bench finished before Ctrl-C or SIGTERM stopped it, carried by the interrupt to the command that
    shows it (``done_before``); ``done`` empty: nothing was."""
    stop.done_before = done or None  # type: ignore[attr-defined]


def done_before(stop: BaseException) -> Any:
    return getattr(stop, "done_before", None)
