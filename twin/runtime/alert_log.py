"""Alerts said in the log. In virtual time, each kind on each device (or experiment) in full the first few times,
then at the 10th, 100th, 1,000th, ... with its count, so that a lab whose steps all fail does not bury the terminal
in the same warning (a device type quarantined again and again said it over 200 times in a campaign of a fraction
of a second). On a live clock each one is said: a person may have to act on it (refill a stock, mend a device).
The journal keeps every one."""

from __future__ import annotations

import logging
from collections import Counter
from typing import Any

from twin.campaign.events import ALERT_LOGGER, alert_text

log = logging.getLogger(ALERT_LOGGER)

#: How many times an alert is said in full before only its 10th, 100th, ... are.
IN_FULL = 3


class AlertLog:
    def __init__(self, virtual: bool = True, crashing: dict[str, tuple[str, float]] | None = None,
                 people: frozenset[str] = frozenset()) -> None:
        """``crashing``: the devices whose type simulates crashes (``faults.mtbc_h``) -> (type, ``faults.restart_s``):
        one of them gone from the bus is said as the crash it most likely is. ``people``: the instances that are
        people, whose steps fail by going unconfirmed."""
        self.virtual = virtual
        self.crashing = crashing or {}
        self.people = people
        self._said: Counter[tuple[str, Any, Any]] = Counter()
        self._away: dict[str, float] = {}  # devices that left the bus: when

    def presence(self, note: Any) -> None:
        """On a live clock, a device that left the bus, and one that came back (its first arrival is no news): a
        person may have a process to restart or a host to mend; and a device type usable again after it was said to
        be unusable. In virtual time a crash is the model's, counted in the summary."""
        if self.virtual or note.device is None:
            return
        if note.kind == "device.lost":
            self._away[note.device] = note.t_lab
            if note.device in self.crashing:
                dtype, restart_s = self.crashing[note.device]
                log.warning("device.lost %s: crashed, as devices.%s.faults.mtbc_h simulates (back after "
                            "faults.restart_s, %g lab-s), or its process or link is down; a step it was running fails "
                            "as lost and is retried as orchestrator.retry allows", note.device, dtype, restart_s)
                return
            log.warning("device.lost %s: left the bus (its process ended, or its host or link is down); a step it was "
                        "running fails as lost and is retried as orchestrator.retry allows, and the device is given "
                        "work again once it is back (a `twin device serve` that ended must be started again; one "
                        "cut off by its router or network rejoins by itself)", note.device)
        elif note.kind == "device.quarantined":  # a person may have a device to mend
            d = note.detail if isinstance(note.detail, dict) else {}
            why = f" ({str(d['reason'])[:200]})" if d.get("reason") else ""
            failed = "its steps went unconfirmed in time, one after another" if note.device in self.people else \
                "failing step after step"
            log.warning("device.quarantined %s: set aside after %s%s (orchestrator.quarantine_after); its steps go "
                        "to the other instances of its type, if any, and it is given a step to try it after "
                        "orchestrator.probe_after_s, %g lab-s", note.device, failed, why, d.get("probe_after_s", 0))
        elif note.kind == "devices.available":  # said after devices.unavailable, which on a live clock is logged
            log.warning("devices.available %s: one can take work again (back on the bus, or a quarantined one given "
                        "a step to try it), and the work waiting for it goes on", note.device)
        elif note.kind == "device.online" and note.device in self._away:
            away = note.t_lab - self._away.pop(note.device)
            log.warning("device.online %s: back on the bus after %.0f lab-s away; it is given work again", note.device,
                        away)

    def __call__(self, note: Any) -> None:
        key = (note.kind, note.device, None if note.device else note.experiment)
        self._said[key] += 1
        n = self._said[key]
        if n <= IN_FULL or not self.virtual:
            log.warning("%s", alert_text(note))
        elif _power_of_ten(n):
            log.warning("%s (the %s time; said again at the %s, and the journal has every one)", alert_text(note),
                        _nth(n), _nth(10 * n))


def _power_of_ten(n: int) -> bool:
    while n % 10 == 0:
        n //= 10
    return n == 1


def _nth(n: int) -> str:
    return f"{n:,}th"
