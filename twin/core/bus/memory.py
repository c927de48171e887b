"""The in-memory bus: Zenoh's semantics with no sockets, for tests and RL training.

Every delivery is a ``call_soon`` on the running loop, so a message in flight
keeps the loop busy and the virtual clock never jumps past it.
"""

from __future__ import annotations

import asyncio
import logging
from collections import defaultdict

from twin.core.bus.base import Closable, Handler, NoReplyError, Replier, TokenHandler, key_matches, keys_intersect
from twin.core.errors import BusError

log = logging.getLogger(__name__)


class _Entry:
    __slots__ = ("keyexpr", "fn", "registry", "closed")

    def __init__(self, keyexpr: str, fn, registry: list) -> None:
        self.keyexpr, self.fn, self.registry, self.closed = keyexpr, fn, registry, False
        registry.append(self)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.registry.remove(self)


class _Token:
    def __init__(self, bus: MemoryBus, key: str) -> None:
        self._bus, self.key, self.closed = bus, key, False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._bus._token_gone(self.key)


class MemoryBus:
    """One process, one loop. Several ``MemoryBus`` objects may share a ``hub``."""

    def __init__(self, hub: MemoryHub | None = None) -> None:
        self._hub = hub or MemoryHub()

    @property
    def listening(self) -> list[str]:
        return []

    async def start(self) -> None:
        self._hub.loop = asyncio.get_running_loop()

    async def close(self) -> None:
        pass

    def publish(self, key: str, payload: bytes) -> None:
        hub = self._hub
        subs = hub.route_cache.get(key)
        if subs is None:
            subs = hub.route_cache[key] = [s for s in hub.subs if key_matches(s.keyexpr, key)]
        if subs:
            hub.loop.call_soon(_deliver_all, subs, key, payload)

    def wants(self, key: str) -> bool:
        hub = self._hub
        subs = hub.route_cache.get(key)
        if subs is None:
            subs = hub.route_cache[key] = [s for s in hub.subs if key_matches(s.keyexpr, key)]
        return bool(subs)

    def router_lost(self) -> bool:
        return False

    def subscribe(self, keyexpr: str, handler: Handler) -> Closable:
        self._hub.route_cache.clear()
        entry = _Entry(keyexpr, handler, self._hub.subs)
        return _Uncache(entry, self._hub)

    def serve(self, keyexpr: str, replier: Replier) -> Closable:
        return _Entry(keyexpr, replier, self._hub.queryables)

    async def request(self, key: str, payload: bytes, timeout: float) -> bytes:
        repliers = [q for q in self._hub.queryables if keys_intersect(q.keyexpr, key)]
        if not repliers:
            raise NoReplyError(f"no replier serves {key!r}: is the device or service running?")
        try:
            async with asyncio.timeout(timeout):
                return await repliers[0].fn(key, payload)
        except TimeoutError:
            raise NoReplyError(f"no reply to {key!r} within {timeout} lab-seconds") from None
        except Exception as exc:  # as over Zenoh: the requester gets the replier's failure as the bus's error
            log.error("replier for %s failed", key, exc_info=True)
            raise BusError(f"the replier for {key!r} failed: {exc}") from exc

    def declare_token(self, key: str) -> Closable:
        hub = self._hub
        hub.tokens[key] += 1
        if hub.tokens[key] == 1:
            for w in list(hub.watchers):
                if key_matches(w.keyexpr, key):
                    hub.loop.call_soon(_deliver, w, key, True)
        return _Token(self, key)

    def _token_gone(self, key: str) -> None:
        hub = self._hub
        hub.tokens[key] -= 1
        if hub.tokens[key] == 0:
            del hub.tokens[key]
            for w in list(hub.watchers):
                if key_matches(w.keyexpr, key):
                    hub.loop.call_soon(_deliver, w, key, False)

    def watch_tokens(self, keyexpr: str, handler: TokenHandler) -> Closable:
        hub = self._hub
        entry = _Entry(keyexpr, handler, hub.watchers)
        for key in sorted(hub.tokens):
            if key_matches(keyexpr, key):
                hub.loop.call_soon(_deliver, entry, key, True)
        return entry


def _deliver_all(entries: list[_Entry], key: str, value) -> None:
    for entry in entries:
        if not entry.closed:
            entry.fn(key, value)


def _deliver(entry: _Entry, key: str, value) -> None:
    if not entry.closed:
        entry.fn(key, value)


class _Uncache:
    def __init__(self, entry: _Entry, hub: MemoryHub) -> None:
        self._entry, self._hub = entry, hub

    def close(self) -> None:
        self._entry.close()
        self._hub.route_cache.clear()


class MemoryHub:
    """What the buses of one process share: their subscriptions, repliers and tokens."""

    def __init__(self) -> None:
        self.loop: asyncio.AbstractEventLoop | None = None
        self.subs: list[_Entry] = []
        self.queryables: list[_Entry] = []
        self.watchers: list[_Entry] = []
        self.tokens: dict[str, int] = defaultdict(int)
        self.route_cache: dict[str, list[_Entry]] = {}
