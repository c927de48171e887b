"""A Zenoh session of the tests' own, as a client that is not labtwin's opens one."""

import json
import time

import zenoh


def open_session(connect: str | None = None, listen: str | None = None) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps([connect]))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps([listen]))
    return zenoh.open(cfg)


def until_answered(session: zenoh.Session, key: str, wall_s: float = 60.0) -> None:
    """Wait until a queryable on ``key`` answers: then the lab's subscribers are known to ``session`` too (a query
    no queryable is known for returns at once, so the tries are spaced)."""
    deadline = time.monotonic() + wall_s
    while time.monotonic() < deadline:
        if any(reply.ok is not None for reply in session.get(key, timeout=1.0)):
            return
        time.sleep(0.05)
    raise AssertionError(f"nothing answered on {key} in {wall_s:g} s of wall time")
