"""Where a bench keeps its journals, recordings and configs: a directory removed when the bench exits."""

from __future__ import annotations

import tempfile
from pathlib import Path

_kept: list[tempfile.TemporaryDirectory] = []  # each removed at exit (or as the bench's process ends)


def scratch() -> Path:
    made = tempfile.TemporaryDirectory(prefix="labtwin-bench-")
    _kept.append(made)
    return Path(made.name)
