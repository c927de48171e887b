"""What a Zenoh endpoint looks like: checked before a session is opened, so a typo is named, not Zenoh's trace."""

from __future__ import annotations

import re
import socket

_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws)/(\[[0-9a-fA-F:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})(#.*)?$"
                       r"|^(unixsock-stream|unixpipe|serial|vsock)/\S+$")
HOW = "write PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447 or tls/lab.example:7447 (port 0-65535)"


def not_endpoints(endpoints: list[str]) -> list[str]:
    """Those of ``endpoints`` that are not Zenoh endpoints (each cut to 80 characters)."""
    bad = []
    for e in endpoints:
        m = _ENDPOINT.match(e) if isinstance(e, str) else None
        if m is None or (m.group(3) is not None and int(m.group(3)) > 65535):
            bad.append(str(e)[:80])
    return bad


def taken(error: Exception) -> str:
    """The endpoint Zenoh could not listen on because something else does ('' if that was not why), said as a
    person would say it: a second lab or router on the port got Zenoh's words and its Rust source paths."""
    m = re.search(r"bound to (\S+?):? .*Address already in use", str(error))
    return (f"{m.group(1)} is taken: another lab, router or program listens there (`ss -ltnp` names it); stop "
            "it, or listen on another port") if m else ""


def with_ports_chosen(endpoints: list[str]) -> list[str]:
    """``endpoints`` with each TCP one on port 0 given a free port now: Zenoh cannot say which it took, and the
    lab's log names the endpoint `twin ctl` and `twin watch` connect to. One that cannot be bound here is left to
    Zenoh, whose error names it."""
    chosen = []
    for e in endpoints:
        m = _ENDPOINT.match(e) if isinstance(e, str) else None
        if m is None or m.group(1) not in ("tcp", "tls") or m.group(3) != "0":
            chosen.append(e)
            continue
        host = m.group(2).strip("[]")
        try:
            family = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0][0]
            with socket.socket(family, socket.SOCK_STREAM) as probe:
                probe.bind((host, 0))
                port = probe.getsockname()[1]
        except OSError:
            chosen.append(e)
            continue
        chosen.append(f"{m.group(1)}/{m.group(2)}:{port}{m.group(4) or ''}")
    return chosen
