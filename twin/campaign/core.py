"""The campaign as a deterministic state machine: ``feed`` events, ``advance`` to get actions.

``pending → dispatched → running → done | failed → retry | abandoned``

Events are buffered and, at each ``advance(now)``, handled in a canonical
order (device messages by device, then presence, timers, a stop), so the
result does not depend on how a runtime interleaved events of the same
instant. Then, if anything changed, one decision pass: ask the planner for
experiments while there is room, ask the scheduler while a free device could
take a ready step. An ``Ask`` waits for its answer (``Proposed``/``Decided``)
before the pass goes on; events that arrive meanwhile wait in the inbox.
"""

from __future__ import annotations

import secrets
from typing import Any

from twin.campaign import (answered, consumables, device_events, dispatch, floods, human, operator, outcomes,
                           policy, provenance, questions, shutdown, stranded, timers)
from twin.campaign.consumables import Stocks
from twin.campaign.availability import Availability
from twin.campaign.events import (Action, Ask, CancelTimer, Decided, DeviceMessage, Event, InvalidInput,
                                  Note, Operator, Presence, Proposed, RecordExperiment, Send, SetTimer, Status, Stop,
                                  TimerFired, TimerKey, TimerKind)
from twin.campaign.ledger import UNRUNNABLE, Attempt, Counters, Device, Experiment, Task
from twin.campaign.decisions import Outcome, Proposal, RouteStep
from twin.core.messages import Kind
from twin.scenario.model import Scenario, expected_duration


_ORDER = {DeviceMessage: 0, InvalidInput: 0, Presence: 1, TimerFired: 2, Operator: 3, Stop: 4}


def _order(ev: Event) -> tuple[int, str]:
    rank = _ORDER[type(ev)]
    if rank == 0:
        return 0, ev.device if isinstance(ev, DeviceMessage) else ev.sender  # type: ignore[union-attr]
    if rank == 1:
        return 1, ev.device  # type: ignore[union-attr]
    if rank == 2:
        return 2, f"{ev.key.kind}:{ev.key.ref}"  # type: ignore[union-attr]
    if rank == 3:
        return 3, ev.ref  # type: ignore[union-attr]
    return 4, ""


class CampaignCore:
    def __init__(self, scenario: Scenario, campaign_id: str = "c1", secret: bytes | None = None) -> None:
        """``secret``: what attempt tokens are derived from (random by default; a resumed campaign passes
        the dead one's, so that its devices' answers still count). Tokens never enter the journal's events."""
        self.s, self.campaign_id = scenario, campaign_id
        self.secret = secret if secret is not None else secrets.token_bytes(32)
        # a device lost again within a lease is a bad link or an impostor's token; the memory bus has neither
        self._flap_s = 0.0 if scenario.bus.kind == "memory" else \
            scenario.bus.lease_ms / 1000 * (scenario.clock.speed if scenario.clock.mode == "scaled" else 1)
        self.seed = scenario.campaign.seed
        self.devices = {
            name: Device(name, dtype) for dtype in scenario.devices for name in scenario.instance_names(dtype)
        }
        self.people = human.people(scenario)  # device instances that are people: always present
        for name in self.people:
            self.devices[name].online = True
        self.experiments: list[Experiment] = []
        self.active: dict[int, Experiment] = {}  # pending or running
        self.ready: dict[str, Task] = {}
        self.attempts: dict[tuple[str, int], Attempt] = {}
        self.history: list[Outcome] = []
        self.best: dict[str, tuple[float, int]] = {}  # target -> (score, experiment)
        self.met_at: dict[str, float] = {}
        self._unscorable: set[str] = set()  # outputs already said to be unscorable
        self.met_after: dict[str, int] = {}  # target -> experiments finished when it was met
        self.met_cost: dict[str, float] = {}  # target -> money spent when it was met
        self.spent = 0.0  # what attempts and experiments' materials cost; ``cost`` adds the devices' hours
        self._per_hour = sum(d.instances * d.cost_per_hour for d in scenario.devices.values())
        self.counts = Counters()
        self.decision_wall_s: list[float] = []
        self.planner_exhausted = False
        self.planner_failed = ""  # why the planner can propose no more: the campaign finishes what is in the lab
        self.planner_why = ""  # the planner's own word on why it proposed nothing, the last time it did
        self.stopping = ""
        self.awaited: set[str] | None = None  # before the start: devices maybe still offline (device_events)
        self.resumable = False  # the stop came from outside (Stop.outside): twin resume continues the campaign
        self.paused_by = ""  # an operator paused the campaign: nothing new is proposed or dispatched
        self.questions: dict[str, questions.Question] = {}  # failed steps an operator is asked about
        self.replaced = 0  # experiments an operator had the planner replace ('alternative'): beyond the budget
        self.stocks = Stocks(scenario.consumables, scenario.instance_names)
        self.starved: dict[str, Task] = {}  # ready steps waiting for a consumable to be refilled
        self._question_seq = 0
        self.finished = False
        self.now = self.t0 = 0.0
        self._running = False  # past start-up
        self._inbox: list[Event] = []
        self._out: list[Action] = []
        self._asking: Ask | None = None
        self._answer: Proposed | Decided | None = None
        self._wake = False
        self._timers: set[TimerKey] = set()  # set and not yet fired or cancelled
        self.stalled = ""  # a live scheduler's wait for nothing, until it next starts a step
        self.alone = True  # no other campaign shares the lab (whose steps ending could wake this one)
        self._filled = False  # the planner had its say in this pass
        self._retrying: dict[str, Task] = {}  # waiting out their back-off
        self._availability = Availability()
        self._workflow = tuple(RouteStep(w.step, w.device, dict(w.params)) for w in scenario.workflow)

    # -- the runtime's side ---------------------------------------------------------
    def start(self, now: float) -> list[Action]:
        self.now = self.t0 = now
        self._note("campaign.started", detail=self.describe())
        if all(d.online for d in self.devices.values()):
            self._begin()
        else:
            self._timer(TimerKey(TimerKind.STARTUP), self.s.orchestrator.startup_s)
        return self.advance(now)

    def feed(self, event: Event | Proposed | Decided) -> None:
        if isinstance(event, (Proposed, Decided)):
            self._answer = event
        else:
            self._inbox.append(event)

    def stop(self, reason: str) -> None:
        self.feed(Stop(reason, outside=True))

    def advance(self, now: float, decide: bool = True) -> list[Action]:
        """Handle what was fed, then decide; returns the actions to perform, in order. ``decide=False``: only
        handle the events (a shared lab lets its campaigns decide one at a time, in its order)."""
        if self.finished:
            self._inbox.clear()
            return []
        self.now = now
        if self._inbox:
            batch, self._inbox = self._inbox, []
            batch.sort(key=_order)
            for ev in batch:
                self._handle(ev)
        if not decide:
            out, self._out = self._out, []
            return out
        if self._answer is not None:
            answer, self._answer, asked = self._answer, None, self._asking
            self._asking = None
            if isinstance(answer, Proposed) and asked is not None and asked.what == "plan":
                self._proposed(answer.proposals[:asked.n], answer.failed, answer.why)
            elif isinstance(answer, Decided) and asked is not None and asked.what == "schedule":
                answered.carry_out(self, answer)
        if self._running and self._asking is None:
            self._decide()
        out, self._out = self._out, []
        return out

    @property
    def unavailable(self) -> list[str]:
        """Device types that work waits for with no usable instance (lost or quarantined), given up on or not."""
        return sorted(self._availability.stranded | self._availability.given_up)

    @property
    def waiting(self) -> Ask | None:
        """The question the core waits on, if any."""
        return self._asking

    @property
    def has_work(self) -> bool:
        """Whether ``advance`` would do anything now."""
        if self.finished:
            return False
        return bool(self._inbox) or self._answer is not None or (self._wake and self._asking is None and self._running)

    def wake(self) -> None:
        """Something outside changed what could be dispatched (a shared lab released a device): decide again."""
        self._wake = True

    @property
    def has_events(self) -> bool:
        return bool(self._inbox)

    @property
    def wants_to_decide(self) -> bool:
        """Whether ``advance`` would start or go on with a decision pass."""
        return not self.finished and (self._answer is not None or (self._wake and self._asking is None and self._running))

    @property
    def elapsed_s(self) -> float:
        return self.now - self.t0

    @property
    def finished_count(self) -> int:
        return len(self.experiments) - len(self.active)

    def describe(self) -> dict[str, Any]:
        """What an observer needs to make sense of the campaign's messages."""
        s = self.s
        return {
            "scenario": s.name, "lab": s.lab, "campaign": self.campaign_id, "seed": s.campaign.seed,
            "budget": s.campaign.budget, "clock": s.clock.mode,
            "devices": {d.name: d.type for d in self.devices.values()},
            "parameters": {k: [p.low, p.high, p.unit] for k, p in s.chemistry.parameters.items()},
            "targets": [t.model_dump(exclude_none=True) for t in s.chemistry.targets],
        }

    # -- actions ----------------------------------------------------------------------
    def _note(self, kind: str, experiment: int | None = None, task: str | None = None, attempt: int | None = None,
              device: str | None = None, detail: Any = None) -> None:
        self._out.append(Note(self.now, kind, experiment, task, attempt, device, detail))

    def _timer(self, key: TimerKey, delay: float) -> None:
        self._timers.add(key)
        self._out.append(SetTimer(key, max(0.0, delay)))

    def cancel_timer(self, key: TimerKey) -> None:
        self._timers.discard(key)
        self._out.append(CancelTimer(key))

    def _send(self, dev: str, kind: Kind, task: str, attempt: int, body: dict[str, Any], token: str) -> None:
        self._out.append(Send(dev, kind, task, attempt, body, token))

    def token(self, task: str, attempt: int) -> str:
        """The attempt's token: unguessable without the secret, the same for the same secret (a resumed core)."""
        return provenance.attempt_token(self.secret, self.campaign_id, task, attempt)

    # -- events -----------------------------------------------------------------------
    def _handle(self, ev: Event) -> None:
        if isinstance(ev, DeviceMessage):
            device_events.message(self, ev)
        elif isinstance(ev, Presence):
            device_events.presence(self, ev.device, ev.alive)
        elif isinstance(ev, TimerFired):
            self._timers.discard(ev.key)
            timers.fired(self, ev.key)
        elif isinstance(ev, Operator):
            operator.act(self, ev)
        elif isinstance(ev, InvalidInput):
            before = self.counts.invalid
            self.counts.invalid += ev.count
            more = floods.left_out(before, self.counts.invalid)
            if more is not None:
                detail = {"key": ev.key, "sender": ev.sender, "reason": ev.reason, "excerpt": ev.excerpt}
                self._note("message.invalid", device=ev.sender, detail={**detail, "left_out": more} if more else detail)
        elif isinstance(ev, Stop):
            if not self.stopping:
                self.stopping, self.resumable = ev.reason, ev.outside
                self._note("campaign.stopping", detail=ev.reason)
            if not self._running:
                self._begin()
            self._asking = None  # a question still open is moot now; its answer will be ignored
            self._wake = True

    def _on_stop(self, reason: str, outside: bool = False) -> None:
        self._handle(Stop(reason, outside))

    def _begin(self) -> None:
        self._running = True
        self._wake = True
        self._timer(TimerKey(TimerKind.LIMIT), self.s.campaign.max_lab_hours * 3600 - (self.now - self.t0))

    # -- the decision pass ----------------------------------------------------------
    def _decide(self) -> None:
        while self._wake:
            if not self._filled:
                n = self._room()
                if n > 0:
                    self._ask(Ask("plan", n, tuple(self.history), tuple(e.params for e in self.active.values())))
                    return
                self._filled = True
            stranded.review(self)
            dry = self.dry
            if not (self.stopping or self.paused_by) and dispatch.pair_possible(self.ready.values(), self.devices,
                                                                               dry):
                c = self.s.campaign
                self._ask(Ask("schedule", view=dispatch.view(self.now, self.ready.values(), self.devices,
                                                             self.finished_count, c.budget, len(self.active), dry)))
                self._wake = False  # set again by whatever changes the lab before the answer comes
                return
            self._end_pass()
        if not self.stopping and self.starved:
            stalled = consumables.stalled(self)
            if stalled:
                self._on_stop(stalled)
        if self.stopping or (not self.active and not self._can_propose()):
            self._shutdown()

    def _ask(self, ask: Ask) -> None:
        self._asking = ask
        self._out.append(ask)

    def _end_pass(self) -> None:
        self._wake = self._filled = False

    def _room(self) -> int:
        if self.stopping or self.paused_by or not self._can_propose():
            return 0
        c = self.s.campaign
        return min(c.max_in_flight - len(self.active), c.budget + self.replaced - len(self.experiments))

    @property
    def cost(self) -> float:
        """What the campaign has cost so far: its attempts, its experiments' materials and ``hours_cost``."""
        return self.spent + self.hours_cost

    @property
    def hours_cost(self) -> float:
        """What every instance's hours have cost since the campaign started (``devices.*.cost_per_hour``)."""
        return self._per_hour * self.elapsed_s / 3600

    def _can_propose(self) -> bool:
        return not self.why_no_proposals()

    def why_no_proposals(self) -> str:
        """Why no more experiments are proposed ('' when they may be): "budget", "planner", "cost", "targets" or,
        when nothing else holds them back, stranded.GIVEN_UP (a device type an experiment would wait for was given up on)."""
        c = self.s.campaign
        if len(self.experiments) >= c.budget + self.replaced:
            return "budget"
        if self.planner_exhausted:
            return "planner"
        if c.max_cost is not None and self.cost >= c.max_cost:
            return "cost"
        if c.stop_on_target and self.s.chemistry.targets and len(self.met_at) == len(self.s.chemistry.targets):
            return "targets"
        return stranded.GIVEN_UP if self._availability.blocks(step.device for step in self._workflow) else ""

    def _proposed(self, proposals: list[Proposal], failed: str = "", why: str = "") -> None:
        if failed:
            if not self.planner_failed:
                self.planner_failed = failed
                self._note("planner.failed", detail=failed)
            self.planner_exhausted = self._filled = True
            return
        if not proposals:
            # nothing now: ask again when something finishes, or give up if nothing will
            self.planner_exhausted = not self.active
            self.planner_why = why
            self._filled = True
            return
        for p in proposals:
            self._add_experiment(p)

    # -- experiments and steps ------------------------------------------------------
    def _add_experiment(self, p: Proposal) -> None:
        bad_route = policy.unusable_route(p.route, self.s.devices) if p.route else ""
        route = self._workflow if bad_route or not p.route else tuple(p.route)
        e = Experiment(len(self.experiments), dict(p.params), route, self.now)
        self.experiments.append(e)
        self.active[e.id] = e
        self._note("experiment.proposed", e.id, detail=e.params)
        if isinstance(p.cost, (int, float)) and 0 < p.cost < float("inf"):  # a planner's nonsense costs nothing
            self.spent += float(p.cost)
        self._out.append(RecordExperiment(e))
        unusable = bad_route or policy.unusable_params(e.params, self.s.chemistry.parameters)
        if unusable:  # the planner's fault, not the devices': nothing is sent
            self._note("planner.invalid", e.id, detail=unusable)
            outcomes.finish(self, e, Status.ABANDONED, f"{UNRUNNABLE}: {unusable}")
            return
        outside = policy.outside_envelope(e.route, e.params, self.s.devices)
        if outside:  # refused before anything is sent: no step runs for an experiment that cannot finish
            self.counts.infeasible += 1
            outcomes.finish_infeasible(self, e, outside)
            return
        self._make_ready(e)

    def _expected(self, e: Experiment, step: RouteStep) -> float:
        dt = self.s.devices[step.device]
        return expected_duration(dt.duration, {**e.params, **step.params}, dt.setup_s, dt.clean_s)

    def _make_ready(self, e: Experiment, task: Task | None = None) -> None:
        if task is None:
            step = e.route[e.stage]
            expected = self._expected(e, step)
            then = tuple((s.device, self._expected(e, s)) for s in e.route[e.stage + 1:])
            task = Task(f"e{e.id}s{e.stage}", e, step, self.now, expected,
                        expected + sum(d for _, d in then), then)
        task.ready_since = self.now
        if self.stocks:
            needs = self._needs(task)
            short = self.stocks.short(needs, barred=task.barred)
            if short:
                self._starve(task, short)
                return
            if self.stocks.per_device:  # some instances may have run dry: say so, the step goes to another
                consumables.dried(self, task, needs)
        self.ready[task.id] = task
        self._note("task.ready", e.id, task.id, detail={"sample_made": e.sample_made, "step": task.step.step})
        self._wake = True

    def _dispatch(self, task: Task, dev: Device) -> None:
        e = task.experiment
        stability = self.s.chemistry.stability_s
        if stability and not e.degraded and e.sample_made is not None and self.now - e.sample_made > stability:
            e.degraded, e.degraded_before = True, task.step.step  # the sample waited for this step longer than it keeps
        task.attempts += 1
        e.attempts += 1
        e.status = Status.RUNNING
        self.counts.attempts += 1
        self.spent += self.s.devices[dev.type].cost
        att = Attempt(task, task.attempts, dev.name, self.now, token=self.token(task.id, task.attempts))
        dev.attempt = att
        dev.attempts += 1
        self.attempts[(task.id, att.n)] = att
        deadline = policy.deadline_s(task.expected_s, self.s.orchestrator)
        self._timer(TimerKey(TimerKind.DEADLINE, f"{task.id}#{att.n}"), deadline)
        body = {"step": task.step.step, "params": {**e.params, **task.step.params}, "sample": e.sample,
                "expected_s": task.expected_s, "deadline_s": deadline}
        used = consumables.take(self, task, dev.name) if self.stocks else {}
        detail: dict[str, Any] = {"deadline_s": deadline, **used}
        self._note("attempt.dispatched", e.id, task.id, att.n, dev.name, detail=detail)
        if dev.name in self.people:
            human.dispatched(self, att, body)
        else:
            self._send(dev.name, Kind.COMMAND, task.id, att.n, body, att.token)

    @property
    def short_of(self) -> list[str]:
        """The stocks (``ITEM`` or ``ITEM@INSTANCE``) that ready steps wait to be refilled."""
        return sorted({item for t in self.starved.values()
                       for item in self.stocks.short(self._needs(t), barred=t.barred)})

    def _needs(self, task: Task) -> dict[str, float]:
        return self.stocks.needs(task.step.step, {**task.experiment.params, **task.step.params}, task.step.device)

    @property
    def dry(self) -> dispatch.Dry | None:
        """What keeps a step off instances short of their own stock (None: no stock is an instance's own)."""
        return self._dry if self.stocks.per_device else None

    def _dry(self, task: Task) -> frozenset[str]:
        return frozenset(st.holder for st in self.stocks.dry(self._needs(task)) if st.holder)

    def _starve(self, task: Task, short: list[str]) -> None:
        consumables.starve(self, task, short)

    # -- outcomes (outcomes.py): what the modules acting on experiments call ---------
    def _resolve(self, att: Attempt, code: str, body: dict[str, Any]) -> None:
        outcomes.resolve(self, att, code, body)

    def _finish(self, e: Experiment, status: Status, reason: str = "") -> None:
        outcomes.finish(self, e, status, reason)

    def _advance_experiment(self, task: Task, result: dict[str, Any]) -> None:
        outcomes.advance(self, task, result)

    # -- shutdown ---------------------------------------------------------------------
    def _shutdown(self) -> None:
        shutdown.end(self)
