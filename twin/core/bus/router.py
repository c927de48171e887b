"""A lab's Zenoh router (`twin router`): a session in router mode, no ``zenohd`` needed."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable

import zenoh

from twin.core.bus import security
from twin.core.bus.endpoints import taken
from twin.core.bus.zenoh_config import ZenohOptions
from twin.core.errors import BusError

log = logging.getLogger(__name__)


def run_router(listen: list[str], lease_ms: int = 1000, extra: dict[str, object] | None = None,
               ready: Callable[[str], None] = print, security_dir: str | None = None, insecure: bool = False) -> None:
    """A Zenoh router — a session in router mode, no ``zenohd`` needed — until SIGINT or SIGTERM.

    ``security_dir``: the lab's security directory; the router then requires a client certificate from the
    lab's CA and enforces the lab's access control (``twin.core.bus.security``)."""
    extra = dict(extra or {})
    if security_dir is not None:
        extra.update(security.router_config(security_dir, security.lab_of(security_dir)))
    # its endpoints checked before what listening on them would mean
    options = ZenohOptions(mode="router", listen=listen, connect=[], lease_ms=lease_ms, extra=extra)
    for warning in security.check_listen(listen, secure=security_dir is not None, insecure=insecure,
                                         what="twin router"):
        log.warning("%s", warning)
    try:
        session = zenoh.open(options.config())
    except Exception as exc:
        if taken(exc):
            raise BusError(f"the router could not listen: {taken(exc)}") from None
        raise BusError(f"the router could not listen on {listen}: {exc}") from exc
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        ready(f"router {session.zid()} listening on {', '.join(listen)}")
        while not stop.wait(0.2):  # a signal may land on one of Zenoh's threads: poll, do not block
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        session.close()
