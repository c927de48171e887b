"""`twin whatif`: the same campaign under variants of the lab, paired over seeds.

A variant is a set of scenario changes (dotted fields, as ``--set`` takes them): the cross product of every
``--vary FIELD=V1,V2,...``, ``--schedulers`` and ``--planners``. Each variant runs the same seeds in virtual
time on the memory bus (the fast runtime), so seed k of one variant meets the same draws as seed k of
another as far as the lab lets it; a change is the median of the per-seed differences against the scenario
as written, which always runs too.
"""

from __future__ import annotations

import itertools
import json
import statistics
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


from twin.core.errors import ScenarioError, TwinError
from twin.runtime.checks import check
from twin.runtime.lab import make_scheduler, prepare, run
from twin.runtime.shared_run import run_shared
from twin.tools.planner_bench import SEEDS_PAIRED, bench_pool, quartiles, short
from twin.tools.pool import keep_done
from twin.scenario import Scenario
from twin.scenario.files import yaml_value
from twin.scenario.sharing import campaign_scenario

AS_WRITTEN = "as written"


@dataclass(frozen=True)
class Variant:
    label: str
    changes: tuple[tuple[str, Any], ...]  # (dotted field, value)


@dataclass
class Outcome:
    """One campaign of one variant: what the table and the files report."""

    variant: str
    seed: int
    reached: bool  # every target met
    lab_hours: float  # to the last target if reached, else the whole campaign's
    campaign_hours: float
    cost: float  # at the last target if reached, else all that was spent
    experiments: int
    abandoned: int
    degraded: int
    utilisation: dict[str, float] = field(default_factory=dict)  # per device type: mean over its instances
    per_campaign: dict[str, float] = field(default_factory=dict)  # a lab of several: each one's lab-h, start to end
    stopped: str = ""  # why the campaign (or a campaign of the lab) ended early, if it did
    stock_out: dict[str, float] = field(default_factory=dict)  # per stock: lab-h it was out (found short, until a refill)


#: Fields a what-if's runs do not read, and why: varying one would print identical rows.
UNUSED_BY_WHATIF = {
    "clock": "a what-if runs every variant on a virtual clock, whatever the scenario's clock",
    "bus": "a what-if runs every variant on a memory bus of its own, whatever the scenario's bus",
    "lab": "the lab's name only names it on a bus",
    "name": "the scenario's name only names it",
    "description": "the description only describes it"}


def parse_vary(items: list[str]) -> list[tuple[str, list[Any]]]:
    """``["devices.spectrometer.instances=1,2,3"]`` → ``[("devices.spectrometer.instances", [1, 2, 3])]``; values
    are read as YAML (``2`` an int, ``0.1`` or ``1e3`` a float, ``true`` a bool, ``[0.5, 1.5]`` a list,
    ``{fail_p: 0.1}`` a mapping, else text); a comma inside brackets or quotes does not split values."""
    out: list[tuple[str, list[Any]]] = []
    for item in items:
        name, eq, values = item.partition("=")
        name = name.strip()
        if not eq or not name or not values.strip():
            raise ScenarioError("--vary", [f"{item!r}: expected FIELD=V1,V2,... (e.g. devices.spectrometer.instances=1,2,3)"])
        if name == "campaign.seed":
            raise ScenarioError("--vary", [f"{item!r}: {SEEDS_PAIRED}"])
        if name.split(".")[0] in UNUSED_BY_WHATIF:
            raise ScenarioError("--vary", [f"{item!r}: {UNUSED_BY_WHATIF[name.split('.')[0]]}, so every variant would "
                                           "run alike; vary what the lab is (devices, workflow, campaign, ...)"])
        parsed: list[Any] = []
        for v in _split_values(values):  # an empty value is YAML's null: `campaigns.1.after=,dots` unsets it first
            try:
                value = yaml_value(v.strip())
            except ScenarioError:  # read as text, which the field then refuses or takes
                value = v.strip()
            if value in parsed:
                raise ScenarioError("--vary", [f"{item!r}: {v.strip() or 'an empty value (null)'} is given twice (each "
                                               "value is a variant)"])
            parsed.append(value)
        if any(name == n for n, _ in out):
            raise ScenarioError("--vary", [f"{name} is varied twice: give all its values in one --vary"])
        out.append((name, parsed))
    return out


def _split_values(text: str) -> list[str]:
    """``1,[2,3],{a: 4, b: 5},'x,y'`` → ``["1", "[2,3]", "{a: 4, b: 5}", "'x,y'"]``."""
    parts, depth, quote, start = [], 0, "", 0
    for i, ch in enumerate(text):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth = max(depth - 1, 0)
        elif ch == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    return parts + [text[start:]]


def axes_of(vary: list[tuple[str, list[Any]]], schedulers: list[str] | None, planners: list[str] | None
            ) -> list[tuple[str, list[Any]]]:
    out = list(vary)
    for name, option, values in (("campaign.scheduler", "--schedulers", schedulers),
                                 ("campaign.planner", "--planners", planners)):
        if not values:
            continue
        if any(field == name for field, _ in vary):
            raise TwinError(f"--vary {name} and {option} both vary {name}: give all its values once "
                            f"({option} {','.join(map(str, values))},… or --vary {name}=…,{','.join(map(str, values))})")
        out.append((name, values))
    return out


def written_values(scenario: Scenario, names: list[str]) -> dict[str, Any]:
    """What the scenario as written says for each dotted field. In a lab of several campaigns, a field of
    ``campaign`` is what its campaigns run with (a campaign's own section replaces the lab's): their one value, or
    theirs joined by '/' (``oldest-sample/fifo``), which no variant equals."""
    data = scenario.model_dump()
    runs = [campaign_scenario(scenario, c, i).model_dump() for i, c in enumerate(scenario.campaigns)]
    out = {}
    for name in names:
        if runs and name.startswith("campaign."):
            theirs = [_at(r, name) for r in runs]
            distinct = [v for i, v in enumerate(theirs) if v not in theirs[:i]]
            out[name] = distinct[0] if len(distinct) == 1 else "/".join(_shown(v) for v in distinct)
        else:
            out[name] = _at(data, name)
    return out


def _at(data: Any, name: str) -> Any:
    node: Any = data
    for part in name.split("."):
        if isinstance(node, list):
            node = node[int(part)] if part.isdigit() and int(part) < len(node) else None
        else:
            node = node.get(part) if isinstance(node, dict) else None
    return node


def variants(scenario: Scenario, vary: list[tuple[str, list[Any]]], schedulers: list[str] | None = None,
             planners: list[str] | None = None) -> list[Variant]:
    """The scenario as written, then every combination; each checked now, so a bad field or value is named
    before anything runs. A combination equal to the scenario as written is not run twice."""
    axes = axes_of(vary, schedulers, planners)
    written = written_values(scenario, [name for name, _ in axes])
    out = [Variant(AS_WRITTEN, ())]
    for combo in itertools.product(*[[(name, v) for v in values] for name, values in axes]):
        if all(written.get(name) == v for name, v in combo):
            continue
        label = ", ".join(f"{name}={v}" for name, v in combo)
        lab = prepare(scenario, overrides=dict(combo))  # a field that does not exist or a value it refuses: said now
        try:  # another driver, steps, model, planner or scheduler: what only the installed plugins can refuse
            check(lab, planners=planners or (), schedulers=schedulers or (), virtual=True)
            for name, value in combo:  # the one scheduler check() does not make: a shared lab's own
                if name.endswith("lab_scheduler") and value:
                    make_scheduler(lab, str(value))
        except TwinError as exc:
            problems = exc.problems if isinstance(exc, ScenarioError) else [str(exc)]
            raise ScenarioError(f"--vary {label}", problems) from None
        out.append(Variant(label, tuple(combo)))
    return out


def one(scenario: Scenario, variant: Variant, seed: int) -> Outcome:
    lab = prepare(scenario, overrides=dict(variant.changes) or None)
    if lab.campaigns:
        return _shared(lab, variant, seed)
    with tempfile.TemporaryDirectory() as d:
        s = run(lab, journal=Path(d) / "j.db", seed=seed, bus="memory", clock="virtual", agent_in_process=True,
                handle_signals=False, options_checked=True)
    targets = [t.name for t in lab.chemistry.targets]
    reached = bool(targets) and all(t in s.targets_met_h for t in targets)
    per_type = {}
    for dtype in lab.devices:
        values = [s.utilisation.get(name, 0.0) for name in lab.instance_names(dtype)]
        per_type[dtype] = statistics.mean(values) if values else 0.0
    hours = s.hours_compared(lab.campaign.max_lab_hours)
    return Outcome(variant.label, seed, reached, max(s.targets_met_h.values()) if reached else hours, hours,
                   max(s.targets_met_cost.values()) if reached else s.cost,
                   max(s.targets_met_after.values()) if reached else s.proposed,
                   s.abandoned, s.degraded_samples, per_type, stopped=s.stopped, stock_out=_stock_out([s]))


def _shared(lab: Scenario, variant: Variant, seed: int) -> Outcome:
    """A lab of several campaigns: reached when every campaign met every target; lab-hours (from the lab's
    start) until the last of them, else until the last campaign ended (one that stalled: at its max_lab_hours);
    cost, experiments and losses summed."""
    with tempfile.TemporaryDirectory() as d:
        # on a virtual clock and the memory bus whatever the lab file says, as a lab of one campaign runs here
        out = run_shared(prepare(lab, seed=seed, clock="virtual", bus="memory"), Path(d), handle_signals=False,
                         agent_in_process=True)
    reached, last, hours, spans = True, 0.0, out.lab_hours, {}
    for c in lab.campaigns:
        summary = out.campaigns.get(c.name)
        scenario = campaign_scenario(lab, c, 0)
        if summary is not None:  # a campaign that ended early (a stall) counts at its limit
            spans[c.name] = summary.hours_compared(scenario.campaign.max_lab_hours)
            hours = max(hours, out.submitted_h.get(c.name, 0.0) + spans[c.name])
        names = [t.name for t in scenario.chemistry.targets]
        if summary is None or not names or not all(t in summary.targets_met_h for t in names):
            reached = False
            continue
        last = max(last, out.submitted_h[c.name] + max(summary.targets_met_h.values()))
    runs = list(out.campaigns.values())
    per_type = {dtype: statistics.mean(out.utilisation.get(n, 0.0) for n in lab.instance_names(dtype))
                for dtype in lab.devices}
    return Outcome(variant.label, seed, reached, last if reached else hours, hours,
                   sum(r.cost for r in runs), sum(r.proposed for r in runs), sum(r.abandoned for r in runs),
                   sum(r.degraded_samples for r in runs), per_type, spans,
                   "; ".join(f"{n}: {c.stopped}" for n, c in out.campaigns.items() if c.stopped), _stock_out(runs))


def _stock_out(summaries: list) -> dict[str, float]:
    """Each stock's lab-hours out of stock (the lab's stocks, as every campaign that shares them reports them)."""
    out: dict[str, float] = {}
    for s in summaries:
        for name, c in s.consumables.items():
            out[name] = max(out.get(name, 0.0), c.get("out_h", 0.0))
    return out


def runs_alike(scenario: Scenario, chosen: list[Variant]) -> bool:
    """Whether every variant runs the same on every seed — a job shop: experiments known, durations fixed, no
    faults, no plan sampled ahead — so that one run each says all that more seeds would."""
    from twin.tools.scheduler_bench import deterministic

    for v in chosen:
        lab = prepare(scenario, overrides=dict(v.changes) or None)
        if not deterministic(lab) or lab.campaign.plays_ahead:
            return False
    return True


def _one(job: tuple[Scenario, Variant, int]) -> Outcome:
    return one(*job)


def whatif(scenario: Scenario, chosen: list[Variant], seeds: int, workers: int = 2,
           on_run: Callable[[Outcome], None] = lambda o: None) -> list[Outcome]:
    jobs = [(scenario, v, seed) for seed in range(seeds) for v in chosen]  # seed by seed, as a bench's runs go
    results: list[Outcome] = []
    order = {v.label: i for i, v in enumerate(chosen)}
    with bench_pool(workers) as pool:
        try:
            for fut in pool.completed([pool.submit(_one, job) for job in jobs]):
                results.append(fut.result())
                on_run(results[-1])
        except KeyboardInterrupt as stop:  # the seeds every variant finished are kept for the table
            runs = {(o.variant, o.seed) for o in results}
            whole = {seed for seed in range(seeds) if all((v.label, seed) in runs for v in chosen)}
            keep_done(stop, sorted((o for o in results if o.seed in whole), key=lambda o: (order[o.variant], o.seed)))
            raise
    return sorted(results, key=lambda o: (order[o.variant], o.seed))


def summarise(results: list[Outcome], chosen: list[Variant]) -> list[dict[str, Any]]:
    """Per variant: medians and IQRs, the paired change against the scenario as written, and the bottleneck."""
    base = {o.seed: o for o in results if o.variant == AS_WRITTEN}
    out = []
    for v in chosen:
        mine = [o for o in results if o.variant == v.label]
        if not mine:
            continue
        util = {t: statistics.mean(o.utilisation.get(t, 0.0) for o in mine) for t in mine[0].utilisation}
        deltas = [o.lab_hours - base[o.seed].lab_hours for o in mine if o.seed in base]
        cost_deltas = [o.cost - base[o.seed].cost for o in mine if o.seed in base]
        out.append({
            "variant": v.label, "changes": dict(v.changes), "runs": len(mine),
            "reached": sum(o.reached for o in mine),
            "lab_hours": quartiles([o.lab_hours for o in mine]),
            "lab_hours_change": quartiles(deltas) if deltas else None,
            "cost": quartiles([o.cost for o in mine]),
            "cost_change": quartiles(cost_deltas) if cost_deltas else None,
            "experiments": statistics.median(o.experiments for o in mine),
            "abandoned": statistics.mean(o.abandoned for o in mine),
            "degraded": statistics.mean(o.degraded for o in mine),
            "utilisation": util,
            "bottleneck": max(util, key=util.get) if util else "",
            "stock_out": {n: statistics.mean(o.stock_out.get(n, 0.0) for o in mine)
                          for n in dict.fromkeys(n for o in mine for n in o.stock_out)},
            "per_campaign": {n: statistics.median(o.per_campaign[n] for o in mine if n in o.per_campaign)
                             for n in dict.fromkeys(n for o in mine for n in o.per_campaign)},
        })
    return out


def cheapest_within(summary: list[dict[str, Any]], hours: float, targets: bool = True) -> dict[str, Any] | None:
    """The variant of least median cost (of equal costs, the fewest lab-hours) whose median lab-hours to target
    are within ``hours`` and that reached the targets in every run; None if none does. A lab without ``targets``
    (a job shop, a lab that only keeps time) is judged by its whole campaign's median lab-hours."""
    fits = [row for row in summary if (row["reached"] == row["runs"] or not targets) and row["lab_hours"][1] <= hours]
    return min(fits, key=lambda row: (row["cost"][1], row["lab_hours"][1])) if fits else None


def in_seconds(summary: list[dict[str, Any]]) -> bool:
    """Whether the table reads in lab-seconds: every variant's runs end within the hour (a job shop's 55 s read
    0.015 lab-h, and a change of 3 s −0.001)."""
    return bool(summary) and max(row["lab_hours"][2] for row in summary) < 1


def measures(summary: list[dict[str, Any]]) -> frozenset[str]:
    """The measures worth a column: experiments, cost if something costs, abandoned and degraded if some run had
    any (a column of noughts takes the room a varied field's values need)."""
    return frozenset(name for name, worth in (("experiments", True), ("cost", costs_anything(summary)),
                                              ("abandoned", any(row["abandoned"] > 0 for row in summary)),
                                              ("degraded", any(row["degraded"] > 0 for row in summary))) if worth)


def header(axes: list[str], shown: frozenset[str] = frozenset({"cost", "abandoned"}), seconds: bool = False) -> list[str]:
    """The table's columns: one per varied field (a device's field on lines of its own), then the measures
    (``shown``: the optional ones, from ``measures``)."""
    unit = "lab-s" if seconds else "lab-h"
    return [_short(name, axes) for name in axes] + \
        [unit, "IQR", f"Δ {unit}", *(["cost", "Δ cost"] if "cost" in shown else []),
         *(["exp."] if "experiments" in shown else []),
         *(["aband."] if "abandoned" in shown else []), *(["degr."] if "degraded" in shown else []), "busiest"]


def _short(name: str, axes: list[str]) -> str:
    """A varied field's column header: a device's field whole (bar "devices."), any other field by as many of its
    last parts as tell it from the other axes, a part a line."""
    parts = name.split(".")
    if parts[0] == "devices":
        return "\n".join(parts[1:])
    for n in range(1, len(parts) + 1):
        tail = parts[-n:]
        if not any(other != name and other.split(".")[-n:] == tail for other in axes):
            return "\n".join(tail)
    return "\n".join(parts)


def costs_anything(summary: list[dict[str, Any]]) -> bool:
    return any(row["cost"][2] > 0 for row in summary)


def _range(lo: float, hi: float, d: int) -> str:
    """An IQR with the median's decimals below 10 or where whole numbers would hide it ("15.6–15.8", never "16–16"
    beside a median of 15.7); else whole numbers, for a narrow column."""
    whole = f"{lo:.0f}–{hi:.0f}"
    return f"{lo:.{d}f}–{hi:.{d}f}" if hi < 10 or f"{lo:.0f}" == f"{hi:.0f}" else whole


def rows(summary: list[dict[str, Any]], axes: list[str], written: dict[str, Any], targets: bool,
         shown: frozenset[str] = frozenset({"cost", "abandoned"})) -> list[list[str]]:
    out = []
    scale, d = (3600, 0) if in_seconds(summary) else (1, 1)
    for row in summary:
        lo, mid, hi = (scale * x for x in row["lab_hours"])
        censored = "≥" if targets and row["reached"] < row["runs"] else ""
        change, cost_change = row["lab_hours_change"], row["cost_change"]
        change = change and [scale * x for x in change]
        base = row["variant"] == AS_WRITTEN
        busiest = row["bottleneck"]
        out.append([
            *[f"{_shown(written.get(name))}*" if base else _shown(row["changes"].get(name, written.get(name)))
              for name in axes],
            f"{censored}{mid:.{d}f}", _range(lo, hi, d),
            "—" if base or change is None else f"{change[1]:+.{d}f}",
            *([f"{row['cost'][1]:,.0f}", "—" if base or cost_change is None else f"{cost_change[1]:+,.0f}"]
              if "cost" in shown else []),
            *([f"{row['experiments']:g}"] if "experiments" in shown else []),
            *([f"{row['abandoned']:.1f}"] if "abandoned" in shown else []),
            *([f"{row['degraded']:.1f}"] if "degraded" in shown else []),
            f"{busiest} {100 * row['utilisation'].get(busiest, 0):.0f}%" if busiest else "",
        ])
    return out


def campaign_rows(summary: list[dict[str, Any]], axes: list[str], written: dict[str, Any]) -> list[list[str]]:
    """A lab of several campaigns: per variant, each campaign's median lab-hours from its start to its end (the
    times a lab's one scheduler trades against each other), in the order of the first variant's campaigns."""
    names = list(summary[0]["per_campaign"]) if summary else []
    return [[*(f"{_shown(written.get(a))}*" if row["variant"] == AS_WRITTEN else
               _shown(row["changes"].get(a, written.get(a))) for a in axes),
             *(f"{row['per_campaign'][n]:.1f}" if n in row["per_campaign"] else "—" for n in names)]
            for row in summary]


SHOWN_WIDTH = 40  # a variant's value in the table, at most


def _shown(value: Any) -> str:
    """A variant's value in the table: a policy by its file's name (``rl:jobshop_scheduler``; --json and --csv
    keep the path), a whole number as one (the scenario's 600 s, read as 600.0, beside a variant's 900)."""
    if type(value) is float and value.is_integer() and abs(value) < 1e15:
        return str(int(value))
    if isinstance(value, (list, dict)):
        return _compact(value)
    return "none" if value is None else short(value) if isinstance(value, str) else str(value)


def _compact(value: list | dict, width: int = SHOWN_WIDTH) -> str:
    """A list or mapping in a cell: a list of named things by their names (chemistry.targets as ``[R, G, B]``),
    else as JSON, cut to ``width`` characters (--json and --csv keep it whole)."""
    if isinstance(value, list) and value and all(isinstance(v, dict) and isinstance(v.get("name"), str)
                                                 for v in value):
        text = "[" + ", ".join(v["name"] for v in value) + "]"
    else:
        text = json.dumps(value, separators=(", ", ": "), default=str)
    return text if len(text) <= width else text[:width - 1] + "…"


def has_targets(s: Scenario) -> bool:
    """Whether the scenario (or, for a lab of several campaigns, any of them) has targets to reach."""
    return bool(s.chemistry.targets) or any(c.chemistry is not None and c.chemistry.targets for c in s.campaigns)


def caption(targets: bool, seeds: int, shown: frozenset[str] = frozenset({"cost", "abandoned"}), seconds: bool = False,
            alike: bool = False) -> str:
    unit, hours = ("lab-s", "lab-seconds") if seconds else ("lab-h", "lab-hours")
    what = (f"{unit}: {hours} until every target (of every campaign) was met (≥: not met in every run, the whole "
            "campaign counted)"
            if targets else f"{unit}: {hours} of the whole campaign (the scenario has no targets)")
    runs = ("One run per variant: each runs alike on every seed (a job shop: no chance in durations or faults)"
            if alike else f"Medians and IQR over {seeds} paired seeds")
    cost = ("cost: at the last target (else all spent)" if "cost" in shown else
            "no device costs anything (devices.*.cost, cost_per_hour), so no cost columns")
    counts = [f"exp.: experiments {'to the last target (else all run)' if targets else 'run'} (median)"
              if "experiments" in shown else "no exp. column (experiments to target) at this width",
              ("aband.: experiments abandoned (mean)" if "abandoned" in shown else
               "no run abandoned an experiment (no aband. column)"),
              *(["degr.: samples degraded (mean)"] if "degraded" in shown else [])]
    return (f"*: the scenario as written. {runs}. {what}; Δ: " + ("the change" if alike else "median of the per-seed "
            "change") + f" against the scenario as written; {cost}; {'; '.join(counts)}; busiest: the device type "
            "with the highest mean utilisation. --json or --csv: all of it")
