"""Dispatching rules: which ready step goes first, on which free device.

Each rule orders the ready steps and gives each, in turn, a free device of its
type (the first by name, or the least used for ``least-loaded``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from twin import Assignment, FreeDevice, LabView, ReadyStep, capable


def _assign_in_order(order: list[ReadyStep], view: LabView,
                     pick: Callable[[list[FreeDevice]], FreeDevice] = lambda options: options[0]) -> list[Assignment]:
    free = list(view.free)
    out = []
    for step in order:
        if not free:
            break
        options = capable(step, tuple(free))
        if options:
            device = pick(options)
            free.remove(device)
            out.append(Assignment(step.task, device.name))
    return out


def _servable(view: LabView) -> list[ReadyStep]:
    """The ready steps of a type with a free device: the only ones a rule could start now (a lab of hundreds of
    ready steps and all but a few devices busy sorted all of them at every decision)."""
    types = {d.device_type for d in view.free}
    return [s for s in view.ready if s.device_type in types]


class _Rule:
    """A rule is its ordering key over ready steps."""

    def __init__(self, **_: Any) -> None:
        pass

    def key(self, s: ReadyStep) -> tuple:
        raise NotImplementedError

    def decide(self, view: LabView) -> list[Assignment]:
        return _assign_in_order(sorted(_servable(view), key=self.key), view)


class FifoScheduler(_Rule):
    """First ready, first served, on the first free device of its type."""

    def key(self, s: ReadyStep) -> tuple:
        return (s.ready_since, s.task)


class OldestSampleScheduler(_Rule):
    """Steps whose sample has waited longest go first, so fewer samples degrade."""

    def key(self, s: ReadyStep) -> tuple:
        made = s.sample_made if s.sample_made is not None else float("inf")
        return (made, s.ready_since, s.task)


class SptScheduler(_Rule):
    """Shortest processing time first: quick steps free their devices soonest."""

    def key(self, s: ReadyStep) -> tuple:
        return (s.expected_s, s.ready_since, s.task)


class MwkrScheduler(_Rule):
    """Most work remaining first: the experiments furthest from done set the makespan."""

    def key(self, s: ReadyStep) -> tuple:
        return (-s.work_remaining_s, s.ready_since, s.task)


class LeastLoadedScheduler(_Rule):
    """First ready, first served, on the free device of its type that has been busy least."""

    def key(self, s: ReadyStep) -> tuple:
        return (s.ready_since, s.task)

    def decide(self, view: LabView) -> list[Assignment]:
        busy = {d.name: (d.busy_s, d.name) for d in view.devices}
        return _assign_in_order(sorted(_servable(view), key=self.key), view,
                                pick=lambda options: min(options, key=lambda d: busy.get(d.name, (0.0, d.name))))


class FairShareScheduler(_Rule):
    """A lab of several campaigns (``orchestrator.lab_scheduler``): the campaign of top priority first, then the
    one furthest below its share of the device time so far, first ready first within it — the lab's turns as one
    rule over every campaign's steps. One campaign: first ready, first served."""

    def decide(self, view: LabView) -> list[Assignment]:
        states = {c.name: (-c.priority, c.used - c.share) for c in view.campaigns}
        order = sorted(_servable(view), key=lambda s: (*states.get(s.campaign, (0, 0.0)), s.ready_since, s.task))
        return _assign_in_order(order, view)


RULES = ("fifo", "spt", "mwkr", "least-loaded", "oldest-sample")
LAB_RULES = ("fair-share",)  # rules that read whose step each is: a lab's one scheduler's baselines and teachers


def rules_for(scenario: Any) -> tuple[str, ...]:
    """The rules a policy is judged against and taught by: in a lab of several campaigns, also those that read
    whose step each is (as the lab's one scheduler)."""
    return (*RULES, *LAB_RULES) if scenario.campaigns else RULES
