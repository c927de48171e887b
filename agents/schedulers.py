"""Dispatching rules. The RL scheduler and CP-SAT come with issue [4 of 5]."""

from __future__ import annotations

from typing import Any

from twin.decisions import Assignment, LabView, ReadyStep, capable


def _assign_in_order(order: list[ReadyStep], view: LabView) -> list[Assignment]:
    free = list(view.free)
    out = []
    for step in order:
        options = capable(step, tuple(free))
        if options:
            device = options[0]
            free.remove(device)
            out.append(Assignment(step.task, device.name))
    return out


class FifoScheduler:
    """First ready, first served, on the first free device of its type."""

    def __init__(self, **_: Any) -> None:
        pass

    def decide(self, view: LabView) -> list[Assignment]:
        return _assign_in_order(sorted(view.ready, key=lambda s: (s.ready_since, s.task)), view)


class OldestSampleScheduler:
    """Greedy: steps whose sample has waited longest go first, so fewer samples degrade."""

    def __init__(self, **_: Any) -> None:
        pass

    def decide(self, view: LabView) -> list[Assignment]:
        def key(s: ReadyStep):
            made = s.sample_made if s.sample_made is not None else float("inf")
            return (made, s.ready_since, s.task)

        return _assign_in_order(sorted(view.ready, key=key), view)
