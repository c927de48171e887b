"""How a command stops: Ctrl-C and SIGTERM unwind it the same way, it says what became of its work, and it exits
with the status a shell expects of a command a signal ended."""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import threading
from collections.abc import Callable, Iterator
from typing import Any, NoReturn, TypeVar

import typer

from twin.cli.common import _fail, err
from twin.core.errors import TwinError

Command = TypeVar("Command", bound=Callable[..., Any])


def interruptible(command: Command) -> Command:
    """A command of many runs in worker processes (a bench, `twin whatif`): Ctrl-C or SIGTERM stops them
    (``WorkerPool``) and says so, and an error raised in a worker is one line, instead of a traceback or a silent
    exit."""
    @functools.wraps(command)
    def stopping(*args: Any, **kwargs: Any) -> Any:
        try:
            with sigterm_unwinds():
                return command(*args, **kwargs)
        except TwinError as exc:  # raised in a worker, past the checks made before it started
            _fail(exc)
        except KeyboardInterrupt as stop:
            err.print(f"{stopped_by(stop)}: the runs still going were stopped; no --csv, --json or --save file was "
                      "written", highlight=False)
            raise typer.Exit(exit_status(stop)) from None

    return stopping  # type: ignore[return-value]


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C raises KeyboardInterrupt, so that a command unwinds the same way: left to
    Python's default, SIGTERM ended a bench or a training at once, and its worker processes lived on, orphaned,
    waiting for work that would never come."""


#: how soon a Ctrl-C or SIGTERM that nothing acted on is delivered again (``sigterm_unwinds(redeliver=True)``)
REDELIVER_S = 0.5


@contextlib.contextmanager
def sigterm_unwinds(redeliver: bool = False) -> Iterator[None]:
    """SIGTERM raises ``Terminated`` while inside (unless something else already handles it). ``redeliver``: for a
    block that does not catch the interrupt itself, Ctrl-C or SIGTERM is raised again every ``REDELIVER_S`` until
    it leaves the block — Python drops an exception raised in a weakref callback or a destructor ("Exception
    ignored in …"), and a Ctrl-C that landed in one while a module was being imported was lost: the route search
    it meant to stop ran its whole budget."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return
    left, started = threading.Event(), threading.Event()

    def again(signum: int) -> None:
        while not left.wait(REDELIVER_S):  # wall time: a person's Ctrl-C, not the lab's
            os.kill(os.getpid(), signum)

    def raised(signum: int, _frame: Any) -> None:
        if redeliver and not started.is_set():
            started.set()
            threading.Thread(target=again, args=(signum,), daemon=True).start()
        raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt

    interrupt = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGTERM, raised)
    if redeliver and interrupt is signal.default_int_handler:
        signal.signal(signal.SIGINT, raised)
    try:
        yield
    finally:
        left.set()
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.signal(signal.SIGINT, interrupt)


def stopped_by(stop: BaseException) -> str:
    return "terminated (SIGTERM)" if isinstance(stop, Terminated) else "interrupted"


def part_done(stop: KeyboardInterrupt, as_json: bool) -> Any:
    """What a bench or what-if finished before Ctrl-C or SIGTERM (``stop``) ended it, for its table; ``stop`` raised
    again if it finished nothing, or its output is JSON (no table to show)."""
    from twin.tools.pool import done_before

    done = done_before(stop)
    if not done or as_json:
        raise stop
    return done


def stopped_partway(stop: BaseException, shown: str) -> NoReturn:
    """After the table of what a bench finished before Ctrl-C or SIGTERM stopped it: say so, and exit as the
    signal would."""
    err.print(f"{stopped_by(stop)}: the table is of {shown}; the runs still going were stopped, and no --csv, "
              "--json or --save file was written", highlight=False)
    raise typer.Exit(exit_status(stop))


def exit_status(stop: BaseException) -> int:
    """A shell's status for a command ended by a signal: 128 + the signal's number."""
    return 128 + (signal.SIGTERM if isinstance(stop, Terminated) else signal.SIGINT)


def exit_if_interrupted(*stopped: str) -> None:
    """A run whose summary says a signal stopped it (``stopped``: "interrupted (SIGINT)") exits as a command ended
    by that signal, once its summary is printed and its journal and recording written: a shell loop or script over
    runs then stops with it instead of starting the next."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if any(why.startswith(f"interrupted ({sig.name})") for why in stopped):
            raise typer.Exit(128 + sig)
