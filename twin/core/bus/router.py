"""A lab's Zenoh router (`twin router`): a session in router mode, no ``zenohd`` needed."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable
from pathlib import Path

import zenoh

from twin.core.bus import security
from twin.core.bus.endpoints import taken
from twin.core.bus.zenoh_config import ZenohOptions
from twin.core.errors import BusError

log = logging.getLogger(__name__)

#: how often (in 0.2-s ticks) a secure router looks whether its security directory names devices it does not admit
CHECK_TICKS = 10


class AdmittedDevices:
    """The devices a secure router's access control admits — those its security directory named when it started —
    and what to say when ``twin security init`` adds more to the directory: Zenoh reads access control once, so a
    process serving a device added since connects, the router refuses everything it sends, and it never joins."""

    def __init__(self, root: str) -> None:
        self._root = Path(root)
        self._manifest = self._root / security.MANIFEST
        self.lab = security.lab_of(root)
        self.devices = security.devices_of(root, self.lab)
        self._told = set(self.devices)
        self._seen = self._stat()

    def said(self) -> str:
        named = ", ".join(sorted(self.devices)) or "none"
        return (f"lab {self.lab}: admitting its orchestrator, scheduler agent, watchers, operators and devices: "
                f"{named} (as {self._manifest} names them now)")

    def news(self) -> list[str]:
        """A warning for devices the directory names and this router does not admit, once each."""
        seen = self._stat()
        if seen == self._seen:
            return []
        try:
            named = security.devices_of(self._root, self.lab)
        except BusError:
            return []  # gone, or another lab's now: look again at the next check
        self._seen = seen
        new = sorted(named - self._told)
        self._told |= named
        if not new:
            return []
        them = "it" if len(new) == 1 else "them"
        return [f"{self._manifest} now names {'device' if len(new) == 1 else 'devices'} {', '.join(new)} of lab "
                f"{self.lab}, which this router does "
                f"not admit: it reads whom it admits when it starts. A process serving {them} connects, but the "
                f"router refuses all it sends, and the lab never sees {them}. Restart this `twin router` to admit "
                f"{them}: the lab and its devices connect again by themselves (steps running meanwhile fail as "
                f"lost, and are retried)"]

    def _stat(self) -> tuple[int, int] | None:
        try:
            st = self._manifest.stat()
        except OSError:
            return None
        return st.st_mtime_ns, st.st_ino


def run_router(listen: list[str], lease_ms: int = 1000, extra: dict[str, object] | None = None,
               ready: Callable[[str], None] = print, security_dir: str | None = None, insecure: bool = False) -> None:
    """A Zenoh router — a session in router mode, no ``zenohd`` needed — until SIGINT or SIGTERM.

    ``security_dir``: the lab's security directory; the router then requires a client certificate from the
    lab's CA and enforces the lab's access control (``twin.core.bus.security``)."""
    extra = dict(extra or {})
    # read before the config: a device added in between is then warned of, never silently refused
    admitted = None
    if security_dir is not None:
        admitted = AdmittedDevices(security_dir)
        extra.update(security.router_config(security_dir, admitted.lab))
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
        raise BusError(f"the router could not listen on {options.listen}: {exc}") from exc
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        ready(f"router {session.zid()} listening on {', '.join(options.listen)}")
        if admitted is not None:
            log.info("%s", admitted.said())
        ticks = 0
        while not stop.wait(0.2):  # a signal may land on one of Zenoh's threads: poll, do not block
            ticks += 1
            if admitted is not None and ticks % CHECK_TICKS == 0:
                for warning in admitted.news():
                    log.warning("%s", warning)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        session.close()
