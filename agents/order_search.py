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
that closes a cycle through steps of no length (which tie paths) is undone, so every order it keeps is one the lab
can follow. It stops early at a path that is one job's work alone, or one device's with no other of its type: no
plan is shorter.
Deterministic for a seed.
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
    """Each device's order as step indices, with each step's device, place in it and neighbours there."""

    def __init__(self, shop: Shop, sequences: list[list[int]]) -> None:
        self.shop, self.seqs = shop, sequences
        n = len(shop.tasks)
        self.machine = [-1] * n
        self.pos = [0] * n
        for m, seq in enumerate(sequences):
            for p, i in enumerate(seq):
                self.machine[i], self.pos[i] = m, p

    def prev(self, i: int) -> int:
        p = self.pos[i]
        return self.seqs[self.machine[i]][p - 1] if p else -1

    def next(self, i: int) -> int:
        seq = self.seqs[self.machine[i]]
        p = self.pos[i] + 1
        return seq[p] if p < len(seq) else -1

    def swap(self, u: int, v: int) -> None:
        """``u`` just before ``v`` on their device: ``v`` before ``u``."""
        seq, pu = self.seqs[self.machine[u]], self.pos[u]
        seq[pu], seq[pu + 1] = v, u
        self.pos[u], self.pos[v] = pu + 1, pu

    def heads_tails(self) -> tuple[list[float], list[float], float] | None:
        """Each step's earliest start and the longest path after its end; the longest path. None for a cycle.
        (The search's inner loop: written out for speed, no tuples or generators per step.)"""
        s = self.shop
        n = len(s.tasks)
        jprev, jnext, d = s.job_prev, s.job_next, s.duration
        mprev = [-1] * n
        mnext = [-1] * n
        for seq in self.seqs:
            for a, b in zip(seq, seq[1:]):
                mprev[b] = a
                mnext[a] = b
        indegree = [(jprev[i] >= 0) + (mprev[i] >= 0) for i in range(n)]
        order = [i for i in range(n) if not indegree[i]]
        head = [0.0] * n
        for i in order:  # the list grows as steps become free: a breadth-first topological order
            end = head[i] + d[i]
            j = jnext[i]
            if j >= 0:
                if end > head[j]:
                    head[j] = end
                indegree[j] -= 1
                if not indegree[j]:
                    order.append(j)
            j = mnext[i]
            if j >= 0:
                if end > head[j]:
                    head[j] = end
                indegree[j] -= 1
                if not indegree[j]:
                    order.append(j)
        if len(order) < n:
            return None
        tail = [0.0] * n
        length = 0.0
        for i in reversed(order):
            after = 0.0
            j = jnext[i]
            if j >= 0:
                after = d[j] + tail[j]
            j = mnext[i]
            if j >= 0 and d[j] + tail[j] > after:
                after = d[j] + tail[j]
            tail[i] = after
            if head[i] + d[i] + after > length:
                length = head[i] + d[i] + after
        return head, tail, length

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
            for j, same in ((self.next(i), True), (s.job_next[i], False)):
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
    a, b = o.prev(u), o.next(v)
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
    stall_limit = max(200, 2 * n_ops)
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
        allowed, forbidden = [], []
        for u, v in moves:
            cost = _estimate(o, head, tail, u, v)
            (forbidden if tabu.get((v, u), 0) > it and cost >= best - EPS else allowed).append((cost, u, v))
        # every move tabu: the one whose ban ends first
        ranked = sorted(allowed) + sorted(forbidden, key=lambda m: tabu[m[2], m[1]])
        for _, u, v in ranked:
            o.swap(u, v)
            ht = o.heads_tails()
            if ht is not None:
                break
            o.swap(v, u)  # a cycle: another path from u to v (steps of no length tie with the one swapped)
        else:
            break
        tabu[(u, v)] = it + tenure + rng.randrange(tenure + 1)
        head, tail, length = ht
        if length < best - EPS:
            best, best_seqs, stall = length, [list(seq) for seq in o.seqs], 0
            continue
        stall += 1
        if stall >= stall_limit:  # from the best again, shaken
            o = _Orders(shop, [list(seq) for seq in best_seqs])
            head, tail, length = o.heads_tails()  # type: ignore[misc]
            for _ in range(3):
                kick = _moves(o.critical_blocks(head, tail, length), shop.job)
                if not kick:
                    break
                u, v = rng.choice(kick)
                o.swap(u, v)
                ht = o.heads_tails()
                if ht is None:
                    o.swap(v, u)
                    break
                head, tail, length = ht
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
