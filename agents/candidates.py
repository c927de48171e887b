"""What the candidate-scoring RL scheduler sees: every (ready step, free device) pair that may run, as a row.

Unlike a fixed grid of slots, any number of ready steps, device types and instances fit: each pair that the
lab allows (a free, capable device the step need not avoid) is one candidate row of ``FEATURES`` numbers, up to
``MAX_CANDIDATES`` (beyond that, the pairs of the steps with the most work remaining are kept — the MWKR rule's
order — so a very large lab is seen in part, never mis-seen). Action ``i`` starts candidate ``i``; action
``MAX_CANDIDATES`` waits for the next event, allowed only while some device is busy. The policy
(``agents.candidate_policy``) scores every row with one shared network, so its size does not depend on the lab.

A row describes a pair in terms that carry to another lab: times divided by the scenario's typical step
duration (``twin.time_scale``), counts divided by ten, and the dispatching rules'
own orderings (the step's rank by work remaining, by duration, by waiting time) as features, so that the
network starts from what the rules know; and the lab's critical path as the job-shop heuristics weigh it (the
known work left per device type and per job against a lower bound of what remains, what arrives next from a
running step, and the step against the others the same device could take).

In a lab of several campaigns with one scheduler (``orchestrator.lab_scheduler``) a row also says whose step it
is (``LabView.campaigns``): whether its campaign has the top priority, how far it is above or below its share of
the device time, its progress, and how many steps and how much work of other campaigns queue for the same device
type. These are the last five columns (since ``candidates-v3``); a policy trained on ``candidates-v2`` reads a row
without them, and is blind to campaigns (``agents.candidate_policy.widened`` starts a v3 policy from it).

``candidates-v4`` (this labtwin's) reads what grows with the lab as a share of it: a step's operations left
against the most any ready step has, its type's ready steps against all ready steps, the operations queued for
its type against the busiest type's, the free instances of its type against its instances, ready and free
steps per device, and lab time against elapsed plus the bound on what remains — where v2 and v3 divided
counts by ten and time by a hundred typical steps, so that a 50-job shop showed counts five times any its
policy had seen. A v2 or v3 policy still reads its own columns, and one trained from it keeps them
(``trained_encoding``).
"""

from __future__ import annotations

import bisect
from typing import Any

import numpy as np

from twin import ANY_WORKFLOW, Assignment, LabView, ReadyStep, Scenario, drawn_at_random, time_scale

ENCODING = "candidates-v4"
MAX_CANDIDATES = 128
FEATURES = 34
GLOBALS = 8
OBS_SIZE = MAX_CANDIDATES * FEATURES + GLOBALS
ACTIONS = MAX_CANDIDATES + 1
WAIT = MAX_CANDIDATES
CLIP = 10.0
# earlier encodings a policy file may have been trained with, and the row width each reads: v2 is v3 without the
# campaign columns (the last five), so a v2 policy reads the first 29 of every row and is blind to campaigns
WIDTHS = {"candidates-v2": 29, "candidates-v3": FEATURES, ENCODING: FEATURES}
# v4 reads the counts that grow with the lab as shares of it (ready steps per device, a type's ready steps and the
# operations queued for it against the busiest type's, the lab time against elapsed + the bound): a 50-job shop
# then looks like the 10-job ones it trained on, where v2/v3's "ready steps ÷ 10" ran past anything seen
RELATIVE = {ENCODING}


def trained_encoding(init_encoding: str | None) -> str:
    """The encoding a policy trained from one of ``init_encoding`` reads labs with: this labtwin's for a new policy
    or one started from a relative one; ``candidates-v3`` for one started from a v2 or v3 policy, whose columns
    keep their meaning (v2's widened by the campaign columns) so that it starts deciding as that one did."""
    return ENCODING if init_encoding is None or init_encoding in RELATIVE or init_encoding not in WIDTHS \
        else "candidates-v3"


def version(encoding: str) -> str:
    """``candidates`` (the family: this labtwin's) or one of its versions, as the version."""
    return ENCODING if encoding == "candidates" else encoding


def signature(s: Scenario | None = None, encoding: str = ENCODING) -> dict:
    """What a policy must match to be used at all; the shapes it was trained on are checked separately."""
    encoding = version(encoding)
    return {"encoding": encoding, "observation_size": MAX_CANDIDATES * WIDTHS[encoding] + GLOBALS, "actions": ACTIONS}


def _ranks(values: list[float]) -> list[float]:
    """Each value's rank in [0, 1] (0 = the smallest; ties share the lower rank)."""
    if len(values) < 2:
        return [0.0] * len(values)
    order = sorted(values)
    return [bisect.bisect_left(order, v) / (len(values) - 1) for v in values]


class Observed:
    """The range of every column a policy saw on the labs it was judged on (the rows of its candidates and the
    globals), kept in its policy file as ``observed``. A policy deciding in a larger lab than it trained on
    sees counts and work it never met (a 50-job shop queues five times the steps of the 10-job ones); held at
    the edge of this range, those read as the most it knows instead of as values its network never fitted."""

    def __init__(self, width: int) -> None:
        self.lo = np.full(width, np.inf, np.float32)
        self.hi = np.full(width, -np.inf, np.float32)
        self.glo = np.full(GLOBALS, np.inf, np.float32)
        self.ghi = np.full(GLOBALS, -np.inf, np.float32)

    def add(self, rows: np.ndarray, glob: np.ndarray) -> None:
        if len(rows):
            np.minimum(self.lo, rows.min(0), out=self.lo)
            np.maximum(self.hi, rows.max(0), out=self.hi)
        np.minimum(self.glo, glob, out=self.glo)
        np.maximum(self.ghi, glob, out=self.ghi)

    def merge(self, other: Observed | None) -> Observed:
        """This range widened by ``other``'s."""
        if other is not None:
            for mine, theirs, keep in ((self.lo, other.lo, np.minimum), (self.hi, other.hi, np.maximum),
                                       (self.glo, other.glo, np.minimum), (self.ghi, other.ghi, np.maximum)):
                keep(mine, theirs, out=mine)
        return self

    def to_meta(self) -> dict | None:
        if not np.isfinite(self.lo).all():
            return None  # no candidate was ever seen
        return {"rows": [self.lo.tolist(), self.hi.tolist()], "globals": [self.glo.tolist(), self.ghi.tolist()]}

    @classmethod
    def from_meta(cls, meta: Any, width: int, where: str) -> Observed:
        """The range a policy file records (``where`` names it in the error if it is not one)."""
        try:
            rows, glob = meta["rows"], meta["globals"]
            out = cls(width)
            out.lo, out.hi = (np.asarray(v, np.float32) for v in rows)
            out.glo, out.ghi = (np.asarray(v, np.float32) for v in glob)
            shapes_fit = out.lo.shape == out.hi.shape == (width,) and out.glo.shape == out.ghi.shape == (GLOBALS,)
            ordered = shapes_fit and bool((out.lo <= out.hi).all() and (out.glo <= out.ghi).all())
            finite = ordered and all(np.isfinite(v).all() for v in (out.lo, out.hi, out.glo, out.ghi))
        except (KeyError, TypeError, ValueError):
            finite = False
        if not finite:
            raise ValueError(f"{where}: its 'observed' is not two ranges of finite numbers ({width} row columns, "
                             f"{GLOBALS} globals, low ≤ high); policies are saved by `twin train`")
        return out


class CandidateEncoder:
    def __init__(self, scenario: Scenario, encoding: str = ENCODING) -> None:
        encoding = version(encoding)
        self.width = WIDTHS[encoding]  # a policy of an earlier encoding reads the first columns only
        self.relative = encoding in RELATIVE
        self.scale = time_scale(scenario)
        self.stability = scenario.chemistry.stability_s or 0.0
        self.encoded: list[tuple[ReadyStep, str]] = []  # the candidates of the view last encoded, in row order
        self.held: Observed | None = None  # what it sees is held inside this range (the policy's observed one)
        self.seen: Observed | None = None  # what it sees is added to this range (a policy being judged)

    def pairs(self, view: LabView) -> list[tuple[ReadyStep, str]]:
        """The candidates, in row order: steps by most work remaining, then devices by name."""
        free = sorted((f for f in view.free), key=lambda f: f.name)
        out = []
        for r in sorted(view.ready, key=lambda r: (-r.work_remaining_s, r.ready_since, r.task)):
            out += [(r, f.name) for f in free if f.device_type == r.device_type and f.name not in r.avoid]
        return out[:MAX_CANDIDATES]

    def encode(self, view: LabView) -> tuple[np.ndarray, np.ndarray]:
        """(observation, action mask)."""
        now, k = view.now, self.scale
        pairs = self.encoded = self.pairs(view)
        rows = np.zeros((MAX_CANDIDATES, FEATURES), np.float32)
        mask = np.zeros(ACTIONS, bool)
        devices = {d.name: d for d in view.devices}
        by_type: dict[str, list] = {}
        for d in view.devices:
            by_type.setdefault(d.device_type, []).append(d)
        ready_of: dict[str, int] = {}
        for r in view.ready:
            ready_of[r.device_type] = ready_of.get(r.device_type, 0) + 1
        free_of: dict[str, int] = {}
        for f in view.free:
            free_of[f.device_type] = free_of.get(f.device_type, 0) + 1
        load, arriving = self._loads(view)
        stability_of = {c.name: c.stability_s for c in view.campaigns}  # a lab's campaigns: each one's samples
        campaign_columns = self._campaigns(view, ready_of)
        ops_of: dict[str, int] = {}
        for r in view.ready:
            for t in (r.device_type, *(t for t, _ in r.then)):
                ops_of[t] = ops_of.get(t, 0) + 1
        per_unit = {t: w / max(len(by_type.get(t, ())), 1) for t, w in load.items()}  # known work per instance
        lb = max([r.work_remaining_s for r in view.ready]
                 + [(d.busy_until - now) + sum(s for _, s in d.then) for d in view.devices if d.busy_until is not None]
                 + list(per_unit.values()) + [k])
        steps = sorted({r.task: r for r, _ in pairs}.values(), key=lambda r: r.task)
        work = dict(zip((r.task for r in steps), _ranks([r.work_remaining_s for r in steps])))
        short = dict(zip((r.task for r in steps), _ranks([r.expected_s for r in steps])))
        waited = dict(zip((r.task for r in steps), _ranks([r.ready_since for r in steps])))
        group: dict[str, list[float]] = {}  # per free device, the most of each among the steps it could take
        for r, name in pairs:
            g = group.setdefault(name, [1e-9, 1e-9, 1e-9])
            g[0] = max(g[0], r.work_remaining_s)
            g[1] = max(g[1], r.expected_s)
            g[2] = max(g[2], per_unit.get(r.then[0][0], 0.0) if r.then else 0.0)
        if self.relative:  # the most of each in this lab (v4); v2 and v3 divide by ten
            then_scale = max((len(r.then) for r in view.ready), default=0) or 1
            ready_scale, ops_scale = max(len(view.ready), 1), max(ops_of.values(), default=0) or 1
        else:
            then_scale = ready_scale = ops_scale = 10
        for i, (r, name) in enumerate(pairs):
            d = devices.get(name)
            kind = by_type.get(r.device_type, [])
            nxt_type, nxt_s = r.then[0] if r.then else ("", 0.0)
            nxt = by_type.get(nxt_type, [])
            nxt_busy = sum(x.busy_until is not None for x in nxt) / len(nxt) if nxt else 0.0
            nxt_wait = min((x.busy_until - now for x in nxt if x.busy_until is not None), default=0.0) if nxt and \
                all(x.busy_until is not None for x in nxt) else 0.0
            stability = stability_of.get(r.campaign, self.stability)
            age = (now - r.sample_made) if r.sample_made is not None else 0.0
            spare = (stability - age) / k if stability and r.sample_made is not None else CLIP
            rows[i] = [
                1.0,
                r.expected_s / k,
                r.work_remaining_s / k,
                (r.work_remaining_s - r.expected_s) / k,
                (now - r.ready_since) / k,
                age / stability if stability else 0.0,
                spare,
                len(r.then) / then_scale,
                nxt_s / k,
                nxt_busy,
                nxt_wait / k,
                ready_of.get(r.device_type, 0) / ready_scale,
                free_of.get(r.device_type, 0) / (max(len(kind), 1) if self.relative else 10),
                len(kind) / 10,
                (d.failures / (d.attempts + 1)) if d else 0.0,
                (d.busy_s / max(now, k)) if d else 0.0,
                1.0 - work[r.task],  # 1: the most work remaining (MWKR's pick)
                1.0 - short[r.task],  # 1: the shortest (SPT's pick)
                1.0 - waited[r.task],  # 1: waiting longest (FIFO's pick)
                float(bool(r.avoid)),
                # the lab's critical path, as the job-shop heuristics weigh it (loads per instance ÷ the bound)
                per_unit.get(r.device_type, 0.0) / lb,
                per_unit.get(nxt_type, 0.0) / lb,
                r.work_remaining_s / lb,
                ops_of.get(r.device_type, 0) / ops_scale,
                arriving.get(r.device_type, (CLIP * k, 0.0))[0] / k,
                arriving.get(r.device_type, (0.0, 0.0))[1] / lb,
                # against the other steps this device could take instead
                r.work_remaining_s / group[name][0],
                r.expected_s / group[name][1],
                per_unit.get(nxt_type, 0.0) / group[name][2],
                *campaign_columns(r),
            ]
            mask[i] = True
        n = max(len(view.devices), 1)
        busy = sum(d.busy_until is not None for d in view.devices)
        per = n if self.relative else 10
        glob = np.array([busy / n, len(view.ready) / per, len(view.free) / per, len(pairs) / MAX_CANDIDATES,
                         view.finished / max(view.budget, 1), view.in_lab / max(view.budget, 1),
                         sum(not d.online for d in view.devices) / n,
                         now / (now + lb) if self.relative else now / (k * 100.0)], np.float32)
        mask[WAIT] = busy > 0 or not pairs
        rows, glob = np.clip(rows[:, :self.width], -CLIP, CLIP), np.clip(glob, -CLIP, CLIP)
        if self.seen is not None:
            self.seen.add(rows[:len(pairs)], glob)
        if self.held is not None:
            np.clip(rows[:len(pairs)], self.held.lo, self.held.hi, out=rows[:len(pairs)])
            np.clip(glob, self.held.glo, self.held.ghi, out=glob)
        obs = np.concatenate([rows.ravel(), glob])
        return obs.astype(np.float32), mask

    @staticmethod
    def _campaigns(view: LabView, ready_of: dict[str, int]):
        """The columns that say whose a candidate is, in a lab of several campaigns (``LabView.campaigns``): its
        campaign has the highest priority of those running (1/0), its share of the device time used so
        far less the share it is due, its progress through its budget, the other campaigns' ready steps for the
        same device type, and their part of the known work queued for that type. One campaign: 1, 0, its
        progress, 0, 0."""
        alone = (1.0, 0.0, view.finished / max(view.budget, 1), 0.0, 0.0)
        if not view.campaigns:  # one campaign (training's hot path): the same for every row
            return lambda r: alone
        states = {c.name: c for c in view.campaigns}
        top = max(c.priority for c in view.campaigns)
        count: dict[tuple[str, str], int] = {}
        work: dict[tuple[str, str], float] = {}
        for r in view.ready:
            count[r.campaign, r.device_type] = count.get((r.campaign, r.device_type), 0) + 1
            for t, s in ((r.device_type, r.expected_s), *r.then):
                work[r.campaign, t] = work.get((r.campaign, t), 0.0) + s
        total: dict[str, float] = {}
        for (_, t), w in work.items():
            total[t] = total.get(t, 0.0) + w

        def columns(r: ReadyStep) -> tuple[float, ...]:
            c = states.get(r.campaign)
            if c is None:
                return alone
            others = total.get(r.device_type, 0.0) - work.get((r.campaign, r.device_type), 0.0)
            return (float(c.priority >= top), c.used - c.share, c.finished / max(c.budget, 1),
                    (ready_of.get(r.device_type, 0) - count.get((r.campaign, r.device_type), 0)) / 10,
                    others / total[r.device_type] if total.get(r.device_type) else 0.0)
        return columns

    @staticmethod
    def _loads(view: LabView) -> tuple[dict[str, float], dict[str, tuple[float, float]]]:
        """The known work still to do per device type, and per type the soonest step to arrive from a running one
        (lab-s until then, its experiment's work remaining after that)."""
        load: dict[str, float] = {}
        for r in view.ready:
            load[r.device_type] = load.get(r.device_type, 0.0) + r.expected_s
            for t, s in r.then:
                load[t] = load.get(t, 0.0) + s
        arriving: dict[str, tuple[float, float]] = {}
        for d in view.devices:
            if d.busy_until is None:
                continue
            left = max(0.0, d.busy_until - view.now)
            load[d.device_type] = load.get(d.device_type, 0.0) + left
            for t, s in d.then:
                load[t] = load.get(t, 0.0) + s
            if d.then:
                t = d.then[0][0]
                rest = sum(s for _, s in d.then)
                if t not in arriving or left < arriving[t][0]:
                    arriving[t] = (left, rest)
        return load, arriving

    def decode(self, view: LabView, action: int) -> list[Assignment]:
        """The assignment an action means, for the view last encoded; an invalid one is raised."""
        action = int(action)
        if action == WAIT:
            return []
        if not 0 <= action < len(self.encoded):
            raise ValueError(f"action {action}: there are {len(self.encoded)} candidates")
        r, name = self.encoded[action]
        return [Assignment(r.task, name)]


def lab_shape(s: Scenario) -> dict:
    """What a scheduler policy's fit is judged on: the step types a lab runs, how many device types it has, and
    the most instances of one type (a lab drawn by ``twin.scenario.random_labs`` stands for any workflow; a lab
    file of several campaigns, or one serving none yet, runs whatever its devices run)."""
    steps = {ANY_WORKFLOW} if drawn_at_random(s) else {w.step for w in s.workflow}
    routes = s.campaign.planner_options.get("proposals", [])
    for p in routes:  # a job shop's fixed routes
        steps |= {str(step.get("step")) for step in p.get("route", [])}
    if s.campaigns or not (steps or routes):  # a lab file: every step its devices run (campaigns come and go)
        steps |= {step for d in s.devices.values() for step in d.steps}
    counts = [d.instances for d in s.devices.values()]
    return {"steps": sorted(steps), "device_types": len(counts), "instances": max(counts, default=0)}


def widen(fits: dict | None, more: dict) -> dict:
    """The range of shapes ``fits`` covers, widened to ``more`` (a ``lab_shape`` or another range)."""
    def as_range(x: dict) -> dict:
        n, m = x["device_types"], x["instances"]
        return {"steps": list(x["steps"]), "device_types": list(n) if isinstance(n, list) else [n, n],
                "instances": list(m) if isinstance(m, list) else [1, m]}

    b = as_range(more)
    if not fits:
        return b
    a = as_range(fits)
    return {"steps": sorted(set(a["steps"]) | set(b["steps"])),
            "device_types": [min(a["device_types"][0], b["device_types"][0]),
                             max(a["device_types"][1], b["device_types"][1])],
            "instances": [1, max(a["instances"][1], b["instances"][1])]}


def fits_of(meta: dict, where: str) -> dict | None:
    """The range of shapes a policy file records it was trained on (None if it says none); ``where`` names the file
    in the error if it is not one."""
    fits = meta.get("fits")
    if fits is None:
        return None

    def whole_range(v: Any) -> bool:
        return (isinstance(v, list) and len(v) == 2 and all(isinstance(x, int) and not isinstance(x, bool) for x in v)
                and 0 <= v[0] <= v[1])
    if not (isinstance(fits, dict) and isinstance(fits.get("steps"), list)
            and all(isinstance(step, str) for step in fits["steps"])
            and whole_range(fits.get("device_types")) and whole_range(fits.get("instances"))):
        raise ValueError(f"{where}: its 'fits' is not the shapes a policy was trained on ({{'steps': [step types], "
                         "'device_types': [least, most], 'instances': [least, most]}); policies are saved by "
                         "`twin train`")
    return fits


def outside(fits: dict, shape: dict) -> list[str]:
    """Why a lab of ``shape`` is outside what a policy was trained on (empty: inside)."""
    why = []
    unseen = [] if ANY_WORKFLOW in fits["steps"] else sorted(set(shape["steps"]) - set(fits["steps"]))
    if unseen:
        why.append(f"step type(s) {unseen} never seen in training (trained on {fits['steps']})")
    lo, hi = fits["device_types"]
    if not lo <= shape["device_types"] <= hi:
        n = shape["device_types"]
        why.append(f"{n} device type{'' if n == 1 else 's'} (trained on {lo if lo == hi else f'{lo}–{hi}'})")
    if shape["instances"] > fits["instances"][1]:
        why.append(f"{shape['instances']} instances of one type (trained on at most {fits['instances'][1]})")
    return why
