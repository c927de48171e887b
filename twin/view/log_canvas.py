"""`twin watch --log`: the viewer's log of decisions and faults as lines on a terminal, for a lab watched without a
display. A canvas that prints the log's rows (each dispatch, a debug row, left out) and hands every row on to a
recording's canvas, if there is one."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from twin.core.printable import printable


def log_line(path: str, t: float, text: str, level: str) -> str:
    """One row of a log as a line: lab time, level, the campaign of a lab several share, and the text."""
    campaign = path.split("/")[1] + ": " if path.startswith("campaigns/") else ""
    return f"{t / 3600:9.3f} h  {level:<5}  {campaign}{printable(text)}"


class LogCanvas:
    def __init__(self, write: Callable[[str], None], inner: Any = None) -> None:
        self.write, self.inner = write, inner

    def text(self, path: str, t: float, text: str, level: str) -> None:
        if path.endswith("log") and level != "DEBUG":
            self.write(log_line(path, t, text, level))
        if self.inner is not None:
            self.inner.text(path, t, text, level)

    def __getattr__(self, name: str) -> Any:
        """Every other row goes to the recording's canvas as it is, or nowhere."""
        inner = self.__dict__.get("inner")
        return _nothing if inner is None else getattr(inner, name)


def _nothing(*args: Any, **kwargs: Any) -> None:
    return None


class Unrecorded:
    """What a watch that only prints has where a recording goes: nothing to send, save or serve."""

    def __init__(self) -> None:
        self.before_close: list[Callable[[], None]] = []
        self.messages: list[str] = []
        self.url, self.server = "", None

    def close(self) -> None:
        for draw in self.before_close:
            draw()

    def lay_out(self, campaigns: list[str]) -> None:
        return None

    def stop_serving(self) -> None:
        return None
