"""A shared lab's control desk: ``labtwin/<lab>/control/<command>`` for a lab of several campaigns.

``status`` without a campaign lists the lab's campaigns; ``submit`` adds one (the text of a campaign file,
``twin submit``) and answers with what `twin validate` would warn of it, its trial experiments' among them; any other command names its campaign (the ``campaign`` field, which may be left out when the
lab has one) and goes to that campaign's own desk (twin/runtime/control.py), which journals it there.
"""

from __future__ import annotations

import json
from typing import Any

from twin.core.messages import json_from_wire

MAX_REQUEST = 1 << 20  # a campaign file is a few KB; scenario files are bounded at 1 MiB


class LabDesk:
    def __init__(self, lab: Any) -> None:
        """``lab``: the ``LiveLab`` it answers for."""
        self.lab = lab

    async def serve(self, key: str, payload: bytes) -> bytes:
        command = key.rsplit("/", 1)[-1]
        try:
            answer = await self._answer(command, payload)
        except ValueError as exc:
            answer = {"ok": False, "error": str(exc)}
        return json.dumps(answer).encode()

    async def _answer(self, command: str, payload: bytes) -> dict[str, Any]:
        if len(payload) > MAX_REQUEST:
            raise ValueError(f"a request of {len(payload)} bytes; at most {MAX_REQUEST}")
        try:
            body = json_from_wire(payload or b"{}")
        except ValueError:
            raise ValueError("the request is not JSON") from None
        if not isinstance(body, dict):
            raise ValueError("the request is not a JSON object")
        if command == "submit":
            return await self.lab.submit(body)
        name = body.pop("campaign", None)
        if command == "status" and name is None:
            return self.lab.status()
        started = self.lab.shared.started
        if name is None:
            if len(started) != 1:
                raise ValueError(f"this lab runs {len(started)} campaigns: name one with --campaign "
                                 f"({', '.join(started) or 'none yet'})")
            name = started[0]
        seat = self.lab.seats.get(name) if isinstance(name, str) else None
        if seat is None or name not in started:
            raise ValueError(f"campaign {str(name)[:64]!r} is not running in this lab "
                             f"({', '.join(started) or 'none yet'})")
        return json.loads(await seat.desk.serve(f"control/{command}", json.dumps(body).encode()))
