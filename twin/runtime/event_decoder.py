"""A device's message off the bus, decoded for the campaign core: a ``DeviceMessage``, or an ``InvalidInput``
naming the sender and the reason; a device that keeps another clock is told of once."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from twin.campaign import DeviceMessage, InvalidInput
from twin.core import keys
from twin.core.clock import LabClock
from twin.core.messages import Dropped, InvalidMessage, Kind, decode, excerpt, kept
from twin.view.observer import WATCHED

log = logging.getLogger(__name__)

MAX_HELD = 10_000
CLOCK_OFF_S, CLOCK_OFF_WALL_S = 60.0, 5.0  # a device stamping times further than both from the lab's: another clock


class EventDecoder:
    """A device's message off the bus: a ``DeviceMessage``, or an ``InvalidInput`` that names the sender and the
    reason. With ``clock`` (a live lab's), a device whose messages say a lab time far from the lab's is told of
    once: ``on_clock_off(detail)``, and the log.

    What an in-process observer is to be shown of a result or a reading waits until the campaign accepts the
    message (``take``; the campaign shows those it journals): a result forged on a device's key, refused for its
    provenance, is drawn neither live nor in the replay of the journal."""

    def __init__(self, observer: Any = None, clock: LabClock | None = None,
                 on_clock_off: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.observer = observer
        self.dropped = Dropped(log)
        self._clock = clock if clock is not None and not clock.is_virtual else None
        self._on_clock_off, self._clock_off = on_clock_off, set[str]()
        self._held: dict[bytes, dict[str, Any]] = {}  # a message as kept for the journal -> what the observer is shown
        self._overflowed = False

    def take(self) -> dict[bytes, dict[str, Any]]:
        """What the observer is to be shown of the messages decoded since the last call, by the message as the
        campaign journals it (``DeviceMessage.payload``)."""
        held, self._held = self._held, {}
        return held

    def event(self, key: str, payload: bytes) -> DeviceMessage | InvalidInput:
        on_key = keys.device_of(key)
        try:
            env, body = decode(payload, sender_hint=on_key)
        except InvalidMessage as exc:
            self.dropped.said(f"on {key}", exc)
            return InvalidInput(exc.sender, exc.reason, key, excerpt(payload))
        if self._clock is not None and env.sender == on_key and env.sender not in self._clock_off \
                and env.kind != Kind.REJECTED:  # "no clock yet" is one reason to refuse a command
            self._check_time(env.sender, env.t_lab)
        as_kept = kept(env, payload)
        plain = body.to_dict()
        if self.observer is not None and env.kind in WATCHED:
            if len(self._held) < MAX_HELD:
                self._held[as_kept] = {"kind": env.kind, "id": env.id, "sender": env.sender, "task": env.task,
                                    "campaign": env.campaign or "", "t_lab": env.t_lab, "body": plain}
            elif not self._overflowed:  # more before the campaign's next turn: a flood
                self._overflowed = True
                log.warning("viewer: over %d results and readings came between two turns of the campaign; those "
                            "past them are not drawn (the journal has every one it accepts)", MAX_HELD)
        return DeviceMessage(env.kind, env.sender, env.task, env.attempt, plain, as_kept, on_key, env.token,
                             env.campaign or "")

    def _check_time(self, sender: str, t_lab: float) -> None:
        assert self._clock is not None
        now = self._clock.now()
        off = t_lab - now
        if abs(off) <= max(CLOCK_OFF_S, CLOCK_OFF_WALL_S * self._clock.speed) or len(self._clock_off) >= 64:
            return
        self._clock_off.add(sender)
        detail = {"sender": sender, "t_lab": t_lab, "lab_now": round(now, 3), "off_s": round(off, 3)}
        log.warning("%s stamps its messages %+.0f lab-s off the lab's time (t_lab %.1f against %.1f): it keeps "
                    "another clock. t_lab is the lab's time (docs/wire.md, 'Lab time'); the viewer draws what "
                    "it sends at the times it says", sender, off, t_lab, now)
        if self._on_clock_off is not None:
            self._on_clock_off(detail)
