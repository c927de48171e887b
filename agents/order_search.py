"""`campaign.local_search`: a tabu search over each device's order of steps in the run played ahead (the greedy
run, or the best of ``campaign.rollouts``).

A job shop's plan (``agents.rollout_plan``) is each device's order of steps; the lab follows it, each step
starting as soon as its job's previous step and its device's previous one have ended, so the lab's length is the
longest path through the jobs' and the devices' orders. This module shortens that path: Nowicki and Smutnicki's
neighbourhood (N5: on the longest path, swap the first two or the last two steps of each run of steps on one
device), each swap priced by the heads-and-tails estimate, the best swap not tabu taken (or a tabu one that beats
the best found), a swap's reverse tabu for a while, and after a long stall a restart from the best orders found
with a few random swaps on their longest path. Swapping two adjacent steps of the longest path closes no cycle
when every step takes time; two steps of one job (a job that visits a device twice) are never swapped, and a swap
that would close a cycle through steps of no length (which tie paths) is refused, so every order it keeps is one
the lab can follow. It stops early at a path that is one job's work alone, or one device's with no other of its
type: no plan is shorter. Each swap updates a topological order of the steps (Pearce and Kelly) and only the
starts and tails that change, rather than computing the path afresh. Deterministic for a seed.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from twin import Scenario

EPS = 1e-9


@dataclass
class Shop:
    """Steps (indices) with their durations and each one's previous and next step in its job (-1: none)."""

    tasks: list[str]
    duration: list[float]
    job_prev: list[int]
    job_next: list[int]
    job: list[int]  # each step's job

    @classmethod
    def of_jobs(cls, jobs: list[list[tuple[str, float]]]) -> Shop:
        """From each job's steps in order, as (task, duration)."""
        tasks, duration, prev, nxt, of = [], [], [], [], []
        for j, job in enumerate(jobs):
            for k, (task, d) in enumerate(job):
                i = len(tasks)
                tasks.append(task)
                duration.append(float(d))
                prev.append(i - 1 if k else -1)
                nxt.append(i + 1 if k + 1 < len(job) else -1)
                of.append(j)
        return cls(tasks, duration, prev, nxt, of)


@dataclass
class Result:
    orders: dict[str, list[str]]
    length: float  # the longest path through the orders kept
    start_length: float  # through the orders given
    iterations: int
    shortest: bool = False  # the search stopped at a path that is one device's or one job's work: none is shorter


class _Orders:
    """Each device's order as step indices, with each step's device, place in it and neighbours there; a
    topological order of the steps, and each step's earliest start (head) and longest path after its end (tail),
    kept up to date as steps are swapped."""

    def __init__(self, shop: Shop, sequences: list[list[int]]) -> None:
        self.shop, self.seqs = shop, sequences
        n = len(shop.tasks)
        self.machine = [-1] * n
        self.pos = [0] * n
        self.mprev = [-1] * n
        self.mnext = [-1] * n
        for m, seq in enumerate(sequences):
            for p, i in enumerate(seq):
                self.machine[i], self.pos[i] = m, p
            for a, b in zip(seq, seq[1:]):
                self.mprev[b] = a
                self.mnext[a] = b
        self.acyclic = self._full()

    def heads_tails(self) -> tuple[list[float], list[float], float] | None:
        """Each step's earliest start and the longest path after its end; the longest path. None for a cycle."""
        return (self.head, self.tail, self.length) if self.acyclic else None

    def _full(self) -> bool:
        """Everything computed afresh (Kahn's order); False for orders that close a cycle."""
        s = self.shop
        n = len(s.tasks)
        indegree = [(s.job_prev[i] >= 0) + (self.mprev[i] >= 0) for i in range(n)]
        order = [i for i in range(n) if not indegree[i]]
        for i in order:  # the list grows as steps become free: a breadth-first topological order
            for j in (s.job_next[i], self.mnext[i]):
                if j >= 0:
                    indegree[j] -= 1
                    if not indegree[j]:
                        order.append(j)
        if len(order) < n:
            return False
        self.order = order
        self.rank = [0] * n
        for r, i in enumerate(order):
            self.rank[i] = r
        self.head, self.tail = [0.0] * n, [0.0] * n
        self._heads(0, set(range(n)))
        self._tails(n - 1, set(range(n)))
        self._length()
        return True

    def _length(self) -> None:
        head, tail, d = self.head, self.tail, self.shop.duration
        self.length = max([head[i] + d[i] + tail[i] for i in range(len(d))], default=0.0)

    def _heads(self, first: int, dirty: set[int]) -> None:
        """Heads again from place ``first`` of the order on, for ``dirty`` steps and whatever their change reaches."""
        s = self.shop
        self._relax(range(first, len(self.order)), dirty, self.head, (s.job_prev, self.mprev), (s.job_next, self.mnext))

    def _tails(self, last: int, dirty: set[int]) -> None:
        """Tails again from place ``last`` of the order back, for ``dirty`` steps and whatever their change reaches."""
        s = self.shop
        self._relax(range(last, -1, -1), dirty, self.tail, (s.job_next, self.mnext), (s.job_prev, self.mprev))

    def _relax(self, places: range, dirty: set[int], value: list[float], ins: tuple[list[int], list[int]],
               outs: tuple[list[int], list[int]]) -> None:
        """``value`` (heads, or tails) of the ``dirty`` steps again, in the order's ``places``: the most of a
        neighbour's value plus its duration over the step's neighbours ``ins`` (job's, device's); a step whose value
        changes makes its neighbours ``outs`` dirty."""
        d, order = self.shop.duration, self.order
        job_in, device_in = ins
        job_out, device_out = outs
        for p in places:
            if not dirty:
                return
            i = order[p]
            if i not in dirty:
                continue
            dirty.discard(i)
            a, b = job_in[i], device_in[i]
            x = value[a] + d[a] if a >= 0 else 0.0
            if b >= 0 and value[b] + d[b] > x:
                x = value[b] + d[b]
            if x != value[i]:
                value[i] = x
                if job_out[i] >= 0:
                    dirty.add(job_out[i])
                if device_out[i] >= 0:
                    dirty.add(device_out[i])

    def swap(self, u: int, v: int) -> bool:
        """``u`` just before ``v`` on their device: ``v`` before ``u``, the order and the paths kept up to date
        (Pearce and Kelly's reordering of the steps between them). False, and nothing changed, if that would
        close a cycle: another path from ``u`` to ``v`` (steps of no length tie paths)."""
        jprev, jnext = self.shop.job_prev, self.shop.job_next
        mprev, mnext, rank, order = self.mprev, self.mnext, self.rank, self.order
        a, b = mprev[u], mnext[v]
        lo, hi = rank[u], rank[v]
        # the steps after u (by the arcs as they will be) placed no later than v: reaching v is a cycle
        after, stack = {u}, [jnext[u], b]
        while stack:
            i = stack.pop()
            if i < 0 or i in after or rank[i] > hi:
                continue
            if i == v:
                return False
            after.add(i)
            stack += (jnext[i], mnext[i])
        before, stack = {v}, [jprev[v], a]  # the steps before v placed no earlier than u
        while stack:
            i = stack.pop()
            if i < 0 or i in before or rank[i] < lo:
                continue
            before.add(i)
            stack += (jprev[i], mprev[i])  # u is not among them: the search after u would have met v
        # the arcs: a -> v -> u -> b for a -> u -> v -> b
        if a >= 0:
            mnext[a] = v
        mprev[v], mnext[v], mprev[u], mnext[u] = a, u, v, b
        if b >= 0:
            mprev[b] = u
        seq, pu = self.seqs[self.machine[u]], self.pos[u]
        seq[pu], seq[pu + 1] = v, u
        self.pos[u], self.pos[v] = pu + 1, pu
        places = sorted(rank[i] for i in before | after)
        moved = sorted(before, key=rank.__getitem__) + sorted(after, key=rank.__getitem__)
        for p, i in zip(places, moved):
            order[p] = i
            rank[i] = p
        self._heads(places[0], {u, v} | ({b} if b >= 0 else set()))
        self._tails(places[-1], {u, v} | ({a} if a >= 0 else set()))
        self._length()
        return True

    def critical_blocks(self, head: list[float], tail: list[float], length: float) -> list[list[int]]:
        """One longest path, as its runs of consecutive steps on one device."""
        s, d = self.shop, self.shop.duration
        tol = EPS * max(1.0, length)
        on = [i for i in range(len(s.tasks)) if head[i] <= tol and abs(head[i] + d[i] + tail[i] - length) <= tol]
        if not on:
            return []
        i, blocks, block = on[0], [], [on[0]]
        while True:
            end = head[i] + d[i]
            nxt = -1
            for j, same in ((self.mnext[i], True), (s.job_next[i], False)):
                if j >= 0 and abs(head[j] - end) <= tol and abs(head[j] + d[j] + tail[j] - length) <= tol:
                    nxt = j
                    break
            if nxt < 0:
                blocks.append(block)
                return blocks
            if same:
                block.append(nxt)
            else:
                blocks.append(block)
                block = [nxt]
            i = nxt


def _moves(blocks: list[list[int]], job: list[int]) -> list[tuple[int, int]]:
    """N5: the first two and the last two steps of each run, but not the first two of the path's first run nor the
    last two of its last (swapping those cannot shorten the path)."""
    moves = []
    last = len(blocks) - 1
    for b, block in enumerate(blocks):
        if len(block) < 2:
            continue
        if b > 0:
            moves.append((block[0], block[1]))
        if b < last:
            moves.append((block[-2], block[-1]))
    return [(u, v) for u, v in dict.fromkeys(moves) if job[u] != job[v]]  # a job's own steps keep their order


def _estimate(o: _Orders, head: list[float], tail: list[float], u: int, v: int) -> float:
    """The longest path through ``u`` or ``v`` once ``v`` goes before ``u`` (Taillard's estimate; exact for a path
    through them)."""
    s, d = o.shop, o.shop.duration
    a, b = o.mprev[u], o.mnext[v]
    pu, pv, su, sv = s.job_prev[u], s.job_prev[v], s.job_next[u], s.job_next[v]
    hv = max(head[pv] + d[pv] if pv >= 0 else 0.0, head[a] + d[a] if a >= 0 else 0.0)
    hu = max(head[pu] + d[pu] if pu >= 0 else 0.0, hv + d[v])
    tu = max(d[su] + tail[su] if su >= 0 else 0.0, d[b] + tail[b] if b >= 0 else 0.0)
    tv = max(d[sv] + tail[sv] if sv >= 0 else 0.0, d[u] + tu)
    return max(hv + d[v] + tv, hu + d[u] + tu)


def improve(shop: Shop, orders: dict[str, list[str]], iterations: int, seed: int = 0,
            tell: Callable[[int, float, float], None] | None = None, every_s: float = 10.0,
            kinds: dict[str, str] | None = None) -> Result:
    """``orders`` (device → its steps, every step of ``shop`` once) with a path no longer, after ``iterations``
    swaps tried. ``tell(swaps so far, the shortest path so far, wall seconds)`` every ``every_s``. ``kinds``: each
    device's type, where devices of one type could run each other's steps (None: none could). Steps stay on their
    devices; the types only keep the search from calling a plan the shortest when another instance could have
    taken some of the work on its path."""
    t0 = told = time.perf_counter()
    index = {task: i for i, task in enumerate(shop.tasks)}
    devices = list(orders)
    kinds = kinds or {}
    alike = {dev: sum(kinds.get(other, other) == kinds.get(dev, dev) for other in kinds) for dev in devices}
    o = _Orders(shop, [[index[t] for t in orders[dev]] for dev in devices])
    ht = o.heads_tails()
    if ht is None:
        raise ValueError("the orders given close a cycle with the jobs' routes: no lab could follow them")
    head, tail, length = ht
    start = best = length
    best_seqs = [list(seq) for seq in o.seqs]
    rng = random.Random(seed)
    n_ops, n_dev = len(shop.tasks), max(1, len(devices))
    tenure = 2 + n_ops // n_dev // 2
    # swaps without a better plan before a restart: 8 per step (34 reference shops, 10,000 swaps, three seeds: 1.27 %
    # from the optimum, against 1.43 with 4 and 1.68 with 2; 100,000 swaps 0.40 against 0.96 with 2)
    stall_limit = max(200, 8 * n_ops)
    tabu: dict[tuple[int, int], int] = {}
    stall = 0
    it = 0
    for it in range(1, iterations + 1):
        if tell is not None and not it % 64 and time.perf_counter() - told >= every_s:
            told = time.perf_counter()
            tell(it, best, told - t0)
        blocks = o.critical_blocks(head, tail, length)
        # the path is one job's work alone (every arc on it its job's), or one device's with no other of its type
        if all(len(b) == 1 for b in blocks) or len(blocks) == 1 and alike[devices[o.machine[blocks[0][0]]]] <= 1:
            return Result({dev: [shop.tasks[i] for i in seq] for dev, seq in zip(devices, o.seqs)}, length, start,
                          it - 1, True)
        moves = _moves(blocks, shop.job)
        if not moves:
            break
        allowed: list[tuple[float, int, int]] = []
        forbidden: list[tuple[float, int, int]] = []
        for u, v in moves:
            cost = _estimate(o, head, tail, u, v)
            (forbidden if tabu.get((v, u), 0) > it and cost >= best - EPS else allowed).append((cost, u, v))
        # every move tabu: the one whose ban ends first
        ranked = sorted(allowed) + sorted(forbidden, key=lambda m: tabu[m[2], m[1]])
        for _, u, v in ranked:
            if o.swap(u, v):  # not if it would close a cycle: then the next best
                break
        else:
            break
        tabu[(u, v)] = it + tenure + rng.randrange(tenure + 1)
        head, tail, length = o.head, o.tail, o.length
        if length < best - EPS:
            best, best_seqs, stall = length, [list(seq) for seq in o.seqs], 0
            continue
        stall += 1
        if stall >= stall_limit:  # from the best again, shaken
            o = _Orders(shop, [list(seq) for seq in best_seqs])
            head, tail, length = o.head, o.tail, o.length
            for _ in range(3):
                kick = _moves(o.critical_blocks(head, tail, length), shop.job)
                if not kick:
                    break
                if not o.swap(*rng.choice(kick)):
                    break
                head, tail, length = o.head, o.tail, o.length
            tabu.clear()
            stall = 0
    return Result({dev: [shop.tasks[i] for i in seq] for dev, seq in zip(devices, best_seqs)}, best, start, it)


def shop_of(lab: Scenario) -> Shop:
    """A job shop's steps (``e<j>s<k>``: experiment j's k-th, experiments numbered from 0 in the fixed
    planner's order), each as long as its device type's duration model says for the experiment's parameters, with its
    set-up and cleaning (the sample goes on after both)."""
    from twin import expected_duration

    proposals = lab.campaign.planner_options["proposals"][:lab.campaign.budget]
    jobs = []
    for j, p in enumerate(proposals):
        job = []
        for k, step in enumerate(p["route"]):
            dt = lab.devices[step["device"]]
            params = {**p.get("params", {}), **step.get("params", {})}
            job.append((f"e{j}s{k}", expected_duration(dt.duration, params, dt.setup_s, dt.clean_s)))
        jobs.append(job)
    return Shop.of_jobs(jobs)
