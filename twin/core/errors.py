"""One error root, so a caller can catch everything labtwin raises on purpose.

Every message says what went wrong and what to do next.
"""


from typing import Any

from twin.core.counts import counted


class Interrupted(BaseException):
    """Raised inside a plugin's call that holds the lab by SIGINT or SIGTERM (``twin.core.held``): the lab is
    stopping, and only an exception ends a call that does not return (a driver's step then fails as its error; a
    scheduler's decision is the fallback rule's; a planner proposes nothing more). Not an ``Exception``, as
    ``KeyboardInterrupt`` is not: a driver's or its SDK's ``except Exception`` (a retry loop) does not keep it."""


#: What a plugin's code (a driver, planner or scheduler) may raise and the lab survives: any error, and
#: ``SystemExit`` too — an instrument's SDK that calls ``sys.exit`` must fail its step, not end the lab — and
#: ``Interrupted``, which the lab's own Ctrl-C raised in it. Never ``KeyboardInterrupt``: that is the user's Ctrl-C.
PLUGIN_ERRORS: tuple[type[BaseException], ...] = (Exception, SystemExit, Interrupted)


class TwinError(Exception):
    """Root of every error labtwin raises on purpose. It crosses a process pool whole (a bench's or a sweep's
    worker): pickling rebuilds it from its message and attributes, not by calling its ``__init__`` again, which
    most subclasses give other arguments than the message."""

    def __reduce__(self) -> tuple[Any, ...]:
        return _rebuilt, (type(self), self.args, self.__dict__)


def _rebuilt(cls: type[TwinError], args: tuple, state: dict[str, Any]) -> TwinError:
    error = cls.__new__(cls)
    error.args = args
    error.__dict__.update(state)
    return error


class ScenarioError(TwinError):
    """A scenario file is malformed; ``problems`` lists each one with its field path."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = problems
        shown = [p if len(p) <= 500 else p[:499] + "…" for p in problems[:20]]
        if len(problems) > 20:
            shown.append(f"… and {len(problems) - 20} more")
        lines = "\n".join(f"  - {p}" for p in shown)
        super().__init__(f"{source}: {counted(len(problems), 'problem', 'problems')}\n{lines}")


class DriverError(TwinError):
    """A device driver could not be found, loaded, or misbehaved."""


class Refused(DriverError):
    """A driver declines a command: ``infeasible`` — never with these parameters (an interlock, a range the
    instrument cannot reach): the experiment is abandoned at once, the device takes no strike, the planner
    learns the point is infeasible; otherwise only now (warming up, busy): the step is retried later and
    the refusal does not count as one of its attempts."""

    def __init__(self, reason: str, infeasible: bool = True) -> None:
        self.reason, self.infeasible = reason, infeasible
        super().__init__(reason)


class PluginError(TwinError):
    """A planner or scheduler plugin could not be found or loaded."""


class BusError(TwinError):
    """The message bus could not be opened, or a request failed."""


class ClockError(TwinError):
    """The requested clock mode cannot work with this set-up."""


class AccountingError(TwinError):
    """An experiment vanished: it is neither done, abandoned with a reason, nor pending."""
