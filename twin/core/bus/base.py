"""The bus contract every implementation passes (tests/twin/test_bus_contract.py).

Handlers are plain functions called on the event loop's thread, one call per
delivered message, in publish order per sender. They must not block: push the
payload to a queue or start a task.
"""

from __future__ import annotations

import re
from collections.abc import Awaitable, Callable
from functools import lru_cache
from typing import Protocol

from twin.core.errors import BusError

Handler = Callable[[str, bytes], None]
#: ``alive`` is True when a token appears (or already exists), False when it goes.
TokenHandler = Callable[[str, bool], None]
Replier = Callable[[str, bytes], Awaitable[bytes]]


class Closable(Protocol):
    def close(self) -> None: ...


class NoReplyError(BusError):
    """A request found no replier, or none answered in time."""


class Bus(Protocol):
    """Publish/subscribe with wildcards, request/reply, and presence tokens."""

    @property
    def listening(self) -> list[str]:
        """The endpoints another process reaches this bus on, each with its port (none for one in-process)."""
        ...

    async def start(self) -> None: ...

    async def close(self) -> None: ...

    def publish(self, key: str, payload: bytes) -> None: ...

    def wants(self, key: str) -> bool:
        """Whether a message on ``key`` may reach anyone (False only when it surely cannot: skip encoding it)."""
        ...

    def subscribe(self, keyexpr: str, handler: Handler) -> Closable: ...

    def router_lost(self) -> bool:
        """True while the router this session reached the others through is gone (restarting, unreachable): a
        token gone from it then may be gone only from here. A session with no router never loses one."""
        ...

    def serve(self, keyexpr: str, replier: Replier) -> Closable: ...

    async def request(self, key: str, payload: bytes, timeout: float) -> bytes: ...

    def declare_token(self, key: str) -> Closable: ...

    def watch_tokens(self, keyexpr: str, handler: TokenHandler) -> Closable: ...


def _chunk_matches(pattern: str, chunk: str) -> bool:
    if pattern in ("*", chunk):
        return True
    if "*" not in pattern:
        return False
    return re.fullmatch(re.escape(pattern).replace(r"\*", ".*"), chunk) is not None


@lru_cache(maxsize=65536)
def key_matches(keyexpr: str, key: str) -> bool:
    """Zenoh key-expression matching of a concrete ``key``: ``*`` is one chunk, ``**`` any number."""
    pat, chunks = keyexpr.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(pat):
            return j == len(chunks)
        if pat[i] == "**":
            return match(i + 1, j) or (j < len(chunks) and match(i, j + 1))
        return j < len(chunks) and _chunk_matches(pat[i], chunks[j]) and match(i + 1, j + 1)

    return match(0, 0)


@lru_cache(maxsize=4096)
def keys_intersect(a: str, b: str) -> bool:
    """Whether two key expressions (either may hold ``*`` or ``**``) have a key in common: a request with a
    wildcard (``campaign/*/history``) reaches each queryable of a concrete key it covers."""
    pa, pb = a.split("/"), b.split("/")

    def match(i: int, j: int) -> bool:
        if i < len(pa) and pa[i] == "**":
            return match(i + 1, j) or (j < len(pb) and match(i, j + 1))
        if j < len(pb) and pb[j] == "**":
            return match(i, j + 1) or (i < len(pa) and match(i + 1, j))
        if i == len(pa) or j == len(pb):
            return i == len(pa) and j == len(pb)
        return (_chunk_matches(pa[i], pb[j]) or _chunk_matches(pb[j], pa[i])) and match(i + 1, j + 1)

    return match(0, 0)
