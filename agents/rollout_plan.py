"""`campaign.rollouts`: the rl scheduler plays a deterministic lab in the twin before it starts, and follows its
best run.

The lab is played ``rollouts`` times on the fast runtime in lockstep (``agents.lockstep``: the greedy run and the
others sampled from the policy). The run with the best objective (lab time, degraded samples and abandoned
experiments, weighted by ``training.weights``) gives each device its order of steps, and the campaign keeps those
orders: a device starts the next step of its order as soon as that step is ready, and waits for it otherwise.
Each step then starts no later than it did in the run planned, so a lab that keeps to the plan ends no later.
Where the lab leaves the plan — a step the plan never held (a retry, an experiment it did not foresee), a device
of the plan that is down, nothing running and no device's next step ready — the policy decides from then on,
greedily. A campaign resumed part-way keeps to the plan with the steps it has not started.

A pure job shop (every experiment a fixed route, all in the lab from the start, no set-up or cleaning, nothing that
degrades or runs out) is also played backwards: every job's route reversed, the same shop in time reversed. A run of
it, each device's order read backwards, is an order for the shop as written whose makespan is no longer (the longest
path through the jobs' and devices' orders is the same either way), so half the runs search from the other end,
the first of them greedy too: ``rollouts: 2`` is the greedy run each way, the better kept.

Only a lab that runs as it was played can be planned: every experiment known before it starts (a job shop),
durations without spread, no faults. The best of several runs of a lab with chance in it is its luckiest, not
its best decided: such a lab (``twin.why_runs_vary``) is refused, with the field to change.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from agents.candidates import CandidateEncoder, Observed
from agents.lockstep import SAMPLE_TEMPERATURES, lockstep
from agents.judging import count, objective
from twin import Assignment, LabView, Scenario, lab_span, prepare, weighted_objective

if TYPE_CHECKING:
    from agents.active_search import ActiveSearch

log = logging.getLogger(__name__)
ROUND = 32  # campaign.rollout_search: active: the runs played between two tunings of the policy
BATCH = 64  # runs played at once: each holds a whole lab in memory
HEARTBEAT_S = 10.0  # how often a long planning says how far it is


@dataclass
class Plan:
    """The best of ``rollouts`` runs: each device's order of steps, and what the runs scored."""

    orders: dict[str, list[str]]
    rollouts: int
    best: float  # its objective
    greedy: float  # the greedy run's
    best_h: float  # its lab-hours
    greedy_h: float
    seconds: float  # wall time the rollouts took
    search: str = "sample"  # campaign.rollout_search
    backwards: int = 0  # of the runs, those played on the shop backwards
    degraded: tuple[int, int] = (0, 0)  # degraded samples, its and the greedy run's
    abandoned: tuple[int, int] = (0, 0)  # abandoned experiments, its and the greedy run's
    searched: int | str | None = None  # campaign.local_search: the swaps tried on its orders, or why none were
    played_h: float = 0.0  # the best run's lab-hours as played, before the search
    shortest: bool = False  # the search found a plan that no order of the devices' steps beats

    def describe(self) -> str:
        gain = 100 * (1 - self.best / self.greedy) if self.greedy else 0.0
        how = f" (active search: the policy tuned on this lab after every {ROUND})" if self.search == "active" else ""
        if self.backwards:
            how += f" ({self.backwards} of them on the shop played backwards)"
        # what else the objective weighs, where the runs differ in it (lab time alike, fewer degraded samples)
        also = "".join(f", {what} {mine} against {greedy}" for what, (mine, greedy) in
                       (("degraded samples", self.degraded), ("abandoned experiments", self.abandoned)) if mine != greedy)
        ran = (f"the best of {self.rollouts} rollouts in the twin{how}" if self.rollouts > 1
               else "the greedy run in the twin")
        if isinstance(self.searched, str):
            ran += f" (campaign.local_search left out: it needs {self.searched})"
        elif self.searched is not None:
            shortest = (" (the shortest plan there is: its longest path is one job's work, or one device's with no "
                        "other of its type)") if self.shortest else ""
            ran += f", {lab_time(self.played_h)} as played, then {self.searched:,} tabu-search swaps on its orders" \
                   f"{shortest},"
        if self.rollouts == 1 and self.searched is None:
            return f"{ran} takes {lab_time(self.best_h)} ({self.seconds:.1f} s of planning)"
        return (f"{ran} takes {lab_time(self.best_h)} against the greedy run's {lab_time(self.greedy_h)}{also} "
                f"(objective {gain:.1f} % lower; {self.seconds:.1f} s of planning)")


def lab_time(hours: float) -> str:
    """Lab seconds for a lab of minutes (a job shop), else lab-hours."""
    return lab_span(hours * 3600, prefix="lab-")


def plan(s: Scenario, scorer: torch.nn.Module, rollouts: int, encoding: str,
         on_batch: Callable[[int, float], None] | None = None, held: Observed | None = None,
         on_share: Callable[[float, float], None] | None = None,
         on_search: Callable[[int, float, float], None] | None = None) -> Plan:
    """Play ``s`` ``rollouts`` times with the policy whose candidate scores ``scorer`` gives; the best run's plan.
    ``on_batch(played, best lab-hours so far)`` after each batch but the last; ``on_share(share of the steps
    played, wall seconds)`` every ``HEARTBEAT_S`` of wall time. ``held``: the range the policy's inputs are held in
    (its file's), so that the greedy run played is the one the lab would run. ``campaign.rollout_search:
    active`` plays the runs in rounds, tuning a copy of the policy on this lab between them (``agents.active_search``).
    ``on_search(swaps, the shortest lab-hours so far, wall seconds)`` every ``HEARTBEAT_S`` of ``campaign.local_search``."""
    t0 = time.perf_counter()
    lab = prepare(s, clock="virtual", bus="memory")
    draws = torch.Generator().manual_seed(s.campaign.seed)  # the same lab and seed, the same plan
    back = backwards(lab)
    labs = [lab] if back is None else [lab, back]
    searches: list[Any] = [None] * len(labs)
    if s.campaign.rollout_search == "active":
        from agents.active_search import ActiveSearch  # it imports the training's loss and fitting

        searches = [ActiveSearch(scorer, s.campaign.seed + way) for way in range(len(labs))]
    # sampled: the runs split between the directions even when they are fewer than a batch
    size, temperatures = (ROUND, (1.0,)) if searches[0] else (min(BATCH, -(-rollouts // len(labs))),
                                                                 SAMPLE_TEMPERATURES)
    orders: list[dict[str, list[str]]] = []
    summaries: list[Any] = []
    scores: list[float] = []
    heartbeat = _Heartbeat(rollouts * _steps(lab), t0, on_share)
    ways: list[int] = []  # each run's direction: 0 as written, 1 backwards
    for n, first in enumerate(range(0, rollouts, size)):
        way = n % len(labs)  # batches take turns: the shop as written, then backwards
        greedy = n < len(labs)  # each direction's first run is its greedy one
        search = searches[way]
        batch: list[dict[str, list[str]]] = [{} for _ in range(min(size, rollouts - first))]
        if search:
            search.start(len(batch))
        played = lockstep(labs[way], search.net if search else scorer, len(batch), temperatures, encoding,
                          seen=partial(_keep, batch, heartbeat, search), greedy_first=greedy, generator=draws,
                          held=held)
        summaries += played
        scores += [objective(summary, labs[way]) for summary in played]
        orders += batch
        ways += [way] * len(batch)
        if search and len(summaries) < rollouts:
            search.learn(scores[first:], greedy_first=greedy)
        if on_batch is not None and len(summaries) < rollouts and len(summaries) // BATCH > first // BATCH:
            on_batch(len(summaries), min(summary.lab_hours for summary in summaries))
    best = min(range(rollouts), key=scores.__getitem__)
    order = forwards(orders[best], steps_per_job(lab)) if ways[best] else orders[best]  # only the run kept is read back
    kept = Plan(order, rollouts, scores[best], scores[0], summaries[best].lab_hours, summaries[0].lab_hours,
                time.perf_counter() - t0, s.campaign.rollout_search,
                ways.count(1),
                *((count(summaries[best], what), count(summaries[0], what)) for what in ("degraded_samples", "abandoned")))
    if s.campaign.local_search:
        _search_orders(kept, lab, fixed_routes(lab), s.campaign.seed, on_search)
        kept.seconds = time.perf_counter() - t0
    return kept


def _search_orders(kept: Plan, lab: Scenario, job_shop: bool, seed: int,
                   tell: Callable[[int, float, float], None] | None = None) -> None:
    """``campaign.local_search``: the plan's orders shortened by a tabu search (``agents.order_search``), on a job
    shop (``fixed_routes``) whose steps last as its duration models say; elsewhere the plan stays the best run's,
    and says why."""
    from agents.order_search import improve, shop_of

    swaps = lab.campaign.local_search
    if not job_shop:
        kept.searched = ("a job shop only (every experiment a fixed route, all in the lab from the start, no shelf "
                         "life or consumables)")
        log.warning("campaign.local_search: %d: the tabu search orders %s; the plan is the best run's as played",
                    swaps, kept.searched)
        return
    shop = shop_of(lab)
    planned = {task for tasks in kept.orders.values() for task in tasks}
    if planned != set(shop.tasks):  # an experiment the run abandoned (refused, infeasible) has steps no device ran
        kept.searched = (f"a run that started every step, and the best run started {len(planned)} of the shop's "
                         f"{len(shop.tasks)} (it abandoned experiments)")
        log.warning("campaign.local_search: %d: the tabu search needs %s; the plan is the best run's as played",
                    swaps, kept.searched)
        return
    played_s = kept.best_h * 3600
    kinds = {name: dtype for dtype in lab.devices for name in lab.instance_names(dtype)}
    found = improve(shop, kept.orders, swaps, seed, None if tell is None else
                    lambda done, best_s, seconds: tell(done, best_s / 3600, seconds), HEARTBEAT_S, kinds)
    if found.start_length > played_s * (1 + 1e-9) + 1e-6:  # its steps took less than their models say: not ours
        kept.searched = (f"steps as long as their devices' duration models say, and the best run's orders come to "
                         f"{lab_time(found.start_length / 3600)} by them against the {lab_time(kept.best_h)} played")
        log.warning("campaign.local_search: %d: the tabu search needs %s; the plan is the best run's as played",
                    swaps, kept.searched)
        return
    kept.searched, kept.shortest, kept.played_h = found.iterations, found.shortest, kept.best_h
    if found.length < played_s:
        kept.orders = found.orders
        kept.best_h = found.length / 3600
        kept.best = weighted_objective(lab, found.length, *(n for n, _ in (kept.degraded, kept.abandoned)))


def fixed_routes(lab: Scenario) -> bool:
    """Whether ``lab`` is a job shop: every experiment a fixed route, all in the lab from the start, nothing that
    degrades or runs out (set-up and cleaning are part of each step's time on its device)."""
    c = lab.campaign
    proposals = (c.planner_options.get("proposals") or [])[:c.budget]
    return not (c.planner != "fixed" or not proposals or c.max_in_flight < len(proposals) or lab.consumables
                or lab.chemistry.stability_s or not all(p.get("route") for p in proposals))


def backwards(lab: Scenario) -> Scenario | None:
    """``lab`` with every experiment's route reversed, if it is a pure job shop (see the module's doc), else None."""
    if not fixed_routes(lab) or any(d.setup_s or d.clean_s for d in lab.devices.values()):
        return None
    proposals = lab.campaign.planner_options["proposals"][:lab.campaign.budget]
    reversed_proposals = [{**p, "route": list(reversed(p["route"]))} for p in proposals]
    return prepare(lab, overrides={"campaign.planner_options.proposals": reversed_proposals})


def steps_per_job(lab: Scenario) -> list[int]:
    """How many steps each experiment of a job shop's fixed routes has (experiment ``e<j>``: entry j)."""
    return [len(p["route"]) for p in lab.campaign.planner_options["proposals"][:lab.campaign.budget]]


def forwards(order: dict[str, list[str]], steps: list[int]) -> dict[str, list[str]]:
    """Each device's order of a run of the shop played backwards, as an order of the shop as written: read from
    the end, job j's k-th step from the end (``e<j>s<k>``) its k-th from the start (``steps``: each job's steps)."""
    flipped = {}
    for device, tasks in order.items():
        flipped[device] = [f"e{j}s{steps[int(j)] - 1 - k}" for j, k in map(_job_step, reversed(tasks))]
    return flipped


def _job_step(task: str) -> tuple[str, int]:
    """A job shop's step ``e<j>s<k>`` as (j, k)."""
    job, k = task[1:].split("s", 1)
    return job, int(k)


def _keep(orders: list[dict[str, list[str]]], heartbeat: _Heartbeat, search: ActiveSearch | None, i: int,
          encoder: CandidateEncoder, obs: np.ndarray, mask: np.ndarray, action: int, made: list[Assignment]) -> None:
    """Each run's order of steps on each device, as it assigns them (and its choices, for an active search)."""
    for a in made:
        orders[i].setdefault(a.device, []).append(a.task)
    heartbeat.started(len(made))
    if search is not None:
        search.seen(i, encoder, obs, mask, action)


def _steps(lab: Scenario) -> int:
    """The steps one run of a planned lab starts: every experiment is known (a fixed planner's proposals) and none
    is retried (no faults)."""
    proposals = (lab.campaign.planner_options.get("proposals") or [])[:lab.campaign.budget]
    return sum(len(p.get("route") or lab.workflow or ()) for p in proposals)


@dataclass
class _Heartbeat:
    """Calls ``tell(share of the steps started, wall seconds)`` every ``HEARTBEAT_S``."""

    total: int
    t0: float
    tell: Callable[[float, float], None] | None
    done: int = 0
    told: float = 0.0

    def started(self, n: int) -> None:
        self.done += n
        if self.tell is None or not self.total:
            return
        now = time.perf_counter()
        if now - max(self.t0, self.told) >= HEARTBEAT_S:
            self.told = now
            self.tell(min(1.0, self.done / self.total), now - self.t0)


@dataclass
class PlanFollower:
    """Keeps each device's order of the plan while the lab does; ``decide`` gives None once it has left it."""

    plan: Plan
    queues: dict[str, deque[str]] = field(init=False)
    left: set[str] = field(init=False)  # the plan's steps not started yet
    fresh: bool = field(init=False, default=True)  # no decision asked yet
    guessed: set[str] = field(init=False, default_factory=set)  # taken for done when a resumed campaign began

    def __post_init__(self) -> None:
        self.left = {task for tasks in self.plan.orders.values() for task in tasks}
        self._queue()

    def _queue(self) -> None:
        """Each device's steps of the plan not started yet, in the plan's order."""
        self.queues = {device: deque(t for t in tasks if t in self.left) for device, tasks in self.plan.orders.items()}

    def decide(self, view: LabView) -> list[Assignment] | None:
        if self.fresh:
            self.fresh = False
            if any(d.attempts for d in view.devices):  # a resumed campaign: some of the plan is done or running
                why = self._resume(view)
                if why:
                    return self._left_plan(view, why)
        strays = [r.task for r in view.ready if r.task not in self.left]
        if strays and set(strays) <= self.guessed:
            self._unguess(strays)
            strays = []
        if strays:
            return self._left_plan(view, f"step {strays[0]} is ready and the plan does not hold it (still)")
        online = {d.name for d in view.devices if d.online}
        down = [name for name, queue in self.queues.items() if queue and name not in online]
        if down:
            return self._left_plan(view, f"{down[0]} is down with steps of the plan still to run")
        ready = {r.task for r in view.ready}
        out = []
        for device in view.free:
            queue = self.queues.get(device.name)
            if queue and queue[0] in ready:
                task = queue.popleft()
                self.left.discard(task)
                out.append(Assignment(task, device.name))
        if not out and ready and not any(d.busy_until is not None for d in view.devices) and \
                len({_job_step(t)[0] for t in ready}) >= view.in_lab:
            # a plan kept to always has a step to start when nothing runs: the earliest one not started (unless an
            # experiment in the lab has no step ready, nor running: one in a retry's back-off, which will come)
            return self._left_plan(view, "nothing runs and no device's next step is ready (an experiment it "
                                         "counted on ended early?)")
        return out

    def _resume(self, view: LabView) -> str:
        """A campaign resumed part-way: the steps it has started come off the devices' orders, and the plan goes on
        with the rest. A job's steps before the one ready or running are done; a job with no step ready or running
        is taken for done, and a step running for started. Either may be retried (a deadline passed while the
        campaign was dead): such a step, ready again, is put back where the plan had it, with its job's later
        steps. Returns why the plan cannot go on, or ''."""
        at: dict[str, float] = {}  # each job with a step ready or running: that step's place in the job
        running = set()
        for d in view.devices:
            if d.busy_until is not None:
                if not d.task:
                    return f"the campaign had started before the plan was made (resumed), and {d.name} runs a step " \
                           "the lab does not name"
                running.add(d.task)
        for task in [r.task for r in view.ready] + sorted(running):
            if task not in self.left:
                return f"the campaign resumed with step {task} ready or running, which the plan does not hold"
            job, k = _job_step(task)
            at[job] = min(at.get(job, k), k)
        # a step running then may come back too: its deadline may have passed while the campaign was dead
        self.guessed = running | {t for t in self.left if _job_step(t)[0] not in at}
        self.left -= self.guessed | {t for t in self.left if _job_step(t)[1] < at.get(_job_step(t)[0], 0)}
        self._queue()
        log.info("the campaign resumed at %.0f lab-s: the plan goes on with its %d steps not started", view.now,
                 len(self.left))
        return ""

    def _unguess(self, ready: list[str]) -> None:
        """Steps taken for done when the campaign resumed are ready after all: they, and their jobs' later steps,
        go back into the plan where it had them."""
        for task in ready:
            job, k = _job_step(task)
            back = {t for t in self.guessed if _job_step(t)[0] == job and _job_step(t)[1] >= k}
            self.guessed -= back
            self.left |= back
        self._queue()

    def _left_plan(self, view: LabView, why: str) -> None:
        log.warning("the lab left the plan at %.0f lab-s: %s; the policy decides from here", view.now, why)
        return None
