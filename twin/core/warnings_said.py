"""The warnings logged while something is checked, kept to be shown with it (under a file's name by `twin
validate`, in the answer to `twin submit`)."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator


class WarningsSaid(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.said: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.said.append(record.getMessage())


@contextlib.contextmanager
def warnings_said() -> Iterator[WarningsSaid]:
    """A handler on the root logger for the block: what it has kept is in ``.said``."""
    said = WarningsSaid()
    logging.getLogger().addHandler(said)
    try:
        yield said
    finally:  # in-process callers (tests, a notebook) keep no handler of this
        logging.getLogger().removeHandler(said)
