"""How a Zenoh session is opened: where it listens and connects, in which mode, with which lease; and the check of a
scenario's own Zenoh settings. With ``zenoh_bus.py`` and ``router.py``, the only modules that import zenoh."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import zenoh

from twin.core.bus.endpoints import HOW, not_endpoints, with_ports_chosen
from twin.core.errors import BusError

CONNECT_TIMEOUT_MS = 5_000  # a client waits this long for its router or lab; a typo shows in seconds


@dataclass
class ZenohOptions:
    """Where the session listens and connects. Loopback only unless asked otherwise.

    ``mode`` "auto" is a peer, except for a session that only connects (to a router, to a
    lab): that one is a client, whose traffic the other end routes. A peer with nowhere to
    listen would otherwise receive nothing through a router.
    """

    mode: str = "auto"
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    connect: list[str] = field(default_factory=list)
    lease_ms: int = 1000
    extra: dict[str, object] = field(default_factory=dict)  # other config paths, e.g. TLS
    connect_timeout_ms: int = CONNECT_TIMEOUT_MS
    wait_longer: str = "bus.connect_timeout_ms waits longer"  # how the caller's user waits longer, said on a timeout

    @property
    def is_client(self) -> bool:
        return self.mode == "client" or (self.mode == "auto" and bool(self.connect) and not self.listen)

    def __post_init__(self) -> None:
        for flag, endpoints in (("listen", self.listen), ("connect", self.connect)):
            bad = not_endpoints(endpoints)
            if bad:
                raise BusError(f"{flag}: {', '.join(map(repr, bad))} is not a Zenoh endpoint: {HOW}")
        self.listen = with_ports_chosen(self.listen)

    def config(self, connect_timeout_ms: int | None = None) -> zenoh.Config:
        cfg = zenoh.Config()
        mode = "client" if self.is_client else self.mode if self.mode != "auto" else "peer"
        cfg.insert_json5("mode", json.dumps(mode))
        if mode == "client":  # wait a little for the router or lab to come up rather than fail at once
            cfg.insert_json5("connect/timeout_ms", str(connect_timeout_ms or self.connect_timeout_ms))
        if self.connect:
            # Zenoh backs off to 4 s between tries: a device started before its lab would come up to 4 s late,
            # after the lab's startup wait on a fast clock, and a lab whose router restarted 4 s after it
            cfg.insert_json5("connect/retry", "{period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2}")
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
        cfg.insert_json5("transport/link/tx/lease", str(self.lease_ms))
        cfg.insert_json5("transport/link/tx/keep_alive", "4")
        for path, value in self.extra.items():
            cfg.insert_json5(path, json.dumps(value))
        return cfg


def check_config(extra: dict[str, object]) -> None:
    """Refuse Zenoh config paths or values Zenoh does not take (``bus.zenoh`` in a scenario), by name."""
    for path, value in extra.items():
        try:
            zenoh.Config().insert_json5(path, json.dumps(value))
        except Exception as exc:
            raise BusError(f"bus.zenoh.{path[:80]}: Zenoh refuses {str(json.dumps(value))[:80]} there ({exc}); "
                           "its DEFAULT_CONFIG.json5 lists the paths") from None
