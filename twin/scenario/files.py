"""Scenario and job-shop files are untrusted input: read them with bounds before any object is built.

Text must be UTF-8 and at most ``MAX_BYTES``; YAML is parsed by a safe loader
that refuses duplicate keys, nesting deeper than ``MAX_DEPTH`` and documents
whose aliases expand to more than ``MAX_VALUES`` values (a "billion laughs"
file is a few hundred bytes). Every refusal is a ``ScenarioError`` naming the
file, and the line where there is one.
"""

from __future__ import annotations

import difflib
import itertools
import os
import re
import select
import stat
import sys
from pathlib import Path
from typing import Any

import yaml

from twin.core.errors import ScenarioError

MAX_BYTES = 1 << 20  # a scenario is a few KB; the largest public job shops are ~100 KB
MAX_DEPTH = 32
MAX_VALUES = 100_000
MAX_ALIASES = 1_000
_STDIN: dict[str, Any] = {}  # the standard input read, and the stream it was read from
PIPE_WAIT_S = 10.0  # a named pipe nobody writes to is refused after this, not waited on for ever


def _standard_input() -> bytes:
    """Standard input, read once: a command that loads its scenario again (a bench, once per shop) gets the same
    text, not an empty stream (a new stream, a test's, is read afresh)."""
    if _STDIN.get("stream") is not sys.stdin:
        _STDIN.update(stream=sys.stdin, data=sys.stdin.buffer.read(MAX_BYTES + 1))
    return _STDIN["data"]


def not_a_file(path: str | Path) -> str:
    """Why ``path``, which exists, cannot be read as a file — a directory, a named pipe (which would block its
    reader until someone writes), a device — or '' for a regular file or none at all."""
    try:
        mode = Path(path).stat().st_mode
    except OSError:
        return ""
    if stat.S_ISREG(mode):
        return ""
    kind = "a directory" if stat.S_ISDIR(mode) else "a named pipe" if stat.S_ISFIFO(mode) else "a device or socket"
    return f"is {kind}, not a file"


def read_text(path: str | Path, what: str = "scenario") -> str:
    """The file's text: refused (with what to do) if missing, a directory, too large, or not UTF-8. ``-`` is
    standard input (its relative paths are then the current directory's)."""
    path = Path(path)
    where = str(path)
    try:
        if where == "-":
            data = _standard_input()
        elif path.is_dir():
            raise ScenarioError(where, [f"is a directory: give a {what} file"])
        elif stat.S_ISFIFO(path.stat().st_mode):
            data = _from_pipe(path, where, what)
        else:
            with path.open("rb") as f:
                data = f.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise ScenarioError(where, [f"file not found: {nearest_file(path) or 'check the path'} ({what} files are "
                                    "usually in scenarios/)"]) from None
    except OSError as exc:
        raise ScenarioError(where, [f"cannot be read: {exc.strerror or exc}"]) from None
    if len(data) > MAX_BYTES:
        raise ScenarioError(where, [f"larger than {MAX_BYTES // 1024} KiB: a {what} file is text of a few KB; "
                                    "is this the right file?"])
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        kind = "UTF-16 text" if data[:2] in (b"\xff\xfe", b"\xfe\xff") else "binary data, or text in another encoding"
        raise ScenarioError(where, [f"not UTF-8 text (byte {exc.start} is {data[exc.start]:#04x}; it looks like {kind}): "
                                    "save it as UTF-8"]) from None
    return text.removeprefix("\ufeff")  # the byte-order mark Windows editors put first


def nearest_file(path: Path) -> str:
    """'did you mean X?' for a file beside where ``path`` points whose name is close to its (a letter off, another
    extension) or the one that begins with its (flaky.zip: flaky_scheduler.zip), or ''."""
    try:
        files = [p for p in itertools.islice(path.parent.iterdir(), 1000) if p.is_file()]
    except OSError:  # its directory is missing too, or cannot be listed
        return ""
    close = difflib.get_close_matches(path.name, [p.name for p in files], n=1, cutoff=0.75)
    longer = [p.name for p in files if p.suffix == path.suffix and p.stem.startswith(path.stem)]
    meant = close[0] if close else longer[0] if len(longer) == 1 else ""
    return f"did you mean {path.parent / meant}?" if meant else ""


def _from_pipe(path: Path, where: str, what: str) -> bytes:
    """What a named pipe (``<(...)``, a mkfifo) holds, up to ``MAX_BYTES + 1``; one that nobody writes to within
    ``PIPE_WAIT_S`` (at the start, or since what it last wrote) is refused: a blocking open would wait for a
    writer for ever."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        chunks: list[bytes] = []
        size = 0
        while size <= MAX_BYTES:
            if not select.select([fd], [], [], PIPE_WAIT_S)[0]:
                raise ScenarioError(where, [f"is a named pipe that nothing wrote to within {PIPE_WAIT_S:g} s: give "
                                            f"a {what} file, or write it into the pipe"])
            chunk = os.read(fd, 1 << 16)
            if not chunk:  # its writer closed it: the whole text
                break
            chunks.append(chunk)
            size += len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def read_yaml(path: str | Path) -> Any:
    """The YAML document in ``path``, as plain Python data, read within the bounds above."""
    return parse_yaml(read_text(path), str(path))


def parse_yaml(text: str, path: str = "<text>", what: str = "a scenario or campaign") -> Any:
    """The YAML document ``text`` (a file's, or one sent over the bus), within the bounds above; ``what`` it is,
    for the errors."""
    if len(text.encode()) > MAX_BYTES:
        raise ScenarioError(path, [f"larger than {MAX_BYTES // 1024} KiB, far more than {what} needs"])
    try:
        loader = _BoundedLoader(text, what)
        try:
            node = loader.get_single_node()
            if node is None:
                return None
            _count_values(node, str(path))
            return loader.construct_document(node)
        finally:
            loader.dispose()
    except ScenarioError as exc:
        raise ScenarioError(str(path), exc.problems) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = str(getattr(exc, "problem", None) or exc)[:200]
        raise ScenarioError(str(path), [f"{where}not valid YAML: {problem}"]) from None


class NumbersLoader(yaml.SafeLoader):
    """PyYAML's safe loader, with YAML 1.2's floats: PyYAML reads YAML 1.1, whose floats need a dot and a signed
    exponent, so ``1e3`` and ``2.5e-4`` were text (and refused as "not a valid number")."""


NumbersLoader.add_implicit_resolver("tag:yaml.org,2002:float",
                                    re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"), list("-+0123456789"))


def yaml_value(text: str) -> Any:
    """A value given on the command line (``--set``, ``--vary``), read as the same text in a scenario file is, within
    the same bounds (3,000 ``[`` was a RecursionError); what cannot be read raises ``ScenarioError``."""
    return parse_yaml(text, "the value", "a value given on the command line")


class _BoundedLoader(NumbersLoader):
    def __init__(self, stream: str, what: str) -> None:
        super().__init__(stream)
        self.what = what
        self._depth = 0
        self._aliases = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_ALIASES:
                raise _refused(self, f"more than {MAX_ALIASES} aliases (*name)")
            return super().compose_node(parent, index)
        self._depth += 1
        if self._depth > MAX_DEPTH:
            raise _refused(self, f"nested more than {MAX_DEPTH} levels deep")
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, tuple[int, int]] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                at = (key_node.start_mark.line + 1, key_node.start_mark.column + 1)
                try:
                    first = seen.setdefault(key, at)
                except TypeError:
                    continue  # an unhashable key: the base class says so
                if first != at:  # on one line too: {a: 1, a: 2}
                    where = f"line {at[0]}" if first[0] != at[0] else f"line {at[0]}, column {at[1]}"
                    before = f"on line {first[0]}" if first[0] != at[0] else f"at column {first[1]}"
                    raise ScenarioError("", [f"{where}: key {_short(key)} is given twice (first {before}); YAML "
                                             "would keep only the last one"])
        return super().construct_mapping(node, deep)


def _refused(loader: _BoundedLoader, why: str) -> ScenarioError:
    mark = loader.peek_event().start_mark
    return ScenarioError("", [f"line {mark.line + 1}: {why}; {loader.what} does not need that"])


def _count_values(root: Any, where: str) -> None:
    """How many values the document holds once every alias is expanded: refused above ``MAX_VALUES``."""
    sizes: dict[int, int] = {}

    def size(node: Any) -> int:
        known = sizes.get(id(node))
        if known is not None:
            return known
        sizes[id(node)] = 1  # a node that contains itself counts once (PyYAML refuses it later anyway)
        if isinstance(node, yaml.SequenceNode):
            n = 1 + sum(size(c) for c in node.value)
        elif isinstance(node, yaml.MappingNode):
            n = 1 + sum(size(k) + size(v) for k, v in node.value)
        else:
            n = 1
        sizes[id(node)] = min(n, MAX_VALUES + 1)
        return sizes[id(node)]

    if size(root) > MAX_VALUES:
        raise ScenarioError(where, [f"its aliases expand to more than {MAX_VALUES:,} values (a YAML alias bomb?); "
                                    "write the values out, or use fewer anchors"])


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"
