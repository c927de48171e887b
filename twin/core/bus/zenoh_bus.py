"""The Zenoh bus, the default. With ``zenoh_config.py`` (how a session is opened) and ``router.py``, the only
modules that import zenoh.

Zenoh calls back on its own threads. Each callback only appends to one inbox
and, if no drain is scheduled yet, schedules one with ``call_soon_threadsafe``:
the loop then drains the whole batch at once, so the cost of crossing threads
is paid per batch, not per message.

On a virtual clock every message sent to a subscriber of this process is held
on the clock until it is delivered, and a batch is delivered in publish order
only when nothing more is in flight: time never jumps past a message, and runs
are bit-for-bit repeatable.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import os
import struct
import time
from collections import defaultdict, deque
from collections.abc import Callable
from typing import Any

import zenoh

from twin.core.bus.base import Closable, Handler, NoReplyError, Replier, TokenHandler, key_matches, keys_intersect
from twin.core.bus.endpoints import taken
from twin.core.bus.zenoh_config import ZenohOptions
from twin.core import log_floods
from twin.core.clock import LabClock
from twin.core.tasks import kept
from twin.core.errors import BusError, ClockError

log = logging.getLogger(__name__)
_STAMP = struct.Struct("<QQ")  # publish order, and the id of the bus that sent it
_LAST = 1 << 63  # deliveries from elsewhere sort after local ones of the same batch
_CONNECT_TRY_MS = 1_000  # a longer wait is made of tries this long, so that Ctrl-C is seen between them


class _Declared:
    """A queryable or token watcher. It exists before its Zenoh object, whose callbacks may
    fire on Zenoh's threads before ``declare_*`` has even returned."""

    def __init__(self, bus: ZenohBus, keyexpr: str, fn, sid: int, registry: list | None) -> None:
        self.keyexpr, self._bus, self.fn, self.sid, self._registry = keyexpr, bus, fn, sid, registry
        self._zobj: Any = None
        self.closed = False
        if registry is not None:
            registry.append(self)
            bus._routes.clear()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self._registry is not None:
            self._registry.remove(self)
            self._bus._routes.clear()
        if self._zobj is not None and not self._bus._session.is_closed():
            self._zobj.undeclare()


class _Group:
    """One Zenoh subscriber and the local subscriptions it feeds."""

    def __init__(self, keyexpr: str) -> None:
        self.keyexpr = keyexpr
        self.zsub: Any = None
        self.subs: list[Any] = []


class _Subscription:
    def __init__(self, bus: ZenohBus, group: _Group, fn: Handler, sid: int) -> None:
        self._bus, self.group, self.fn, self.sid = bus, group, fn, sid
        self.keyexpr, self.closed = group.keyexpr, False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._bus._unsubscribe(self)


class _Token:
    def __init__(self, bus: ZenohBus, key: str) -> None:
        self._bus, self.key, self.closed = bus, key, False
        bus._hold_for_watchers(key, alive=True)
        self._token = bus._session.liveliness().declare_token(key)
        bus._local_tokens.append(key)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._bus._local_tokens.remove(self.key)
        self._bus._hold_for_watchers(self.key, alive=False)
        if not self._bus._session.is_closed():
            self._token.undeclare()


class ZenohBus:
    def __init__(self, clock: LabClock, options: ZenohOptions | None = None) -> None:
        self.options = options or ZenohOptions()
        if clock.is_virtual and self.options.connect:
            raise ClockError(
                "a virtual clock cannot see messages in flight between processes: "
                f"this bus connects to {self.options.connect}. Use --clock scaled or wall "
                "for a lab spread over processes, or drop the connect endpoints."
            )
        self._clock = clock
        self._virtual = clock.is_virtual
        self._session: zenoh.Session | None = None
        self._had_router = False  # this session has reached a router (which may go and come back)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._inbox: deque = deque()
        self._wake_pending = False
        self._batch: list = []
        self._seq = itertools.count(1)
        # another labtwin process stamps its messages too: only this bus's own are held on the clock and ordered
        self._bus_id = int.from_bytes(os.urandom(8), "little")
        self._zid: Any = None  # the session's Zenoh id, once open
        self._ids = itertools.count()
        self._groups: dict[str, _Group] = {}
        self._queryables: list[_Declared] = []
        self._watchers: list[_Declared] = []
        self._local_tokens: list[str] = []
        self._token_seq: dict[tuple[str, bool], int] = {}
        self._expected_changes: dict[tuple[int, str, bool], int] = defaultdict(int)
        self._routes: dict[str, int] = {}
        self._foreign_attachments = 0
        self._pending_requests: set[asyncio.Future] = set()
        self._answering: set[asyncio.Task] = set()  # replies being made
        self._remove_idle_hook: Callable[[], object] = lambda: None

    @property
    def listening(self) -> list[str]:
        return [] if self.options.is_client else list(self.options.listen)

    # -- life cycle -------------------------------------------------------
    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._remove_idle_hook = self._clock.on_idle(self._deliver_at_idle)
        try:
            self._session = await self._open()
            self._zid = self._session.zid()
            self._had_router = bool(self._session.info.routers_zid())
        except zenoh.ZError as exc:
            if "Unable to connect" in str(exc):
                raise BusError(
                    f"nothing answered at {', '.join(self.options.connect)} within "
                    f"{self.options.connect_timeout_ms / 1000:g} s: is the router (twin router --listen ...) or the "
                    "lab running there, and is the endpoint right (protocol, host, port)?"
                    + self._tls_hint()
                    + (f" {self.options.wait_longer}" if self.options.wait_longer else "")) from None
            if taken(exc):
                raise BusError(taken(exc)) from None
            raise BusError(
                f"could not open a Zenoh session (listen={self.options.listen}, "
                f"connect={self.options.connect}): {exc}. Check that the endpoints are "
                "free and well formed, e.g. tcp/127.0.0.1:7447."
            ) from exc

    def _tls_hint(self) -> str:
        """What else to check when nothing answered at a TLS endpoint."""
        if not any(e.startswith(("tls/", "quic/")) for e in self.options.connect):
            return ""
        if not any(str(k).endswith("connect_certificate") for k in self.options.extra):
            return (" A tls/ endpoint is a lab with security: give its security directory (--security DIR), whose "
                    "certificate the router asks for.")
        return (" Over TLS the host must also be one the router's certificate names: remove DIR/router and run "
                "`twin security init DIR --lab LAB --host HOST ...` to name more (the CA is kept).")

    async def _open(self) -> zenoh.Session:
        """``zenoh.open``; a client's wait for its router or lab in tries of at most a second, with a turn of
        the loop between them: Zenoh's own wait cannot be interrupted, and Ctrl-C (which cancels the task) should
        not have to wait out ``connect_timeout_ms``."""
        opts = self.options
        if not opts.is_client or opts.connect_timeout_ms <= _CONNECT_TRY_MS:
            return zenoh.open(opts.config())
        deadline = time.monotonic() + opts.connect_timeout_ms / 1000  # wall time: Zenoh's wait is wall time
        while True:
            left_ms = round((deadline - time.monotonic()) * 1000)
            try:
                return zenoh.open(opts.config(max(100, min(left_ms, _CONNECT_TRY_MS))))
            except zenoh.ZError as exc:
                if "Unable to connect" not in str(exc) or left_ms <= _CONNECT_TRY_MS:
                    raise
            await asyncio.sleep(0)

    async def close(self) -> None:
        self._remove_idle_hook()
        if self._session is not None and not self._session.is_closed():
            self._session.close()
        for fut in self._pending_requests:
            if not fut.done():
                fut.set_exception(BusError("the bus closed before the reply came"))
        for task in self._answering:  # a replier still at work when the bus closes answers no one
            task.cancel()

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise BusError("the bus is not started: call `await bus.start()` first")
        return self._session

    # -- thread hand-off --------------------------------------------------
    def _post(self, item: tuple) -> None:
        """Runs on Zenoh's threads: one append, at most one wake-up per batch."""
        self._inbox.append(item)
        if not self._wake_pending:
            self._wake_pending = True
            self._loop.call_soon_threadsafe(self._drain)

    def _drain(self) -> None:
        self._wake_pending = False
        inbox, batch = self._inbox, self._batch
        local = 0
        expected = self._expected_changes
        seq_of = self._seq_of
        while inbox:
            item = inbox.popleft()
            if item[0] is None:  # a sample, unpacked here to keep Zenoh's threads short
                sample = item[2]
                seq = seq_of(sample)
                key, payload = str(sample.key_expr), sample.payload.to_bytes()
                local += seq != _LAST
                batch.extend((seq, sub.sid, sub, key, payload, None) for sub in item[1].subs)
                continue
            counted = item[5]
            if counted is True:
                local += 1
            elif counted and expected.get(counted, 0) > 0:
                expected[counted] -= 1
                local += 1
            batch.append(item)
        if self._virtual:
            self._clock.release(local)  # delivered when the loop is next idle
            return
        self._deliver()

    def _deliver_at_idle(self) -> bool:
        """On a virtual clock, all that arrived is delivered at idle points, in publish order."""
        if not self._batch:
            return False
        self._batch.sort(key=lambda it: (it[0], it[1]))
        self._loop.call_soon(self._deliver)
        return True

    def _deliver(self) -> None:
        batch, self._batch = self._batch, []
        for _seq, _sid, entry, key, value, _counted in batch:
            if not entry.closed:
                try:
                    entry.fn(key, value)
                except Exception:
                    log.exception("bus handler for %s failed on %s", entry.keyexpr, key)

    # -- publish / subscribe ----------------------------------------------
    def _local_subscribers(self, key: str) -> int:
        """How many Zenoh subscribers of this session a publication on ``key`` reaches."""
        n = self._routes.get(key)
        if n is None:
            n = self._routes[key] = sum(1 for expr in self._groups if key_matches(expr, key))
        return n

    def publish(self, key: str, payload: bytes) -> None:
        seq = next(self._seq)
        if self._virtual:
            self._clock.hold(self._local_subscribers(key))
        self.session.put(
            key,
            payload,
            congestion_control=zenoh.CongestionControl.BLOCK,
            attachment=_STAMP.pack(seq, self._bus_id),
        )

    def wants(self, key: str) -> bool:
        return True  # a subscriber in another process cannot be ruled out

    def router_lost(self) -> bool:
        if self._session is None:
            return False
        if self._session.info.routers_zid():
            self._had_router = True
            return False
        return self._had_router

    def subscribe(self, keyexpr: str, handler: Handler) -> Closable:
        """Subscribers of one key expression share one Zenoh subscriber and are fanned out here."""
        group = self._groups.get(keyexpr)
        if group is None:
            group = _Group(keyexpr)

            def on_sample(sample: zenoh.Sample) -> None:
                self._post((None, group, sample))

            group.zsub = self.session.declare_subscriber(keyexpr, on_sample)
            self._groups[keyexpr] = group
            self._routes.clear()
        sub = _Subscription(self, group, handler, next(self._ids))
        group.subs.append(sub)
        return sub

    def _unsubscribe(self, sub: _Subscription) -> None:
        group = sub.group
        group.subs.remove(sub)
        if not group.subs:
            del self._groups[group.keyexpr]
            self._routes.clear()
            if not self.session.is_closed():
                group.zsub.undeclare()

    def _seq_of(self, sample: zenoh.Sample | zenoh.Query) -> int:
        """Our publish-order stamp; a message from outside this bus (no attachment, a foreign one, another
        labtwin process's) has none."""
        att = sample.attachment
        if att is None:
            return _LAST
        raw = att.to_bytes()
        if len(raw) != _STAMP.size:
            self._foreign_attachments += 1
            if log_floods.said(self._foreign_attachments):
                log.warning("a message on %s carries a %d-byte attachment that is not a labtwin bus's stamp: "
                            "delivered as from outside (%d so far; the first ten said, then every thousandth)",
                            sample.key_expr, len(raw), self._foreign_attachments)
            return _LAST
        seq, bus_id = _STAMP.unpack(raw)
        return seq if bus_id == self._bus_id else _LAST

    # -- request / reply --------------------------------------------------
    def serve(self, keyexpr: str, replier: Replier) -> Closable:
        def on_query(query: zenoh.Query) -> None:
            seq = self._seq_of(query)
            self._post((seq, entry.sid, entry, str(query.key_expr), (query, seq != _LAST), seq != _LAST))

        async def answer(key: str, query: zenoh.Query, mine: bool) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                reply = await replier(key, payload)
            except Exception as exc:  # the requester gets an error, never silence
                log.exception("replier for %s failed", keyexpr)
                reply, ok = str(exc).encode(), False
            else:
                ok = True
            if self._virtual and mine:  # a reply to another process never comes back to this clock
                self._clock.hold(1)
            with query:
                if ok:
                    query.reply(query.key_expr, reply)
                else:
                    query.reply_err(reply)

        def dispatch(key: str, asked: tuple[zenoh.Query, bool]) -> None:
            kept(self._answering, answer(key, *asked))

        entry = _Declared(self, keyexpr, dispatch, next(self._ids), self._queryables)
        entry._zobj = self.session.declare_queryable(keyexpr, on_query)
        return entry

    async def request(self, key: str, payload: bytes, timeout: float) -> bytes:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future = loop.create_future()
        self._pending_requests.add(fut)
        local = sum(1 for q in self._queryables if keys_intersect(q.keyexpr, key))
        own = self._zid  # replies from this session's queryables were held on the clock; others not
        if self._virtual:
            if not local:
                raise NoReplyError(f"no replier serves {key!r}: is the device or service running?")
            self._clock.hold(local)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                value = ("ok", reply.ok.payload.to_bytes())
            else:
                value = ("err", reply.err.payload.to_bytes())
            replier = reply.replier_id
            loop.call_soon_threadsafe(settle, value, replier is not None and replier.zid == own)

        def on_done() -> None:
            loop.call_soon_threadsafe(settle, ("none", b""), False)

        def settle(value: tuple[str, bytes], counted: bool) -> None:
            if counted and self._virtual:
                self._clock.release(1)
            if not fut.done():
                fut.set_result(value)

        self.session.get(
            key,
            zenoh.handlers.Callback(on_reply, on_done),
            payload=payload,
            attachment=_STAMP.pack(next(self._seq), self._bus_id),
            timeout=max(1.0, timeout / max(self._clock.speed, 1e-9)) if not self._virtual else 60.0,
        )
        try:
            async with asyncio.timeout(timeout):
                status, body = await fut
        except TimeoutError:
            raise NoReplyError(f"no reply to {key!r} within {timeout} lab-seconds") from None
        finally:
            self._pending_requests.discard(fut)
        if status == "ok":
            return body
        if status == "err":
            raise BusError(f"the replier for {key!r} failed: {body.decode(errors='replace')}")
        raise NoReplyError(f"no replier answered {key!r}: is the device or service running?")

    # -- presence ---------------------------------------------------------
    def _hold_for_watchers(self, key: str, alive: bool) -> None:
        """A token change is held on the clock until each local watcher has seen it."""
        self._token_seq[(key, alive)] = next(self._seq)
        if self._virtual:
            watchers = [w for w in self._watchers if key_matches(w.keyexpr, key)]
            for w in watchers:
                self._expected_changes[(w.sid, key, alive)] += 1
            self._clock.hold(len(watchers))

    def declare_token(self, key: str) -> Closable:
        return _Token(self, key)

    def watch_tokens(self, keyexpr: str, handler: TokenHandler) -> Closable:
        token_seq = self._token_seq
        state: dict[str, bool] = {}

        def deliver_changes(key: str, alive: bool) -> None:
            if not alive and key in self._local_tokens:
                # Zenoh counts two remote tokens of one name, but not a local and a remote one: another
                # process's token of this name went, and this session's own is still declared
                return
            if state.get(key) != alive:
                state[key] = alive
                handler(key, alive)

        def on_change(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            alive = sample.kind == zenoh.SampleKind.PUT
            self._post((token_seq.get((key, alive), _LAST), sid, entry, key, alive, (sid, key, alive)))

        entry = _Declared(self, keyexpr, deliver_changes, next(self._ids), self._watchers)
        sid = entry.sid
        entry._zobj = self.session.liveliness().declare_subscriber(keyexpr, on_change, history=True)
        # Zenoh's history may miss a token declared an instant ago in this very
        # session; report local tokens ourselves (repeats are filtered above).
        for key in self._local_tokens:
            if key_matches(keyexpr, key):
                self._post((token_seq[(key, True)], sid, entry, key, True, False))
        return entry
