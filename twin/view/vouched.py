"""Results and readings a watcher in another process hears from devices, drawn only once their campaign has said
it took them.

A watcher cannot tell an attempt's token, so a result forged on a device's key (on a bus without security) would
look like a measurement, and a reading forged on it like the device's. Each decisions message names the results
and readings its campaign accepted since the one before (``accepted``: their fingerprints,
``twin.core.messages.fingerprint``; readings ride with the next decisions, results send one at once): what is
heard live waits here until it is named (or passes at once if it was named first), and what is never named is
never drawn. A lab whose decisions name nothing (``accepted`` absent: an older labtwin) has everything drawn as it
comes — until a decisions message names something: from then on a decisions message without names (forged on a bus
without security, where anyone can publish on the campaign's keys) changes nothing.
"""

from __future__ import annotations

from collections.abc import Callable

from twin.core.messages import InvalidMessage, decode, fingerprint, json_from_wire, kept

#: What waits to be named, and names not yet heard, kept at most (the oldest go first): forged messages never named
#: would otherwise pile up.
MAX_KEPT = 10_000
HELD = ("result", "telemetry")


class Vouched:
    def __init__(self, feed: Callable[[str, bytes], None]) -> None:
        self.feed = feed
        self._waiting: dict[str, tuple[str, bytes]] = {}  # fingerprint -> the result or reading heard
        self._named: dict[str, None] = {}  # named before they were heard
        self._trusting = False  # the lab names nothing
        self._naming = False  # the lab has named what it accepted: it is never trusted again

    def __call__(self, key: str, payload: bytes) -> None:
        name = _held_as(payload)
        if name == "":
            return  # never drawn
        if name is not None and not self._trusting:
            if name in self._named:
                del self._named[name]
                self.feed(key, payload)
            else:
                _keep(self._waiting, name, (key, payload))
            return
        if b'"decisions"' in payload:
            self._names(payload)
        self.feed(key, payload)

    def _names(self, payload: bytes) -> None:
        """The results a decisions message names: drawn now if heard, else remembered."""
        try:
            env = json_from_wire(payload)
            detail = env["body"]["detail"] if env.get("kind") == "decision" else None
        except (ValueError, KeyError, TypeError, AttributeError):
            return
        if not isinstance(detail, dict) or env["body"].get("what") != "decisions":
            return
        names = detail.get("accepted")
        if names is None:  # a lab that does not name what it accepted
            if self._naming:
                return
            self._trusting = True
            waiting, self._waiting = self._waiting, {}
            for key, result in waiting.values():
                self.feed(key, result)
            return
        self._naming, self._trusting = True, False
        for name in names if isinstance(names, list) else ():
            heard = self._waiting.pop(name, None) if isinstance(name, str) else None
            if heard is not None:
                self.feed(*heard)
            elif isinstance(name, str):
                _keep(self._named, name, None)


def _held_as(payload: bytes) -> str | None:
    """The fingerprint of a result or reading, to be held until named ("" for one no campaign could accept: it
    fails validation); None for anything else."""
    if b'"result"' not in payload and b'"telemetry"' not in payload:
        return None
    try:
        env, _ = decode(payload)
    except InvalidMessage:
        try:
            claimed = json_from_wire(payload)
        except ValueError:
            return None  # not a message: the observer skips it
        return "" if isinstance(claimed, dict) and claimed.get("kind") in HELD else None
    return fingerprint(kept(env, payload)) if env.kind in HELD else None


def _keep(kept_so_far: dict, name: str, value: object) -> None:
    kept_so_far[name] = value
    if len(kept_so_far) > MAX_KEPT:
        del kept_so_far[next(iter(kept_so_far))]
