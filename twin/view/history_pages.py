"""A lab's history as a watcher reads it: page after page from ``labtwin/<lab>/campaign/<id>/history``, each page
checked, and which run of the lab a page belongs to."""

from __future__ import annotations

import json
import logging
import re

from twin.core import keys
from twin.core.bus import Bus, NoReplyError
from twin.core.clock import LabClock
from twin.core.errors import TwinError
from twin.core.messages import json_from_wire
from twin.scenario.spec import NAME

log = logging.getLogger("twin.view.watch")  # what the watch says, under the name it has always had


async def read_history(bus: Bus, clock: LabClock, lab: str, first: dict, on_message) -> None:
    """A lab's history from its first page on; one that stops answering, or answers with a malformed page, is
    recorded from now on."""
    try:
        await pages(bus, clock, keys.campaign(lab, "*", "history"), first, on_message)
    except (NoReplyError, ValueError, TwinError) as exc:
        log.warning("lab %r did not give all of its history (%s): recording it from now on", lab, exc)


async def pages(bus: Bus, clock: LabClock, key: str, page: dict, on_message) -> None:
    """Feed a history's items, page after page, from ``page`` on (a checked page: :func:`history_page`)."""
    while True:
        for payload in page["items"]:
            on_message("", payload)
        after = page["next"]
        if after is None:
            return
        page = history_page(await bus.request(key, json.dumps({"after": after}).encode(), timeout=2.0 * clock.speed),
                            after)


def another_run(first: dict | None, again: dict) -> bool:
    """Whether the lab came back with another run than the one the watch began with (a resume keeps its run)."""
    before, now = (first or {}).get("run"), again.get("run")
    return bool(before) and bool(now) and before != now


class MalformedPage(ValueError):
    """A history page that is not one a lab sends: a rogue or broken server answered for the lab."""


def history_page(raw: bytes, after: int) -> dict:
    """A page of a campaign's history, as asked for with ``{"after": after}``, checked: its items are messages
    (text), its ``next`` lies beyond ``after`` (a page that does not move on would be asked for forever), its
    campaign is a name. Raises :class:`MalformedPage` saying what is wrong."""
    try:
        page = json_from_wire(raw)
    except ValueError:
        raise MalformedPage(f"not JSON: {bytes(raw[:40])!r}") from None
    if not isinstance(page, dict):
        raise MalformedPage(f"not a page but a {type(page).__name__}")
    if "error" in page:
        raise MalformedPage(f"an error: {str(page['error'])[:120]}")
    items, following = page.get("items", []), page.get("next")
    if not isinstance(items, list) or not all(isinstance(item, str) for item in items):
        raise MalformedPage("its items are not a list of messages")
    if following is not None and (isinstance(following, bool) or not isinstance(following, int)
                                  or following <= after or not items):
        raise MalformedPage(f"its next page ({str(following)[:40]}) does not follow page {after}")
    campaign = page.get("campaign", "")
    if not isinstance(campaign, str) or not isinstance(page.get("shared", False), bool) or \
            (page.get("shared") and not re.match(NAME, campaign)):
        raise MalformedPage(f"its campaign ({str(campaign)[:40]!r}) is not a campaign's name")
    if not isinstance(page.get("run", ""), str):
        raise MalformedPage(f"its run ({str(page.get('run'))[:40]}) is not a run's name")
    return {**page, "items": items, "next": following}
