"""Lab time, injected into every actor.

The event loop itself runs on lab time: ``loop.time()`` returns lab seconds, so
``asyncio.timeout``, ``call_later`` and ``sleep`` all mean lab time, in every
mode. The mode decides only how the loop waits for its next timer:

- ``virtual`` never waits: when nothing is runnable and no message is in
  flight, lab time jumps to the next timer (trio's autojump, SimPy's
  ``Environment.run``);
- ``scaled`` waits ``lab seconds / speed`` of wall time
  (SimPy's ``RealtimeEnvironment(factor=)``);
- ``wall`` is ``scaled`` at speed 1.

A bus whose deliveries cross threads (Zenoh) must ``hold()`` the clock for each
message it has sent and ``release()`` it on delivery, so that virtual time never
jumps past a message still in flight.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import numbers
import selectors
import signal
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, Literal, Protocol, TypeVar

log = logging.getLogger(__name__)
T = TypeVar("T")
ClockMode = Literal["virtual", "scaled", "wall"]

#: Wall seconds the virtual clock waits for an in-flight message before it
#: assumes the message was lost and lets time move on again.
IN_FLIGHT_PATIENCE_S = 5.0


def lab_seconds(seconds: Any, call: str = "sleep") -> float:
    """A wait in lab seconds as a float; a driver's wait that is not a number (or is NaN) is its bug, said at
    the call (a negative wait is no wait; an infinite one lasts until the step is cancelled)."""
    if isinstance(seconds, bool) or not isinstance(seconds, numbers.Real) or seconds != seconds:  # numpy's are Real
        raise TypeError(f"clock.{call}({str(seconds)[:40]!r}): lab seconds must be a number, not "
                        f"{'NaN' if seconds != seconds else type(seconds).__name__}")
    return float(seconds)


class Clock(Protocol):
    """What actors and the orchestrator know of time."""

    mode: ClockMode

    def now(self) -> float:
        """Lab seconds since the clock started."""

    async def sleep(self, seconds: float) -> None: ...

    def timeout(self, seconds: float | None) -> asyncio.Timeout: ...


class _TimeBase:
    virtual = False

    def time(self) -> float:
        raise NotImplementedError

    def select(self, real_select: Callable[[float | None], list], timeout: float | None) -> list:
        raise NotImplementedError


class _VirtualTime(_TimeBase):
    virtual = True

    #: While callbacks are ready, the selector is polled for outside I/O only this often: a
    #: virtual run is pure computation, and a system call per loop turn was a tenth of its time.
    POLL_EVERY = 64

    def __init__(self) -> None:
        self.now = 0.0
        self.loop: asyncio.BaseEventLoop | None = None
        self.in_flight = 0
        self.idle_hooks: list[Callable[[], bool]] = []
        self._turns = 0

    def time(self) -> float:
        return self.now

    def select(self, real_select, timeout):
        if timeout == 0:
            self._turns += 1
            return real_select(0) if self._turns % self.POLL_EVERY == 0 else []
        if self.in_flight > 0:
            return self._wait_for_in_flight(real_select, timeout)
        events = real_select(0)
        if events:
            return events
        if [hook for hook in self.idle_hooks if hook()]:
            return []  # a hook scheduled work at this idle point: run it before time moves
        if timeout is None:
            # Nothing scheduled and nothing in flight: only outside I/O (a
            # signal, a watcher) can wake us, so wait for it for real.
            return real_select(None)
        # jump to the next timer's own time (not now + timeout, which rounds differently):
        # the fast runtime jumps the same way, so both reach the same lab times to the bit
        scheduled = getattr(self.loop, "_scheduled", None)
        self.now = max(self.now, scheduled[0]._when) if scheduled else self.now + timeout
        return []

    def release(self, n: int = 1) -> None:
        """``n`` messages (or thread calls) in flight have arrived."""
        self.in_flight = max(0, self.in_flight - n)

    def _wait_for_in_flight(self, real_select, timeout):
        events = real_select(IN_FLIGHT_PATIENCE_S)
        if not events and self.in_flight > 0:
            log.warning(
                "virtual clock: %d message(s) or thread call(s) in flight for %.0f s of wall time; "
                "assuming they were lost and letting lab time move on",
                self.in_flight,
                IN_FLIGHT_PATIENCE_S,
            )
            self.in_flight = 0
        return events


class _ScaledTime(_TimeBase):
    def __init__(self, speed: float, start: float = 0.0) -> None:
        if speed <= 0:
            raise ValueError(f"clock speed must be > 0, got {speed}")
        self.speed, self.start = speed, start
        self._t0 = time.monotonic()

    def time(self) -> float:
        return self.start + (time.monotonic() - self._t0) * self.speed

    def select(self, real_select, timeout):
        return real_select(None if timeout is None else timeout / self.speed)

    def follow(self, lab_s: float, wall_s: float, speed: float) -> float:
        """Re-anchor on another process's clock: it read ``lab_s`` at Unix time ``wall_s``. Returns the jump."""
        before = self.time()
        mono, wall = time.monotonic(), time.time()
        self.speed, self.start, self._t0 = speed, lab_s + (wall - wall_s) * speed, mono
        return self.time() - before


class _LabSelector(selectors.DefaultSelector):
    def __init__(self, base: _TimeBase) -> None:
        super().__init__()
        self._base = base

    def select(self, timeout=None):
        return self._base.select(super().select, timeout)


class LabEventLoop(asyncio.SelectorEventLoop):
    """An asyncio loop whose ``time()`` is lab time."""

    def __init__(self, base: _TimeBase) -> None:
        super().__init__(selector=_LabSelector(base))
        self._base = base
        if isinstance(base, _VirtualTime):
            base.loop = self
        self._clock_resolution = 1e-6
        #: What Ctrl-C asks of this loop when it runs in a thread of its own, where signals never reach it (a
        #: campaign's clean stop); nothing here: Ctrl-C cancels what the loop runs
        self.on_interrupt: list[Callable[[], None]] = []

    def time(self) -> float:
        return self._base.time()

    def run_in_executor(self, executor: Any, func: Any, *args: Any) -> asyncio.Future:  # type: ignore[override]
        """Work handed to a thread (``asyncio.to_thread``: a driver's blocking call moved off the loop): a virtual
        clock waits for it as for a message in flight, instead of jumping past the deadlines it is inside."""
        fut = super().run_in_executor(executor, func, *args)
        base = self._base
        if isinstance(base, _VirtualTime):
            base.in_flight += 1
            fut.add_done_callback(lambda _: base.release())
        return fut

    @property
    def speed(self) -> float:
        """Lab seconds per wall second (1 on a virtual clock, where wall time does not apply)."""
        return getattr(self._base, "speed", 1.0)


def wall_on_loop(seconds: float) -> float:
    """``seconds`` of wall time in the running loop's time (lab seconds on a lab's loop; as they are on a virtual
    one): what a timeout (``asyncio.timeout``, a library's own) given in wall seconds must be told, since the loop
    measures it."""
    return max(0.0, seconds) * getattr(asyncio.get_running_loop(), "speed", 1.0)


async def sleep_wall(seconds: float) -> None:
    """Wait ``seconds`` of wall time on the running loop (lab seconds on a virtual one): for code that deals
    with the world outside the lab, a real instrument's patience, say."""
    await asyncio.sleep(wall_on_loop(seconds))


class LabClock:
    """The one clock of a run; create its loop with :meth:`new_loop` or :meth:`run`."""

    def __init__(self, mode: ClockMode = "virtual", speed: float = 1.0, start: float = 0.0) -> None:
        """``start``: the lab time the clock starts at (a resumed live campaign goes on from its journal's)."""
        self.mode: ClockMode = mode
        if mode == "virtual":
            self._base: _TimeBase = _VirtualTime()
            self._base.now = start
        elif mode == "scaled":
            self._base = _ScaledTime(speed, start)
        elif mode == "wall":
            self._base = _ScaledTime(1.0, start)
        else:
            raise ValueError(f"unknown clock mode {mode!r}: use virtual, scaled or wall")
        self.speed = 1.0 if mode == "wall" else speed
        #: False while a process that joins a lab has not yet heard the lab's clock (twin/runtime/labtime.py)
        self.anchored = True

    def anchor(self) -> dict[str, Any]:
        """What another process needs to keep this clock's time: mode, speed, and a lab time at a Unix time."""
        return {"mode": self.mode, "speed": self.speed, "lab_s": self.now(), "wall_s": time.time()}

    @staticmethod
    def now_by(speed: float, lab_s: float, wall_s: float) -> float:
        """The lab time now by another process's anchor (it read ``lab_s`` at Unix time ``wall_s``)."""
        return lab_s + (time.time() - wall_s) * speed

    def follow(self, mode: ClockMode, speed: float, lab_s: float, wall_s: float) -> float:
        """Keep the time of a clock whose :meth:`anchor` this is (both processes read the same Unix time: one
        host, or hosts kept in step by NTP). Returns how far lab time jumped, in lab seconds."""
        if not isinstance(self._base, _ScaledTime) or mode == "virtual":
            raise ValueError("only a scaled or wall clock can follow another, and only a scaled or wall one")
        self.mode, self.speed, self.anchored = mode, (1.0 if mode == "wall" else speed), True
        return self._base.follow(lab_s, wall_s, self.speed)

    @property
    def is_virtual(self) -> bool:
        return self._base.virtual

    def new_loop(self) -> LabEventLoop:
        return LabEventLoop(self._base)

    def run(self, main: Coroutine[Any, Any, T]) -> T:
        """Run ``main`` to completion on a fresh loop of this clock. Called where a loop already runs (a Jupyter
        notebook's cell, an ``async def``), which a thread can hold only one of, it runs in a thread of its own and
        this call waits for it, as it would otherwise."""
        try:
            asyncio.get_running_loop()
        except RuntimeError:
            pass  # the campaign runs outside this handler: else every traceback of it says "during handling of" this
        else:
            return _in_own_thread(self.new_loop, main)
        with asyncio.Runner(loop_factory=self.new_loop) as runner:
            return runner.run(main)

    def now(self) -> float:
        return self._base.time()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, lab_seconds(seconds)))

    async def sleep_until(self, t_lab: float) -> None:
        await asyncio.sleep(max(0.0, lab_seconds(t_lab, "sleep_until") - self.now()))

    def timeout(self, seconds: float | None) -> asyncio.Timeout:
        return asyncio.timeout(seconds)

    def call_later(self, seconds: float, callback: Callable[[], Any]) -> asyncio.TimerHandle:
        return asyncio.get_running_loop().call_later(max(0.0, seconds), callback)

    def hold(self, n: int = 1) -> None:
        """Count ``n`` messages in flight: virtual time waits for them."""
        if self._base.virtual:
            self._base.in_flight += n  # type: ignore[attr-defined]

    def on_idle(self, hook: Callable[[], bool]) -> Callable[[], object]:
        """Call ``hook`` whenever the loop is idle, before virtual time jumps.

        A hook that schedules work returns True, and time stays put until that
        work is done. Returns a function that removes the hook.
        """
        if not self._base.virtual:
            return lambda: None
        hooks = self._base.idle_hooks  # type: ignore[attr-defined]
        hooks.append(hook)
        return lambda: hook in hooks and hooks.remove(hook)

    def release(self, n: int = 1) -> None:
        if isinstance(self._base, _VirtualTime):
            self._base.release(n)


async def wait_cancelled(task: asyncio.Task, seconds: float = 1.0) -> None:
    """Cancel ``task`` and wait for it, up to ``seconds`` of lab time. Not ``await task`` under a timeout: the
    timeout's cancel would go to ``task`` too, and a task that swallows cancels would then be waited for ever."""
    task.cancel()
    await asyncio.wait({task}, timeout=seconds)
    if task.done() and not task.cancelled():
        task.exception()  # taken: what it raised on the way out is its own business


def end_by_force(task: asyncio.Task) -> None:
    """End a task whose coroutine swallowed its cancel and went on (a driver's ``except CancelledError: pass``, a
    bare ``except:``): the loop could never end, since it cancels and waits for every task left. Its coroutine is
    closed (``GeneratorExit`` at its ``await``, which those do not catch; ``finally`` blocks run) and the task
    cancelled; what it then raises is taken, not logged."""
    task.add_done_callback(lambda t: t.cancelled() or t.exception())
    with contextlib.suppress(RuntimeError):  # one that awaits again even then cannot be ended
        task.get_coro().close()
    task.cancel()



def _in_own_thread(loop_factory: Callable[[], asyncio.AbstractEventLoop], main: Coroutine[Any, Any, T]) -> T:
    """``main`` run on a new loop in a new thread, waited for. Ctrl-C while waiting (a notebook's "interrupt") is
    handed to that loop: a campaign stops cleanly, as Ctrl-C stops it on the main thread, and returns its summary;
    anything else, or a second Ctrl-C, is cancelled there, waited for while it unwinds (a journal closed, devices
    stopped), and KeyboardInterrupt is raised here."""
    box: dict[str, Any] = {}
    ready, done = threading.Event(), threading.Event()

    async def tracked() -> T:
        box["task"], box["loop"] = asyncio.current_task(), asyncio.get_running_loop()
        ready.set()
        return await main

    def body() -> None:
        try:
            with asyncio.Runner(loop_factory=loop_factory) as runner:
                box["result"] = runner.run(tracked())
        except BaseException as exc:  # handed to the caller's thread
            box["error"] = exc
        finally:
            ready.set()
            done.set()

    def interrupt(cancel: bool) -> None:
        """Ctrl-C handed to the loop: its ``on_interrupt`` handlers, or (none, or ``cancel``) its task cancelled."""
        ready.wait()
        if "task" not in box or done.is_set():
            return
        loop, task = box["loop"], box["task"]

        def there() -> None:
            handlers = [] if cancel else list(getattr(loop, "on_interrupt", ()))
            for handler in handlers:
                handler()
            if not handlers:
                task.cancel()

        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile: nothing left to interrupt
            loop.call_soon_threadsafe(there)

    # waited for with an Event: Thread.join interrupted by Ctrl-C marks the thread stopped (Python 3.11), and a
    # second join returns at once
    thread = threading.Thread(target=body, name="labtwin-campaign", daemon=True)
    interrupted = False
    with _ctrl_c_noted() as ctrl_c:
        thread.start()
        if _until(done, ctrl_c):
            interrupted = True
            interrupt(cancel=False)
            if _until(done, ctrl_c):  # the campaign stops cleanly and returns its summary, as on the main thread
                interrupt(cancel=True)  # a second Ctrl-C: no waiting for a clean stop
                done.wait()
                raise KeyboardInterrupt
    if "error" in box:
        if interrupted and isinstance(box["error"], asyncio.CancelledError):
            raise KeyboardInterrupt
        raise box["error"]
    return box["result"]


def _until(event: threading.Event, ctrl_c: list[int]) -> bool:
    """Wait for ``event`` (False), or until a Ctrl-C is noted (True, and the note taken), waking every 0.1 s wall:
    Ctrl-C's handler runs at a wake-up even where a library set SA_RESTART on SIGINT (an asyncio loop's signal
    handler does), which restarts an endless wait instead of interrupting it. (Once, a CI run hung here, its
    Ctrl-C delivered and never raised.)"""
    while not event.wait(0.1):
        if ctrl_c:
            ctrl_c.clear()
            return True
    return False


@contextlib.contextmanager
def _ctrl_c_noted() -> Iterator[list[int]]:
    """Ctrl-C noted in the list yielded, for the wait to see: the loop this thread runs (``asyncio.run``'s) would
    only cancel its task, which waits without awaiting, and the campaign would run on to its end. Only noted, not
    raised where it lands: inside ``Event.wait``, with its lock taken, the campaign's thread could never set the
    event, and this wait would wait on its own lock for good."""
    noted: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield noted
        return
    previous = signal.signal(signal.SIGINT, lambda sig, _: noted.append(sig))
    try:
        yield noted
    finally:
        signal.signal(signal.SIGINT, previous)
