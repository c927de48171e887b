"""``twin ctl``'s side: one request to a running campaign's control desk (twin/runtime/control.py)."""

from __future__ import annotations

import json
from typing import Any

from twin.core import keys
from twin.core.bus import NoReplyError, open_bus
from twin.core.bus.presence import elsewhere, labs_on
from twin.core.bus.security import Identity, session_config
from twin.core.clock import LabClock
from twin.core.errors import TwinError
from twin.core.messages import json_from_wire
from twin.core.printable import printable


def request(lab: str, command: str, body: dict[str, Any], connect: list[str], security_dir: str | None = None,
            wait_s: float = 10.0, connect_timeout_ms: int = 5000) -> dict[str, Any]:
    """The campaign's answer to ``command`` (``{"ok": ..., ...}``); a lab that does not answer is a TwinError that
    says what to check. With security, the request is made as the lab's operator (its certificate)."""
    clock = LabClock("wall")

    async def ask() -> dict[str, Any]:
        extra = session_config(security_dir, Identity("operator", lab)) if security_dir else {}
        bus = open_bus("zenoh", clock, mode="client", listen=[], connect=connect, extra=extra,
                       connect_timeout_ms=connect_timeout_ms, wait_longer="")
        await bus.start()
        try:
            reply = await bus.request(keys.control(lab, command), json.dumps(body).encode(), wait_s)
        except NoReplyError:
            raise TwinError(f"no campaign of lab {lab!r} answered at {', '.join(connect)} "
                            f"({elsewhere(await labs_on(bus))}): is it running on a Zenoh bus that listens there "
                            f"(twin run --listen ...), and is its scenario's lab {lab!r}?") from None
        finally:
            await bus.close()
        try:
            answer = json_from_wire(reply)
        except ValueError as exc:
            answer = str(exc)
        if not isinstance(answer, dict) or not isinstance(answer.get("ok"), bool):
            raise TwinError(f"what answered for lab {lab!r} at {', '.join(connect)} is not a campaign's answer "
                            f"({printable(str(answer)[:80])}): is another program serving the lab's control key? "
                            "`twin security init` lets only the lab answer")
        return answer

    return clock.run(ask())
