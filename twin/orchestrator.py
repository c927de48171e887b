"""The orchestrator: task life cycle, deadlines, retries, fail-over, quarantine.

``pending → dispatched → running → done | failed → retry | abandoned``

It is event driven: device events, presence changes, deadlines and back-off
timers only update state and wake the main loop, which asks the planner for
experiments and the scheduler for assignments. Every message it receives and
every state change goes to the journal, in lab time.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import random
import time
from collections.abc import Callable
from typing import Any

from twin import keys
from twin.bus import Bus
from twin.clock import LabClock
from twin.decisions import (Assignment, DeviceState, FreeDevice, LabView, Outcome, Planner, Proposal, ReadyStep,
                             RouteStep, Scheduler)
from twin.driver import expected_duration
from twin.decision_log import DecisionLog
from twin.journal import Journal
from twin.messages import InvalidMessage, Kind, decode, pack
from twin.records import Attempt, Device, Experiment, Task, check_accounting
from twin.scenario import Scenario
from twin.targets import scores

log = logging.getLogger(__name__)
ORCH = "orchestrator"


class Orchestrator:
    def __init__(self, scenario: Scenario, bus: Bus, clock: LabClock, journal: Journal,
                 planner: Planner, scheduler: Scheduler, campaign_id: str = "c1",
                 on_progress: Callable[[Orchestrator], None] | None = None) -> None:
        self.s, self.bus, self.clock, self.journal = scenario, bus, clock, journal
        self.planner, self.scheduler = planner, scheduler
        self.campaign_id, self.on_progress = campaign_id, on_progress
        self._rng = random.Random(f"orchestrator:{scenario.campaign.seed}")
        self.devices = {
            name: Device(name, dtype) for dtype in scenario.devices for name in scenario.instance_names(dtype)
        }
        self.experiments: list[Experiment] = []
        self.ready: dict[str, Task] = {}
        self.attempts: dict[tuple[str, int], Attempt] = {}
        self.history: list[Outcome] = []
        self.best: dict[str, tuple[float, int]] = {}  # target -> (score, experiment)
        self.met_at: dict[str, float] = {}
        self.met_after: dict[str, int] = {}  # target -> experiments finished when it was met
        self.met_cost: dict[str, float] = {}  # target -> money spent when it was met
        self.cost = 0.0
        self.counts = {"attempts": 0, "failed": 0, "timed_out": 0, "retried": 0, "invalid": 0,
                       "late": 0, "device_lost": 0, "quarantined": 0, "degraded": 0}
        self.planner_exhausted = False
        self.decision_wall_s: list[float] = []  # how long each scheduler decision took
        self.stopping = ""
        self._wake = asyncio.Event()
        self._ids = 0
        self.active: dict[int, Experiment] = {}  # pending or running
        self._handles: list[Any] = []
        self._t0 = 0.0
        self.decisions = DecisionLog(journal, bus, clock, scenario.lab, campaign_id)
        self._note = self.decisions.note

    # -- the main loop ----------------------------------------------------
    async def run(self) -> None:
        lab = self.s.lab
        self._t0 = self.clock.now()
        self._handles = [
            self.bus.serve(self.decisions.history_key, self.decisions.history),
            self.bus.subscribe(keys.evt(lab), self._on_event),
            self.bus.subscribe(keys.telemetry(lab), self._on_telemetry),
            self.bus.watch_tokens(keys.alive(lab), self._on_presence),
        ]
        self._note("campaign.started", detail=self.describe())
        await self._await_devices()
        limit = self.clock.call_later(self.s.campaign.max_lab_hours * 3600, lambda: self.stop("max_lab_hours reached"))
        try:
            while True:
                self._fill()
                await self._dispatch()
                if self._finished():
                    break
                await self._wake.wait()
                self._wake.clear()
        finally:
            limit.cancel()
            self._shutdown()

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

    def stop(self, reason: str) -> None:
        """Stop proposing and dispatching; what is in the lab is cancelled, the rest stays pending."""
        if not self.stopping:
            self.stopping = reason
            self._note("campaign.stopping", detail=reason)
        self._wake.set()

    @property
    def now(self) -> float:
        return self.clock.now()

    def _finished(self) -> bool:
        if self.stopping:
            return True
        return not self.active and not self._can_propose()

    def _can_propose(self) -> bool:
        c = self.s.campaign
        if self.planner_exhausted or len(self.experiments) >= c.budget:
            return False
        if c.max_cost is not None and self.cost >= c.max_cost:
            return False
        return not (c.stop_on_target and self.s.chemistry.targets and len(self.met_at) == len(self.s.chemistry.targets))

    async def _await_devices(self) -> None:
        try:
            async with self.clock.timeout(self.s.orchestrator.startup_s):
                while not all(d.online for d in self.devices.values()):
                    await self._wake.wait()
                    self._wake.clear()
        except TimeoutError:
            missing = [d.name for d in self.devices.values() if not d.online]
            log.warning("devices not on the bus after %.0f lab-s: %s", self.s.orchestrator.startup_s, missing)
            self._note("devices.missing", detail=missing)

    # -- planning ---------------------------------------------------------
    def _fill(self) -> None:
        c = self.s.campaign
        while not self.stopping and self._can_propose():
            n = min(c.max_in_flight - len(self.active), c.budget - len(self.experiments))
            if n <= 0:
                return
            pending = [e.params for e in self.active.values()]
            proposals = self.planner.propose(n, list(self.history), pending)[:n]
            if not proposals:
                # nothing now: ask again when something finishes, or give up if nothing will
                self.planner_exhausted = not self.active
                return
            for p in proposals:
                self._add_experiment(p)

    def _add_experiment(self, p: Proposal) -> None:
        route = p.route or tuple(RouteStep(w.step, w.device) for w in self.s.workflow)
        e = Experiment(len(self.experiments), dict(p.params), route, self.now)
        self.experiments.append(e)
        self.active[e.id] = e
        self._note("experiment.proposed", e.id, detail=e.params)
        self.journal.experiment(e)
        self._make_ready(e)

    def _make_ready(self, e: Experiment, task: Task | None = None) -> None:
        if task is None:
            step = e.route[e.stage]
            dtype = self.s.devices[step.device]
            params = {**e.params, **step.params}
            expected = expected_duration(dtype.duration, params, dtype.setup_s, dtype.clean_s)
            then = self._later_steps(e)
            task = Task(f"e{e.id}s{e.stage}", e, step, self.now, self.now, expected,
                        expected + sum(d for _, d in then), then)
        task.ready_since = self.now
        self.ready[task.id] = task
        self._note("task.ready", e.id, task.id, detail={"sample_made": e.sample_made, "step": task.step.step})
        self._wake.set()

    # -- scheduling -------------------------------------------------------
    def _view(self) -> LabView:
        ready = tuple(
            ReadyStep(t.id, t.experiment.id, t.step.step, t.step.device, t.ready_since,
                      t.experiment.sample_made, t.expected_s, t.work_remaining_s, self._avoid(t), t.then)
            for t in self.ready.values()
        )
        free = tuple(FreeDevice(d.name, d.type) for d in self.devices.values() if d.free)
        devices = tuple(
            DeviceState(d.name, d.type, d.free, d.online,
                        d.attempt.t_sent + d.attempt.task.expected_s if d.attempt else None, d.attempts, d.failures,
                        d.busy_s, d.attempt.task.then if d.attempt else ())
            for d in self.devices.values()
        )
        return LabView(self.now, ready, free, devices, len(self.experiments) - len(self.active), self.s.campaign.budget,
                       len(self.active))

    def _avoid(self, t: Task) -> frozenset[str]:
        """Fail over: skip devices that failed this step while another usable instance exists."""
        if not t.failed_on:
            return frozenset()
        usable = {d.name for d in self.devices.values() if d.type == t.step.device and d.online and not d.quarantined}
        avoid = frozenset(t.failed_on)
        if usable - avoid:
            return avoid
        last = frozenset(t.failed_on[-1:])
        return last if usable - last else frozenset()

    def _later_steps(self, e: Experiment) -> tuple[tuple[str, float], ...]:
        out = []
        for step in e.route[e.stage + 1:]:
            dt = self.s.devices[step.device]
            out.append((step.device, expected_duration(dt.duration, {**e.params, **step.params}, dt.setup_s, dt.clean_s)))
        return tuple(out)

    def _pair_possible(self) -> bool:
        """Whether some free device could take some ready step (cheaper than building the view)."""
        free: dict[str, set[str]] = {}
        for d in self.devices.values():
            if d.free:
                free.setdefault(d.type, set()).add(d.name)
        return any(free.get(t.step.device, set()) - self._avoid(t) for t in self.ready.values())

    async def _dispatch(self) -> None:
        while not self.stopping and self._pair_possible():
            view = self._view()  # the full view only when a decision is really needed
            started = time.perf_counter()
            decided = self.scheduler.decide(view)
            if inspect.isawaitable(decided):
                decided = await decided
            self.decision_wall_s.append(time.perf_counter() - started)
            sent = 0
            for a in decided:
                problem = self._invalid(a)
                if problem:
                    log.warning("scheduler decision ignored: %s", problem)
                    self._note("scheduler.invalid", task=a.task, device=a.device, detail=problem)
                    continue
                self._send(self.ready.pop(a.task), self.devices[a.device])
                sent += 1
            if not sent:
                return

    def _invalid(self, a: Assignment) -> str:
        task, dev = self.ready.get(a.task), self.devices.get(a.device)
        if task is None:
            return f"task {a.task!r} is not ready"
        if dev is None or not dev.free:
            return f"device {a.device!r} is not free"
        if dev.type != task.step.device:
            return f"device {a.device!r} is a {dev.type}, task {a.task} needs a {task.step.device}"
        return ""

    def _send(self, task: Task, dev: Device) -> None:
        e = task.experiment
        stability = self.s.chemistry.stability_s
        if stability and e.sample_made is not None and self.now - e.sample_made > stability:
            e.degraded = True  # the sample waited longer than it keeps
        task.attempts += 1
        e.attempts += 1
        e.status = "running"
        self.counts["attempts"] += 1
        self.cost += self.s.devices[dev.type].cost
        att = Attempt(task, task.attempts, dev.name, self.now)
        dev.attempt = att
        dev.attempts += 1
        self.attempts[(task.id, att.n)] = att
        o = self.s.orchestrator
        deadline = task.expected_s * o.timeout_factor + o.timeout_slack_s
        att.deadline = self.clock.call_later(deadline, lambda: self._resolve(att, "timed_out", {"reason": f"no result within {deadline:.0f} lab-s"}))
        body = {"step": task.step.step, "params": {**e.params, **task.step.params}, "sample": e.sample, "expected_s": task.expected_s}
        self._note("attempt.dispatched", e.id, task.id, att.n, dev.name, detail={"deadline_s": deadline})
        self.bus.publish(keys.cmd(self.s.lab, dev.name), self._pack(Kind.COMMAND, body, task.id, att.n))

    def _pack(self, kind: Kind, body: dict, task: str, attempt: int) -> bytes:
        self._ids += 1
        return pack(kind, body, id=f"{ORCH}:{self._ids}", sender=ORCH, t_lab=self.now,
                    campaign=self.campaign_id, task=task, attempt=attempt)

    # -- events from devices ---------------------------------------------
    def _on_event(self, key: str, payload: bytes) -> None:
        try:
            env, body = decode(payload, sender_hint=keys.device_of(key))
        except InvalidMessage as exc:
            self.counts["invalid"] += 1
            log.warning("dropped: %s", exc)
            self._note("message.invalid", device=exc.sender, detail=exc.reason)
            return
        att = self.attempts.get((env.task, env.attempt))
        exp = att.task.experiment.id if att else None
        self.journal.message(self.now, f"msg.{env.kind}", exp, env.task, env.attempt, env.sender, payload)
        if att is None or att.device != env.sender:
            self.counts["late"] += 1
            self._note("message.unknown_attempt", exp, env.task, env.attempt, env.sender)
            return
        if att.resolved:
            if env.kind in (Kind.RESULT, Kind.FAULT):
                self.counts["late"] += 1
                self._note("result.late", exp, env.task, env.attempt, env.sender, detail=env.kind)
            return
        if env.kind == Kind.ACCEPTED:
            att.t_accepted = self.now
            self._note("attempt.running", exp, env.task, env.attempt, env.sender)
        elif env.kind == Kind.RESULT:
            self._resolve(att, "ok", body.model_dump())
        elif env.kind == Kind.FAULT:
            self._resolve(att, body.code, {"reason": body.reason})
        elif env.kind == Kind.REJECTED:
            self._resolve(att, "rejected", {"reason": body.reason})

    def _on_telemetry(self, key: str, payload: bytes) -> None:
        try:
            env, body = decode(payload, sender_hint=keys.device_of(key))
        except InvalidMessage as exc:
            self.counts["invalid"] += 1
            self._note("message.invalid", device=exc.sender, detail=exc.reason)
            return
        self.journal.message(self.now, "msg.telemetry", None, env.task or None, env.attempt, env.sender, payload)

    def _on_presence(self, key: str, alive: bool) -> None:
        dev = self.devices.get(keys.device_of(key))
        if dev is None or dev.online == alive:
            return
        dev.online = alive
        self._note("device.online" if alive else "device.lost", device=dev.name)
        if not alive and dev.attempt is not None:
            self.counts["device_lost"] += 1
            self._resolve(dev.attempt, "device_lost", {"reason": f"{dev.name} left the bus (liveliness lost)"})
        self._wake.set()

    # -- outcomes ---------------------------------------------------------
    def _resolve(self, att: Attempt, code: str, body: dict) -> None:
        if att.resolved:
            return
        att.resolved = True
        if att.deadline is not None:
            att.deadline.cancel()
        dev, task, e = self.devices[att.device], att.task, att.task.experiment
        dev.attempt = None
        dev.busy_s += self.now - att.t_sent
        self._note(f"attempt.{'done' if code == 'ok' else 'failed'}", e.id, task.id, att.n, dev.name,
                           detail=None if code == "ok" else {"code": code, **body})
        if code == "timed_out":
            self.counts["timed_out"] += 1
            self.bus.publish(keys.cmd(self.s.lab, dev.name), self._pack(Kind.CANCEL, {"reason": body["reason"]}, task.id, att.n))
        if code == "ok":
            dev.consecutive_failures = 0
            dev.steps_done += 1
            self._advance(task, body)
        else:
            self._failed(task, dev, code, body.get("reason", ""))
        if self.on_progress:
            self.on_progress(self)
        self._wake.set()

    def _advance(self, task: Task, result: dict) -> None:
        e = task.experiment
        e.outputs.update(result.get("outputs") or {})
        sample = result.get("sample")
        if sample is not None:
            if sample is not e.sample:
                e.sample_made = float(sample.get("t_made", self.now))
            e.sample = sample
        e.stage += 1
        if e.stage < len(e.route):
            self._make_ready(e)
        else:
            self._finish(e, "done")

    def _failed(self, task: Task, dev: Device, code: str, reason: str) -> None:
        e, o = task.experiment, self.s.orchestrator
        self.counts["failed"] += 1
        if code != "rejected":
            dev.failures += 1
            dev.consecutive_failures += 1
            task.failed_on.append(dev.name)
            if dev.consecutive_failures >= o.quarantine_after and not dev.quarantined:
                self._quarantine(dev)
        retry = o.retry
        if task.attempts < retry.max_attempts and self.now - task.first_ready < retry.max_delay_s and not self.stopping:
            backoff = min(retry.backoff_max_s, retry.backoff_s * 2 ** (task.attempts - 1))
            backoff *= 1 + retry.jitter * (2 * self._rng.random() - 1)
            e.retries += 1
            self.counts["retried"] += 1
            self._note("task.retry", e.id, task.id, task.attempts, dev.name, detail={"backoff_s": backoff, "after": code})
            self.clock.call_later(backoff, lambda: self._make_ready(e, task) if not self.stopping else None)
        else:
            why = f"step {task.step.step!r} failed {task.attempts} time(s); last: {code} on {dev.name}: {reason}"
            self._finish(e, "abandoned", why)

    def _quarantine(self, dev: Device) -> None:
        dev.quarantined = True
        self.counts["quarantined"] += 1
        probe = self.s.orchestrator.probe_after_s
        self._note("device.quarantined", device=dev.name, detail={"probe_after_s": probe})

        def release() -> None:
            dev.quarantined = False
            self._note("device.probe", device=dev.name)
            self._wake.set()

        self.clock.call_later(probe, release)

    def _finish(self, e: Experiment, status: str, reason: str = "") -> None:
        e.status, e.reason, e.t_done = status, reason, self.now
        del self.active[e.id]
        if status == "done":
            e.scores = scores(e.outputs, self.s.chemistry.targets)
            for name, sc in e.scores.items():
                if name not in self.best or sc < self.best[name][0]:
                    self.best[name] = (sc, e.id)
                if sc == 0 and name not in self.met_at:
                    self.met_at[name] = self.now - self._t0
                    self.met_after[name] = sum(1 for x in self.experiments if x.status in ("done", "abandoned"))
                    self.met_cost[name] = self.cost
                    self._note("target.met", e.id, detail=name)
            self.counts["degraded"] += e.degraded
        self.history.append(Outcome(e.params, e.outputs if status == "done" else None,
                                    min(e.scores.values()) if e.scores else None, reason))
        numeric = {k: v for k, v in e.outputs.items() if isinstance(v, (int, float))}
        self._note(f"experiment.{status}", e.id, detail={"reason": reason, "outputs": numeric, "scores": e.scores})
        self.journal.experiment(e)
        if not self.clock.is_virtual:
            self.journal.flush()  # live runs: a finished experiment is on disk at once

    # -- shutdown ---------------------------------------------------------
    def _shutdown(self) -> None:
        for dev in self.devices.values():
            att = dev.attempt
            if att is not None and not att.resolved:
                att.resolved = True
                if att.deadline:
                    att.deadline.cancel()
                dev.busy_s += self.now - att.t_sent
                dev.attempt = None
                self.bus.publish(keys.cmd(self.s.lab, dev.name), self._pack(Kind.CANCEL, {"reason": "campaign stopped"}, att.task.id, att.n))
                self._note("attempt.cancelled", att.task.experiment.id, att.task.id, att.n, dev.name, detail=self.stopping)
        for e in self.active.values():
            if e.status == "running":
                e.status = "pending"
                e.reason = f"in the lab at shutdown ({self.stopping})" if self.stopping else "in the lab at shutdown"
                self.journal.experiment(e)
        for h in self._handles:
            h.close()
        check_accounting(self.experiments, len(self.experiments))
        self.journal.flush()

    @property
    def elapsed_s(self) -> float:
        return self.now - self._t0
