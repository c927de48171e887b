"""A file written whole or not at all."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def written_whole(path: Path) -> Iterator[Path]:
    """Yields ``.<name>.partial`` beside ``path`` to write into; renamed to ``path`` when the block ends, removed if
    it raises (Ctrl-C, a full disk): no half-written file is ever left under the name, nor over an earlier one."""
    partial = path.with_name(f".{path.name}.partial")
    try:
        yield partial
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
