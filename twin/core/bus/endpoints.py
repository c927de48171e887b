"""What a Zenoh endpoint looks like: checked before a session is opened, so a typo is named, not Zenoh's trace."""

from __future__ import annotations

import re

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
