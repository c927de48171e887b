"""The core's state changes as decisions on the bus, for observers.

Every ``Note`` the core returns is journalled (``Journal.note``)
and, as a decision, sent on ``labtwin/<lab>/campaign/<id>/decisions``; the
notes of one ``advance`` travel together as one message. ``history``
answers a watcher that joins late with what was observed so far, in pages
(``{"after": N}`` asks for the page after the first N; the answer says where
the next one starts, which campaign it is, and whether it shares its lab). Where security is on, only the lab's watcher and
orchestrator identities may ask (``twin.core.bus.security``).
"""

from __future__ import annotations

import itertools
import json
from typing import Any

from twin.core import keys
from twin.core.bus import Bus
from twin.campaign import Note
from twin.core.clock import LabClock
from twin.campaign.journal import Journal
from twin.campaign.journal_read import as_messages, decision_id
from twin.core.messages import Kind, fingerprint, json_from_wire, pack

SENDER = "orchestrator"
PAGE_ROWS = 500
PAGE_BYTES = 256 * 1024  # well under the largest message a receiver accepts


class DecisionStream:
    def __init__(self, journal: Journal, bus: Bus, clock: LabClock, lab: str, campaign_id: str) -> None:
        self.journal, self.bus, self.clock, self.campaign_id = journal, bus, clock, campaign_id
        self.key = keys.campaign(lab, campaign_id, "decisions")
        self.history_key = keys.campaign(lab, campaign_id, "history")
        self._outbox: list[dict[str, Any]] = []
        self._accepted: list[bytes] = []  # the results and readings accepted since the last message, as kept
        self._due = False  # a result among them: a message goes now
        self._batches = itertools.count(1)
        self.shared = False  # one campaign of a lab several share (a watcher then draws each on its own)
        self.run = ""  # which run of the lab this is, the same across its resumes (a watcher tells a new run apart)

    def add(self, n: Note, seq: int) -> None:
        self._outbox.append({"id": decision_id(seq), "t_lab": n.t_lab, "what": n.kind, "detail": {
            "experiment": n.experiment, "task": n.task, "attempt": n.attempt, "device": n.device, "info": n.detail}})

    def accepted(self, kept_payload: bytes, reading: bool = False) -> None:
        """A device's result or reading the campaign took (as journalled): named in the next message (fingerprinted
        only if someone watches). A result sends one at once; readings ride with the next decisions (one of their
        own for each would double the messages of a lab that reports every few lab-minutes)."""
        self._accepted.append(kept_payload)
        self._due = self._due or not reading

    def publish(self) -> None:
        """Send the decisions added so far as one message, with the results and readings accepted meanwhile
        (``accepted``)."""
        if not self._outbox and not self._due:
            return
        self._due = False
        if not self.bus.wants(self.key):  # nobody watches: the journal keeps the decisions, skip encoding them
            self._outbox.clear()
            self._accepted.clear()
            return
        items, self._outbox = self._outbox, []
        accepted, self._accepted = [fingerprint(p) for p in self._accepted], []
        body = {"what": "decisions", "detail": {"items": items, "accepted": accepted}}
        self.bus.publish(self.key, pack(Kind.DECISION, body, id=f"{SENDER}:b{next(self._batches)}", sender=SENDER,
                                        t_lab=items[0]["t_lab"] if items else self.clock.now(),
                                        campaign=self.campaign_id))

    async def history(self, key: str, payload: bytes) -> bytes:
        """A page of what was observed so far, for a watcher that joins late (``twin watch``)."""
        try:
            after = int(json_from_wire(payload or b"{}").get("after", 0))
        except (ValueError, TypeError, AttributeError):
            return json.dumps({"error": 'ask with {"after": N}, N a whole number'}).encode()
        if after == 0:
            # let messages already sent to us land in the journal first (~50 ms of wall time): the
            # watcher's subscription may have missed them, and they must be in the history then
            await self.clock.sleep(0.05 * (1.0 if self.clock.is_virtual else self.clock.speed))
            self.journal.flush()
        end = min(max(0, after), 1 << 62)  # SQLite's OFFSET is a 64-bit integer
        # this page's rows only, and one more to know whether there is a next: a late watcher of a long campaign
        # pages through all of it, and the lab's loop waits while a page is read
        rows = self.journal.rows(end, PAGE_ROWS + 1)
        page: list[str] = []
        size = 0
        for item in as_messages(rows[:PAGE_ROWS]):
            if page and size + len(item) > PAGE_BYTES:
                break
            page.append(item)
            size += len(item)
        end += len(page)
        return json.dumps({"items": page, "next": end if len(rows) > len(page) else None,
                           "campaign": self.campaign_id, "shared": self.shared, "run": self.run}).encode()
