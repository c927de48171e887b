"""Several campaigns on one lab: each campaign's core, one set of devices and consumables, one order of turns.

Every campaign keeps its own core — experiments, attempts, retries, ledger and accounting invariant — and sees
the lab's devices through its own ``Device`` records. The shared lab keeps them telling one story:

- **holds**: a device with a step of one campaign on it (or a cancel it has not answered, or that it has
  quarantined until its probe) is ``held_by`` that campaign in every other campaign's records, so no campaign
  dispatches to it until it is released;
- **turns**: at each instant every campaign first takes in its events (results, presence, timers), then the
  campaigns make their decision passes one at a time, the highest ``priority`` first and, among equals, the one
  furthest below its ``share`` of the device time used so far (the fair-share rule); a campaign's own
  scheduler chooses among its ready steps and the devices still free;
- **presence** goes to every campaign; a device's message goes to the campaign its envelope names (or, if that
  names none of them, to the campaign holding the device, which rejects what it cannot vouch for);
- **consumables** are the lab's: one stock that every campaign takes from; a refill by any campaign puts back in
  the queue the steps of every campaign that waited for it;
- **submissions**: a campaign starts at its ``start_h`` or when the campaign it comes ``after`` has ended.

Actions come out tagged with their campaign ("" for the lab's own timers), so a runtime sends each to that
campaign's journal, planner and scheduler.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from twin.campaign import consumables, dispatch, stall
from twin.campaign.consumables import Stocks
from twin.campaign.core import CampaignCore
from twin.campaign.decisions import Assignment, CampaignState, DeviceState, LabView
from twin.campaign.events import (Action, Ask, Decided, DeviceMessage, Event, InvalidInput, Presence, SetTimer, Stop,
                                  TimerFired, TimerKey, TimerKind)
from twin.scenario.model import Scenario, SharedCampaign

Tagged = tuple[str, Action]
LAB = ""  # the tag of the lab's own actions


def by_campaign(tagged: list[Tagged]) -> list[tuple[str, list[Action]]]:
    """Consecutive actions of one campaign together, in order (a runtime hands each run to that campaign's seat)."""
    out: list[tuple[str, list[Action]]] = []
    for name, action in tagged:
        if out and out[-1][0] == name:
            out[-1][1].append(action)
        else:
            out.append((name, [action]))
    return out


class SharedLab:
    def __init__(self, lab: Scenario, scenarios: dict[str, Scenario], secrets: dict[str, bytes] | None = None,
                 serving: bool = False, one_scheduler: bool | None = None) -> None:
        """``scenarios``: each campaign's scenario (``twin.scenario.sharing.campaign_scenarios``), in the lab
        file's order. ``serving``: the lab goes on when its campaigns have ended, taking more (``add``), until
        it is stopped. ``one_scheduler``: the lab asks one scheduler with every campaign's steps (default: if the
        lab file names one, ``orchestrator.lab_scheduler``); else each campaign's own decides, in turns."""
        self.serving = serving
        self.lab = lab
        self.entries: dict[str, SharedCampaign] = {c.name: c for c in lab.campaigns}
        self.cores = {name: CampaignCore(s, name, (secrets or {}).get(name)) for name, s in scenarios.items()}
        self.stocks = Stocks(lab.consumables, lab.instance_names)
        for core in self.cores.values():
            core.stocks, core.alone = self.stocks, False
        self.online = {name: False for dtype in lab.devices for name in lab.instance_names(dtype)}
        self.started: list[str] = []  # in the order they were submitted
        self.submitted_at: dict[str, float] = {}
        self.unsubmitted: dict[str, str] = {}  # campaigns never started, and why (the lab stopped first)
        self._due: list[str] = []  # submitted, waiting for a turn to start
        self._deciding = ""  # the campaign whose decision pass waits on an answer: one at a time
        self.one_scheduler = bool(lab.orchestrator.lab_scheduler) if one_scheduler is None else one_scheduler
        self._asks: dict[str, Ask] = {}  # with one scheduler: the campaigns that asked it, this pass
        self._lab_ask: Ask | None = None  # ... and the lab's question to it, until it answers
        self._stopping = ""
        self._out: list[Tagged] = []
        self.now = 0.0

    # -- the runtime's side ---------------------------------------------------------
    def start(self, now: float) -> list[Tagged]:
        self.now = now
        for name, entry in self.entries.items():
            if entry.after is None:
                if entry.start_h <= 0:
                    self._submit(name)
                else:
                    self._out.append((LAB, SetTimer(TimerKey(TimerKind.SUBMIT, name), entry.start_h * 3600)))
        return self.advance(now)

    def feed(self, campaign: str, event: Any) -> None:
        """An event for one campaign (its timer, its planner's or scheduler's answer), or the lab's own: a timer,
        or the answer of the lab's one scheduler."""
        if campaign == LAB:
            if isinstance(event, TimerFired) and event.key.kind == TimerKind.SUBMIT and not self._stopping:
                self._submit(event.key.ref)
            elif isinstance(event, Decided) and self._lab_ask is not None:
                self._answered(event)
            return
        self.cores[campaign].feed(event)

    def feed_device(self, event: Event) -> None:
        """Presence, or a device's message (routed by the campaign it names)."""
        if isinstance(event, Presence):
            if event.device in self.online:
                self.online[event.device] = event.alive
            for name in self.started:
                self.cores[name].feed(event)
            return
        core = self._owner(event)
        if core is not None:
            core.feed(event)

    def refusal(self, name: str) -> str:
        """Why a campaign of this name cannot be added now; '' if it can."""
        if name in self.entries:
            return f"name: the lab has a campaign {name!r} already: give the new one another name"
        if self._stopping:
            return f"the lab is stopping ({self._stopping}): it takes no more campaigns"
        return ""

    def add(self, entry: SharedCampaign, scenario: Scenario, secret: bytes | None = None) -> CampaignCore:
        """A campaign submitted now (``twin submit``); it starts at the next turn. ``secret``: what its attempt
        tokens come from (random by default; a rebuilt lab passes the one it had)."""
        refusal = self.refusal(entry.name)
        if refusal:
            raise ValueError(refusal)
        core = CampaignCore(scenario, entry.name, secret)
        core.stocks, core.alone = self.stocks, False
        self.entries[entry.name] = entry
        self.cores[entry.name] = core
        self._submit(entry.name)
        return core

    def stop(self, reason: str, outside: bool = False) -> None:
        """Stop every campaign (``outside``: as ``Stop.outside`` says; a Ctrl-C is, the lab's own end is not)."""
        if not self._stopping:
            self._stopping = reason
            for name in self.entries:
                if name not in self.started and name not in self._due:
                    self.unsubmitted[name] = reason
        for name in self.started:
            self.cores[name].feed(Stop(reason, outside))
        for name in self._due:
            self.unsubmitted[name] = reason
        self._due.clear()

    def advance(self, now: float) -> list[Tagged]:
        """Every campaign takes in its events; then one campaign, in turn order, gets its decision pass."""
        self.now = now
        cores = self.cores
        for name in self._due:
            self.submitted_at.setdefault(name, now)
        for name in self.started:
            if cores[name].has_events:
                self._take(name, cores[name].advance(now, decide=False))
        if self._due and not self._deciding:
            for name in self._due:
                self._begin(name)
            self._due.clear()
        self._sync_holds()
        if self.one_scheduler:
            self._lab_pass(now)
        elif self._deciding:
            core = cores[self._deciding]
            if core.wants_to_decide:
                self._take(self._deciding, core.advance(now))
        else:
            for name in self._turns():
                if cores[name].wants_to_decide:
                    self._take(name, cores[name].advance(now))
                    if cores[name].waiting is not None:
                        self._deciding = name
                    break
        if self._deciding and cores[self._deciding].waiting is None:
            self._deciding = ""
        self._sync_holds()
        out, self._out = self._out, []
        return out

    @property
    def has_work(self) -> bool:
        """Whether ``advance`` would do anything now: events to take in, or a decision pass that may go on (while
        one campaign waits for its planner or scheduler, the others' passes wait their turn)."""
        cores = [self.cores[n] for n in self.started]
        if any(c.has_events for c in cores):
            return True
        if self._lab_ask is not None:
            return False  # the lab's scheduler answers first
        if self._asks and not self._deciding:
            return True  # the lab's scheduler is to be asked
        if self._deciding:
            return self.cores[self._deciding].wants_to_decide
        return bool(self._due) or any(c.wants_to_decide for c in cores)

    def stalled(self) -> str:
        """Why nothing can happen but the campaigns' time limits, or "": every campaign started (none queued, no
        submissions to come), and each one not finished has steps ready that its scheduler, asked, left waiting
        with the whole lab idle (or the lab's one scheduler did). A virtual clock ends the lab on it; a live one only
        alerts (``newly_stalled``)."""
        return "" if self.serving else self._stuck()

    def newly_stalled(self) -> tuple[str, list[str]]:
        """On a live clock, when nothing is left to do (``has_work`` false): the stall ``stalled`` describes is an
        alert, not an end (an operator, or an instrument coming back, may still move the lab; a served lab may be
        given more campaigns). Why, and the campaigns not stalled before (each one's ``stalled`` is set, for
        ``twin ctl status``, until the lab moves again): the runtime notes ``scheduler.stalled`` for each."""
        why = self._stuck()  # a served lab too: it may never be given another
        fresh = []
        for name in self.started:
            core = self.cores[name]
            if not why:
                core.stalled = ""
            elif not core.finished and not core.stalled:
                core.stalled = why
                fresh.append(name)
        return why, fresh

    def _stuck(self) -> str:
        """Each campaign started and not finished has steps ready that its scheduler (or the lab's one), asked,
        left waiting with the whole lab idle; none is due or yet to start (its steps could wake the others)."""
        if (self._due or self._stopping or self._asks or self._lab_ask is not None
                or len(self.started) + len(self.unsubmitted) != len(self.entries)):
            return ""
        live = {n: self.cores[n] for n in self.started if not self.cores[n].finished}
        if not live or not all(c.ready and c.waiting is None and not c.has_events and not c.paused_by
                               and stall.idle(c) for c in live.values()):  # paused: its operator resumes it
            return ""
        if self.one_scheduler:
            return stall.say_for_lab({}, self.lab.orchestrator.lab_scheduler)
        return stall.say_for_lab({n: c.s.campaign.scheduler for n, c in live.items()})

    @property
    def waiting(self) -> Any:
        """The question a campaign (or, with one scheduler, the lab) waits on, if any."""
        if self._lab_ask is not None:
            return self._lab_ask
        return self.cores[self._deciding].waiting if self._deciding else None

    @property
    def finished(self) -> bool:
        if self.serving and not self._stopping:
            return False
        return (not self._due and all(self.cores[n].finished for n in self.started)
                and len(self.started) + len(self.unsubmitted) == len(self.entries))

    def used_s(self, name: str) -> float:
        """Device time campaign ``name`` has had: its steps done and failed, and those on a device now."""
        core = self.cores[name]
        running = sum(self.now - d.attempt.t_sent for d in core.devices.values() if d.attempt is not None)
        return sum(d.busy_s for d in core.devices.values()) + running

    # -- inside ---------------------------------------------------------------------
    def _take(self, name: str, actions: list[Action]) -> None:
        refilled = False
        for a in actions:
            if self.one_scheduler and type(a) is Ask and a.what == "schedule":
                self._asks[name] = a  # the lab's scheduler answers it, with the other campaigns' steps in view
                continue
            self._out.append((name, a))
            refilled = refilled or getattr(a, "kind", None) in ("consumable.refilled", "consumable.returned")
        if refilled:
            for other in self.started:
                if other != name and self.cores[other].starved:
                    consumables.requeue(self.cores[other])
        if self.cores[name].finished:
            self._ended(name)

    def _submit(self, name: str) -> None:
        if name not in self.started and name not in self._due:
            self._due.append(name)

    def _begin(self, name: str) -> None:
        core = self.cores[name]
        for dev_name, alive in self.online.items():
            if dev_name not in core.people:
                core.devices[dev_name].online = alive
        self.started.append(name)
        self._sync_holds()
        self._take(name, core.start(self.now))
        if core.waiting is not None:
            self._deciding = name

    def _ended(self, name: str) -> None:
        for other, entry in self.entries.items():
            if entry.after == name:
                if self._stopping:
                    self.unsubmitted.setdefault(other, self._stopping)
                else:
                    self._submit(other)

    def _turns(self) -> list[str]:
        """The started campaigns in the order they pick: priority, then furthest below their share."""
        used = {n: self.used_s(n) for n in self.started}
        total = sum(used.values()) or 1.0
        weights = {n: self.entries[n].share for n in self.started}
        wsum = sum(weights.values())
        return sorted(self.started, key=lambda n: (-self.entries[n].priority,
                                                   used[n] / total - weights[n] / wsum, self.started.index(n)))

    # -- one scheduler for the lab --------------------------------------------------------
    def _lab_pass(self, now: float) -> None:
        """Every campaign's decision pass, in turn order, up to its question to the scheduler; then one question
        to the lab's scheduler with every campaign's ready steps (a campaign waiting on its planner goes alone)."""
        cores = self.cores
        if self._lab_ask is not None:
            return
        if self._deciding:  # its planner answered: its pass goes on, up to its question to the scheduler
            name = self._deciding
            if cores[name].wants_to_decide:
                self._take(name, cores[name].advance(now))
                self._sync_holds()
            if cores[name].waiting is None or name in self._asks:
                self._deciding = ""
        if not self._deciding:
            for name in self._turns():
                core = cores[name]
                if name in self._asks or not core.wants_to_decide:
                    continue
                self._take(name, core.advance(now))
                self._sync_holds()  # what it dispatched is held from the next campaign at once
                if core.waiting is not None and name not in self._asks:  # its planner was asked
                    self._deciding = name
                    break
        if not self._deciding and self._asks:
            self._lab_ask = Ask("schedule", view=self._merged(now))
            self._out.append((LAB, self._lab_ask))

    def _merged(self, now: float) -> LabView:
        """What the lab's scheduler sees: every asking campaign's ready steps (tasks named ``campaign/task``)
        that no higher-priority campaign's steps compete with for a free device, and the lab's devices."""
        views = {n: self._view(n, now) for n in self._asks}  # as they are now: a campaign may have waited
        free_names = set.intersection(*({f.name for f in v.free} for v in views.values()))
        first = next(iter(views.values()))
        free = tuple(f for f in first.free if f.name in free_names)
        priority = {n: self.entries[n].priority for n in views}
        top: dict[str, int] = {}
        for n, v in views.items():
            for r in v.ready:
                if any(f.device_type == r.device_type and f.name not in r.avoid for f in free):
                    top[r.device_type] = max(top.get(r.device_type, priority[n]), priority[n])
        ready = tuple(dataclasses.replace(r, task=f"{n}/{r.task}", campaign=n) for n, v in views.items()
                      for r in v.ready if priority[n] >= top.get(r.device_type, priority[n]))
        return LabView(now, ready, free, self._device_states(free_names), sum(v.finished for v in views.values()),
                       sum(v.budget for v in views.values()), sum(v.in_lab for v in views.values()),
                       self._campaign_states())

    def _campaign_states(self) -> tuple[CampaignState, ...]:
        """Every running campaign: its priority, the share of device time it is due and the share it has had."""
        running = [n for n in self.started if not self.cores[n].finished]
        used = {n: self.used_s(n) for n in running}
        total, due = sum(used.values()), sum(self.entries[n].share for n in running)
        return tuple(CampaignState(n, self.entries[n].priority, self.entries[n].share / due,
                                   used[n] / total if total else 0.0, self.cores[n].finished_count,
                                   self.cores[n].s.campaign.budget, self.cores[n].s.chemistry.stability_s or 0.0)
                     for n in running)

    def _view(self, name: str, now: float) -> LabView:
        core = self.cores[name]
        return dispatch.view(now, core.ready.values(), core.devices, core.finished_count, core.s.campaign.budget,
                             len(core.active), core.dry)

    def _device_states(self, free: set[str]) -> tuple[DeviceState, ...]:
        """Each device as the lab sees it: its attempts, failures and busy time over every campaign, and the step
        on it now, whichever campaign's."""
        states: dict[str, DeviceState] = {}
        for name in self.started:
            for d in self.cores[name].devices.values():
                until = d.attempt.t_sent + d.attempt.task.expected_s if d.attempt else None
                then = d.attempt.task.then if d.attempt else ()
                task = d.attempt.task.id if d.attempt else ""
                seen = states.get(d.name)
                if seen is None:
                    states[d.name] = DeviceState(d.name, d.type, d.name in free, d.online, until, d.attempts,
                                                 d.failures, d.busy_s, then, task)
                else:
                    states[d.name] = dataclasses.replace(
                        seen, attempts=seen.attempts + d.attempts, failures=seen.failures + d.failures,
                        busy_s=seen.busy_s + d.busy_s, busy_until=seen.busy_until if until is None else until,
                        then=seen.then or then, task=seen.task or task)
        return tuple(states.values())

    def _answered(self, d: Decided) -> None:
        """The lab's scheduler's answer, to each campaign it gave steps to (a device given twice: the first only);
        the others keep waiting and are in the next question (a scheduler may give one pair at a time). Only an
        answer with nothing in it ends every campaign's pass."""
        mine: dict[str, list[Assignment]] = {n: [] for n in self._asks}
        taken: set[str] = set()
        for a in d.assignments:
            name, _, task = a.task.partition("/")
            if name in mine and a.device not in taken:
                mine[name].append(Assignment(task, a.device))
                taken.add(a.device)
        for name, assignments in mine.items():
            if assignments or not taken:
                self.cores[name].feed(Decided(assignments, d.wall_s))
                del self._asks[name]
        self._lab_ask = None

    def _sync_holds(self) -> None:
        holder: dict[str, str] = {}
        for name in self.started:
            if self.cores[name].finished:
                continue  # it cancelled what it ran as it ended: it holds nothing
            for dev in self.cores[name].devices.values():
                if dev.attempt is not None or dev.cancelling is not None or dev.quarantined:
                    holder[dev.name] = name  # a device one campaign quarantined is kept from the others too
        for name in self.started:
            core = self.cores[name]
            for dev in core.devices.values():
                h = holder.get(dev.name, "")
                h = h if h != name else ""
                if dev.held_by and not h:
                    core.wake()  # released: this campaign may want it
                dev.held_by = h

    def _owner(self, event: Event) -> CampaignCore | None:
        """The campaign a device's message is for."""
        if isinstance(event, DeviceMessage) and event.campaign in self.cores and event.campaign in self.started:
            return self.cores[event.campaign]
        sender = event.device if isinstance(event, DeviceMessage) else event.sender if isinstance(
            event, InvalidInput) else ""
        for name in self.started:
            dev = self.cores[name].devices.get(sender)
            if dev is not None and (dev.attempt is not None or dev.cancelling is not None):
                return self.cores[name]
        return self.cores[self.started[0]] if self.started else None
