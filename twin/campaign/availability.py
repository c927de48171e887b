"""Device types with work waiting and no usable instance (lost, quarantined): said once, given up after a
while (``campaign.give_up_after_s``), resumed when an instance comes back. The core performs the effects."""

from __future__ import annotations

from collections.abc import Iterable


class Availability:
    def __init__(self) -> None:
        self.stranded: set[str] = set()  # work waits, no usable instance; the give-up timer runs
        self.given_up: set[str] = set()  # ... past it: no new experiment that needs one is proposed

    def review(self, waiting: dict[str, list[int]], usable: set[str], stopping: bool) -> list[tuple[str, str]]:
        """What changed, as (what, device type): ``unavailable`` (arm the timer), ``available`` (work can go
        on), ``cleared`` (nothing waits any more: disarm the timer)."""
        changes = []
        for dtype in sorted(set(waiting) | self.stranded | self.given_up):
            if dtype in waiting and dtype not in usable and dtype not in self.stranded and not stopping:
                self.stranded.add(dtype)
                changes.append(("unavailable", dtype))
            elif dtype in self.given_up and dtype in usable:
                self.given_up.discard(dtype)
                changes.append(("available", dtype))
            elif dtype in self.stranded and (dtype in usable or dtype not in waiting):
                self.stranded.discard(dtype)
                changes.append(("available" if dtype in usable else "cleared", dtype))
        return changes

    def give_up(self, dtype: str) -> bool:
        """The timer of ``dtype`` fired: whether its waiting work is to be abandoned now."""
        if dtype not in self.stranded:
            return False
        self.stranded.discard(dtype)
        self.given_up.add(dtype)
        return True

    def blocks(self, device_types: Iterable[str]) -> bool:
        """Whether an experiment through these device types would wait for one given up on."""
        return any(t in self.given_up for t in device_types)
