"""The end-of-run summary: the same table ``twin run`` prints and ``twin report`` reprints."""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any

from twin.campaign.ledger import UNRUNNABLE
from twin.campaign.stranded import cut_short, ran_out
from twin.core.counts import counted


EXAMPLE_CHARS = 240


@dataclass
class Summary:
    scenario: str
    seed: int
    journal: str
    lab_hours: float
    proposed: int
    done: int
    abandoned: int
    pending: int
    attempts: int
    failed_attempts: int
    retried: int
    timed_out: int
    devices_lost: int  # times a device left the bus
    quarantines: int
    invalid_messages: int
    late_results: int
    degraded_samples: int
    rejected_messages: int = 0  # well-formed but without the attempt's provenance: forged, misrouted, stale
    infeasible: int = 0  # experiments a device refused, or its safe envelope excluded
    refused_now: int = 0  # attempts a device answered "not now" (busy, warming up, still stopping): no attempt used
    presence_flaps: int = 0
    stuck: int = 0  # of ``quarantines``, those of a device still running a step it was told to cancel (stuck.py)
    steps_lost: int | None = None  # attempts failed because their device left (None: a journal from before)
    abandoned_reasons: dict[str, int] = field(default_factory=dict)
    abandoned_examples: dict[str, str] = field(default_factory=dict)  # each kind of reason: its first in full
    utilisation: dict[str, float] = field(default_factory=dict)
    best: dict[str, dict[str, Any]] = field(default_factory=dict)
    targets_met_h: dict[str, float] = field(default_factory=dict)
    targets_met_after: dict[str, int] = field(default_factory=dict)
    targets_met_cost: dict[str, float] = field(default_factory=dict)
    stopped: str = ""
    ended: str = ""  # why a campaign that was not stopped proposed less than its budget: its planner had no more
    resumable: bool = False  # stopped from outside (a signal, an operator): ``twin resume`` continues it
    cost: float = 0.0
    hours_cost: float = 0.0  # of ``cost``, what the instances' hours cost (devices.*.cost_per_hour)
    wall_s: float = 0.0
    events: int = 0
    decisions: int = 0
    scheduler_fallbacks: int = 0  # decisions the fallback rule made for an absent, late or wrong agent
    decision_ms: dict[str, float] = field(default_factory=dict)  # wall time per scheduler decision: p50, p99, max
    consumables: dict[str, dict[str, Any]] = field(default_factory=dict)  # item -> left, used, unit, short, out_h
    degraded_before: dict[str, int] = field(default_factory=dict)  # step -> samples that waited for it too long
    device_types: dict[str, str] = field(default_factory=dict)  # device -> its type

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def hours_compared(self, max_lab_hours: float) -> float:
        """The lab-hours a bench counts this run for: its own, or, for a run that ended early (a scheduler that
        waited for nothing, a planner that failed), the campaign's limit, which it would have run to: an early
        end must not read as the shortest run of all."""
        return max_lab_hours if self.stopped else self.lab_hours

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Summary:
        return cls(**data)

    def _repr_markdown_(self) -> str:
        """A notebook shows a summary as the viewer's summary panel does."""
        return summary_markdown(self.to_dict())


#: A device type of more instances than this is one row of utilisation: its mean and range
FOLD_INSTANCES = 8


def busy_rows(utilisation: dict[str, float], device_types: dict[str, str]) -> list[tuple[str, str]]:
    """Utilisation per device, in the lab's order; a type of many instances as one row."""
    by_type: dict[str, list[str]] = {}
    for dev in utilisation:
        by_type.setdefault(device_types.get(dev, dev), []).append(dev)
    rows = []
    for dtype, devices in by_type.items():
        if len(devices) <= FOLD_INSTANCES:
            rows += [(dev, f"{100 * utilisation[dev]:5.1f} % busy") for dev in devices]
            continue
        busy = [100 * utilisation[dev] for dev in devices]
        rows.append((f"{dtype} ×{len(devices)}", f"{sum(busy) / len(busy):5.1f} % busy on average "
                                                  f"({min(busy):.1f}–{max(busy):.1f} % per instance)"))
    return rows


def _waited_for(steps: Any) -> str:
    if not isinstance(steps, dict) or not steps:
        return ""
    return " (past chemistry.stability_s before " + ", ".join(
        f"{step} {n}" for step, n in sorted(steps.items(), key=lambda kv: -kv[1])) + ")"


def _cell(value: Any) -> str:
    return str(value).replace("|", "\\|").replace("\n", " ")


def cost_text(cost: float, hours_cost: float) -> str:
    """A campaign's cost, with the part its instances' hours make (``devices.*.cost_per_hour``) if any."""
    return f"{cost:,.0f}" + (f" ({hours_cost:,.0f} of it the devices' hours)" if hours_cost else "")


def losses_text(devices_lost: Any, steps_lost: Any) -> str:
    """How often devices left the bus, and how many running steps failed with them."""
    lost = counted(devices_lost, "device loss", "device losses")
    return lost + (f" ({counted(steps_lost, 'running step', 'running steps')} lost with them)"
                   if devices_lost and steps_lost is not None else "")


def quarantines_text(quarantines: Any, stuck: Any) -> str:
    """How often devices were quarantined, and how often for a step they did not stop when cancelled."""
    return counted(quarantines, "quarantine", "quarantines") + (
        f" ({stuck} of a device still running a step it was told to cancel)" if stuck else "")


def summary_markdown(s: dict[str, Any]) -> str:
    """A summary (as ``Summary.to_dict`` gives it, or as journalled) as a markdown table: the viewer's summary
    panel, and a notebook's view of a ``Summary``."""
    lines = [f"# {_cell(s.get('scenario', 'campaign'))} — seed {s.get('seed', '?')}", "", "| | |", "|---|---|",
             f"| experiments | {s.get('done')} done, {s.get('abandoned')} abandoned, {s.get('pending')} pending "
             f"(of {s.get('proposed')}) |",
             f"| attempts | {s.get('attempts')} ({s.get('failed_attempts')} failed, {s.get('retried')} retried, "
             f"{s.get('timed_out')} timed out) |",
             f"| faults | {losses_text(s.get('devices_lost'), s.get('steps_lost'))}, "
             f"{quarantines_text(s.get('quarantines'), s.get('stuck'))} |",
             f"| samples degraded | {s.get('degraded_samples')}{_cell(_waited_for(s.get('degraded_before')))} |",
             f"| lab time | {s.get('lab_hours', 0):.2f} h |"]
    if s.get("cost"):
        lines.insert(-1, f"| cost | {cost_text(s['cost'], s.get('hours_cost', 0.0))} |")
    for dev, busy in busy_rows(s.get("utilisation") or {}, s.get("device_types") or {}):
        lines.append(f"| {_cell(dev)} | {busy.strip()} |")
    for name, b in (s.get("best") or {}).items():
        met = (s.get("targets_met_h") or {}).get(name)
        status = f"met at {met:.2f} lab-h" if met is not None else f"best score {b.get('score')}"
        lines.append(f"| target {_cell(name)} | {status} (experiment {b.get('experiment')}) |")
    for reason, n in (s.get("abandoned_reasons") or {}).items():
        lines.append(f"| abandoned | {n} × {_cell(reason)} |")
    if s.get("stopped"):
        lines.append(f"| stopped | {_cell(s['stopped'])} |")
    elif s.get("ended"):
        lines.append(f"| ended | {_cell(s['ended'])} |")
    return "\n".join(lines)


def from_core(core: Any, journal: str, wall_s: float, events: int) -> Summary:
    """The summary of a campaign core's ledger (``twin.campaign.CampaignCore``)."""
    exps = core.experiments
    status = Counter(str(e.status) for e in exps)
    elapsed = max(core.elapsed_s, 1e-9)
    reasons: Counter[str] = Counter()
    examples: dict[str, str] = {}  # each kind's first reason, in full
    for e in exps:
        if e.status == "abandoned":
            kind = _reason_kind(e.reason)
            reasons[kind] += 1
            examples.setdefault(kind, e.reason.removeprefix(f"{kind}: ")[:EXAMPLE_CHARS])
    best = {}
    for name, (score, exp_id) in core.best.items():
        outputs = {k: v for k, v in exps[exp_id].outputs.items() if isinstance(v, (int, float))}
        best[name] = {"experiment": exp_id, "score": round(score, 4), "outputs": outputs}
    c = core.counts
    return Summary(
        scenario=core.s.name, seed=core.s.campaign.seed, journal=journal,
        lab_hours=core.elapsed_s / 3600, proposed=len(exps), done=status["done"],
        abandoned=status["abandoned"], pending=status["pending"], attempts=c.attempts,
        failed_attempts=c.failed, retried=c.retried, timed_out=c.timed_out,
        devices_lost=c.device_lost, quarantines=c.quarantined, invalid_messages=c.invalid,
        late_results=c.late, degraded_samples=c.degraded, rejected_messages=c.rejected, presence_flaps=c.flaps,
        stuck=c.stuck,
        infeasible=c.infeasible, refused_now=c.refused_now, steps_lost=c.steps_lost,
        abandoned_reasons=dict(reasons), abandoned_examples=examples,
        utilisation={d.name: round(d.busy_s / elapsed, 4) for d in core.devices.values()},
        device_types={d.name: d.type for d in core.devices.values()},
        best=best, targets_met_h={k: v / 3600 for k, v in core.met_at.items()},
        targets_met_after=dict(core.met_after), targets_met_cost=dict(core.met_cost),
        stopped=core.stopping or (f"the planner failed ({core.planner_failed}); the experiments it had proposed "
                                  "were run to their end" if core.planner_failed else cut_short(core)),
        ended=ran_out(core),
        resumable=core.resumable,
        cost=core.cost, hours_cost=core.hours_cost, wall_s=wall_s, events=events,
        decisions=len(core.decision_wall_s), decision_ms=_percentiles(core.decision_wall_s),
        degraded_before=dict(Counter(e.degraded_before for e in exps if e.degraded and e.status == "done")),
        consumables={name: {"left": round(st.level, 6), "used": round(st.used, 6), "unit": st.unit,
                            "short": st.depleted, "out_h": round(st.out_hours(core.now), 6)}
                     for name, st in core.stocks.items.items()},
    )


def _percentiles(seconds: list[float]) -> dict[str, float]:
    if not seconds:
        return {}
    ms = sorted(1000 * x for x in seconds)
    pick = lambda q: ms[min(len(ms) - 1, int(q * len(ms)))]  # noqa: E731
    return {"p50": round(pick(0.5), 4), "p99": round(pick(0.99), 4), "max": round(ms[-1], 4)}


def _reason_kind(reason: str) -> str:
    """'step 'measure' failed 3 time(s); last: timed_out on spec-1: ...' -> 'measure: timed_out'; 'step 'measure'
    refused 5 time(s), last by spec-1: ...' -> 'measure: refused'."""
    if reason.startswith("infeasible"):
        return "infeasible"
    if reason.startswith(UNRUNNABLE):
        return UNRUNNABLE
    try:
        step = reason.split("'")[1]
        if reason.startswith(f"step '{step}' refused "):
            code = "refused"
        else:
            code = reason.split("last: ")[1].split(" ")[0]
        return f"{step}: {code}" + (" (retried past max_delay_s)" if "max_delay_s" in reason else "")
    except IndexError:
        return reason


@dataclass
class LabSummary:
    """A lab that served several campaigns: each campaign's own summary, and the lab's."""

    lab: str
    seed: int
    journals: str  # the directory of the campaigns' journals
    lab_hours: float  # from the lab's start until its last campaign ended
    campaigns: dict[str, Summary]
    submitted_h: dict[str, float]  # lab hours after the lab's start
    ended_h: dict[str, float]
    priority: dict[str, int]
    owner: dict[str, str]
    not_started: dict[str, str] = field(default_factory=dict)  # campaign -> why (the lab stopped first)
    utilisation: dict[str, float] = field(default_factory=dict)  # device -> busy share of the lab's hours
    wall_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LabSummary:
        data = dict(data)
        data["campaigns"] = {k: Summary.from_dict(v) for k, v in data["campaigns"].items()}
        return cls(**data)
