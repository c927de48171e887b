"""The command line's consoles and log lines, showing text from elsewhere with ``twin.core.printable``."""

from __future__ import annotations

import logging
from typing import Any

from rich.console import Console
from rich.text import Text

from twin.core.printable import printable

FORMAT = "%(levelname)s %(name)s: %(message)s"


class PrintableConsole(Console):
    """A rich console that shows the control characters of the text it is given as escapes (rich's own styling
    is added after, so it still colours a terminal)."""

    def render_str(self, text: str, **options: Any) -> Text:
        return super().render_str(printable(text), **options)


class PrintableFormatter(logging.Formatter):
    """Control characters escaped, and every line of a record after its first indented: a newline in a driver's
    error cannot start a line that reads as a log line of its own (``WARNING twin.alerts: ...``)."""

    def format(self, record: logging.LogRecord) -> str:
        return printable(super().format(record)).replace("\n", "\n  ")


def log_to_stderr(level: int) -> None:
    """Log lines at ``level`` and above to stderr, their control characters escaped and their later lines
    indented."""
    handler = logging.StreamHandler()
    handler.setFormatter(PrintableFormatter(FORMAT))
    logging.basicConfig(level=level, handlers=[handler])


# the handler Python falls back on where a command configured none (a bench, `twin whatif`): escaped too
logging.lastResort = logging.StreamHandler()
logging.lastResort.setLevel(logging.WARNING)
logging.lastResort.setFormatter(PrintableFormatter("%(message)s"))
