"""Zenoh key expressions: one lab per prefix (DESIGN.md, "Messages")."""

PREFIX = "labtwin"
LAB_NAME = r"^[A-Za-z0-9_-]{1,64}$"  # a lab's name is one chunk of its every key (no '/', '*', '$') and a directory


def cmd(lab: str, device: str) -> str:
    return f"{PREFIX}/{lab}/dev/{device}/cmd"


def evt(lab: str, device: str = "*") -> str:
    return f"{PREFIX}/{lab}/dev/{device}/evt"


def telemetry(lab: str, device: str = "*") -> str:
    return f"{PREFIX}/{lab}/dev/{device}/telemetry"


def health(lab: str, device: str = "*") -> str:
    return f"{PREFIX}/{lab}/dev/{device}/health"


def alive(lab: str, device: str = "*") -> str:
    return f"{PREFIX}/{lab}/alive/{device}"


def orchestrator(lab: str) -> str:
    """The campaign's liveliness token: devices cancel orphaned steps when it is gone too long."""
    return f"{PREFIX}/{lab}/orchestrator/alive"


def claim(lab: str, part: str, stamp: str = "*") -> str:
    """A process's claim on a part of a lab it is about to serve (twin/runtime/lab_claim.py); ``part``:
    ``orchestrator``, ``agent`` or ``dev/<device>``."""
    return f"{PREFIX}/{lab}/claim/{part}/{stamp}"


def clock(lab: str) -> str:
    """The lab's clock: its anchor, answered and published (twin/runtime/labtime.py)."""
    return f"{PREFIX}/{lab}/clock"


def control(lab: str, command: str = "*") -> str:
    """An operator's requests to the lab's campaign (``twin ctl``): status, pause, resume, abort, retry, stop."""
    return f"{PREFIX}/{lab}/control/{command}"


def campaign(lab: str, campaign_id: str, topic: str = "**") -> str:
    return f"{PREFIX}/{lab}/campaign/{campaign_id}/{topic}"


def lab_of(key: str) -> str:
    """The lab in any ``labtwin/<lab>/...`` key."""
    return key.split("/")[1]


def device_of(key: str) -> str:
    """The device name in a ``.../dev/<device>/...`` or ``.../alive/<device>`` key."""
    parts = key.split("/")
    return parts[3] if parts[2] in ("dev", "alive") else ""
