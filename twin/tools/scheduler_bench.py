"""`twin bench schedulers`: every scheduler on the same campaigns, over many seeds.

Every run is a real campaign in virtual time over the memory bus; an agent
scheduler (``rl:PATH``) is asked over the bus like in a live run, so its
decision latency includes the round trip. A job shop is deterministic, so it
runs once per scheduler, and CP-SAT's offline optimum for the instance is
the bound each makespan is compared with.
"""

from __future__ import annotations

import statistics
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from twin.core import plugins
from twin.core.counts import counted
from twin.core.errors import TwinError
from twin.runtime.assembly import plays_ahead
from twin.runtime.lab import prepare, run
from twin.tools.planner_bench import label, over_seeds
from twin.tools.pool import WorkerPool
from twin.scenario import Scenario, why_runs_vary

RULES = ("fifo", "spt", "mwkr", "least-loaded", "oldest-sample")


@dataclass
class Run:
    scheduler: str
    seed: int
    makespan_s: float
    utilisation: float  # mean over devices
    degraded: int
    lost: int  # abandoned experiments
    fallbacks: int
    decision_p50_ms: float
    decision_p99_ms: float
    stopped: str = ""  # why the campaign ended early, if it did (its planner failed, say)


def one(scenario: Scenario, scheduler: str, seed: int) -> Run:
    with tempfile.TemporaryDirectory() as d:
        # a rule runs as it goes
        rollouts = {} if plays_ahead(scheduler) else {"campaign.rollouts": 1, "campaign.local_search": 0}
        s = run(scenario, journal=Path(d) / "j.db", seed=seed, bus="memory", clock="virtual",
                overrides={"campaign.scheduler": scheduler, **rollouts}, agent_in_process=True, handle_signals=False,
                options_checked=True)
    util = statistics.mean(s.utilisation.values()) if s.utilisation else 0.0
    hours = s.hours_compared(scenario.campaign.max_lab_hours)
    return Run(scheduler, seed, hours * 3600, util, s.degraded_samples, s.abandoned, s.scheduler_fallbacks,
               s.decision_ms.get("p50", 0.0), s.decision_ms.get("p99", 0.0), s.stopped)


def _one(args: tuple) -> Run:
    return one(*args)


def deterministic(s: Scenario) -> bool:
    return s.jobshop is not None and not why_runs_vary(s)


BOUND_S = 120.0  # how long CP-SAT may take over a shop's bound


@dataclass(frozen=True)
class Bound:
    """CP-SAT's best makespan of a shop, and whether it proved it optimal within ``seconds``."""

    lab_s: float
    proven: bool
    seconds: float = BOUND_S

    def title(self) -> str:
        return (f"CP-SAT optimum {self.lab_s:.0f} lab-s" if self.proven else
                f"CP-SAT's best in {self.seconds:g} s {self.lab_s:.0f} lab-s, not proven optimal")

    def caption(self) -> str:
        return ("vs bound: gap to CP-SAT's optimum; " if self.proven else
                f"vs bound: against CP-SAT's best schedule in {self.seconds:g} s, which it did not prove optimal "
                "(the gap to the optimum is at least this); ")


def bound_in(pool: WorkerPool, s: Scenario, say: Callable[[str], None] | None = None) -> Bound | None:
    """``bound(s)``, solved in one of the bench's workers: CP-SAT's C++ does not look at Python's signals, so a
    Ctrl-C or SIGTERM during a solve in this process waited for its end (up to ``BOUND_S``); a worker is stopped
    with the pool. ``say`` is told of a shop of more than 100 operations, whose solve may take a while, as it
    starts, and if it ends with no schedule."""
    long = sum(len(p.get("route") or ()) for p in s.campaign.planner_options.get("proposals", [])) > 100
    if say is not None and long:
        say(f"CP-SAT solving the shop for the bound (up to {BOUND_S:.0f} s) ...")
    (solved,) = pool.completed([pool.submit(bound, s)])
    best = solved.result()
    if say is not None and long and best is None and deterministic(s) and "cp-sat" in plugins.installed("schedulers"):
        say(f"CP-SAT found no schedule in {BOUND_S:.0f} s: the table has no bound")
    return best


def bound(s: Scenario, seconds: float = BOUND_S) -> Bound | None:
    """CP-SAT's optimum makespan (lab-s) for a deterministic job shop, or its best in ``seconds``; None without
    OR-Tools or a job shop, or for a shop whose jobs may not all be in the lab at once (its optimum is another
    problem's)."""
    if not deterministic(s) or "cp-sat" not in plugins.installed("schedulers"):
        return None
    jobs = s.campaign.planner_options.get("proposals", [])
    if s.campaign.max_in_flight < len(jobs):
        return None
    try:
        best = plugins.load("schedulers", "cp-sat").offline_solution(s, seconds)
    except (ImportError, RuntimeError):  # RuntimeError: no schedule found in the time (a shop of thousands of steps)
        return None
    return Bound(float(best.makespan), bool(best.optimal), seconds)


def bench(scenario: Scenario, schedulers: list[str], seeds: int, workers: int = 2,
          on_run: Callable[[Run], None] | None = None, pool: WorkerPool | None = None) -> dict[str, list[Run]]:
    return over_seeds(_one, scenario, schedulers, 1 if deterministic(scenario) else seeds, workers, on_run, pool)


HEADER = ["scheduler", "mean", "median", "vs bound", "vs best rule", "busy", "degr.", "lost", "fallb.", "ms p50/p99"]


#: Columns of counts: what each counts, and what a run that never counted one did not do. A table may leave out
#: a column that is nought throughout.
COUNTS = {"degr.": ("degraded samples", "degraded a sample"), "lost": ("abandoned experiments", "abandoned an experiment"),
          "fallb.": ("decisions the fallback rule made (an agent absent or late)", "needed the fallback rule")}


def caption(unit: str, bound: Bound | None = None, silent: set[str] | frozenset[str] = frozenset(),
            ahead: str = "") -> str:
    """``ahead``: the schedulers that played the lab ahead and followed their plan, and what asked them to."""
    counts = "".join(f"{h}: {what}; " for h, (what, _) in COUNTS.items() if h not in silent)
    nothing = [did for h, (_, did) in COUNTS.items() if h in silent]
    none = f"no run {', '.join(nothing[:-1])}{' or ' if len(nothing) > 1 else ''}{nothing[-1]} (not shown); " if (
        nothing) else ""
    return (f"mean, median: makespan ({unit}); " + (bound.caption() if bound else "") + "vs best "
            f"rule: against the rule with the lowest mean; busy: mean utilisation; {counts}{none}ms: wall time per "
            "decision, median p50 / worst p99 (an rl agent is asked in the bench's process: the same decisions as "
            "over the bus, without its round trip)" + (f"; {ahead}" if ahead else ""))


def played_ahead(s: Scenario, names: list[str]) -> str:
    """What the table should say of the schedulers that play ``s`` ahead (``campaign.rollouts``,
    ``campaign.local_search``) and follow their plan: their rows are the plan's, not the policy deciding as the lab
    goes; '' when none does."""
    asked = s.campaign.plays_ahead
    ahead = [label(n) for n in names if asked and plays_ahead(n)]
    if not ahead:
        return ""
    return (f"{', '.join(ahead)}: the lab played ahead in the twin ({asked}) and the plan followed, not the "
            "policy deciding as the lab goes; the rules ran as they go")


#: A campaign of a slow scheduler that may take longer than this (wall seconds) is said before the bench runs
SLOW_RUN_S = 300.0


def slow_schedulers(s: Scenario, made: dict[str, object], runs: int) -> str:
    """What the bench may wait for, said before it starts ('' if little): schedulers with a time limit a decision
    (``time_limit_s``, CP-SAT's) times about a decision a workflow step (a job shop: an operation) per campaign."""
    proposals = s.campaign.planner_options.get("proposals") if s.jobshop is not None else None
    decisions = sum(len(p.get("route") or ()) for p in proposals) if isinstance(proposals, list) else \
        s.campaign.budget * max(1, len(s.workflow))
    slow = {name: getattr(m, "time_limit_s") for name, m in made.items()
            if isinstance(getattr(m, "time_limit_s", None), (int, float))
            and decisions * getattr(m, "time_limit_s") > SLOW_RUN_S}
    return "; ".join(f"{label(name)} decides in up to {limit:g} s of wall time, about {decisions:,} decisions a "
                     f"campaign here: up to {decisions * limit / 60:,.0f} min for each of its "
                     f"{counted(runs, 'campaign', 'campaigns')} "
                     "(--set campaign.scheduler_options.time_limit_s=S gives it less)"
                     for name, limit in slow.items())


def rows(results: dict[str, list[Run]], optimum: float | None, unit_s: float) -> list[list[str]]:
    """The table's rows; ``optimum``: the bound's makespan (lab-s)."""
    means = {k: statistics.mean(r.makespan_s for r in v) for k, v in results.items()}
    rules = [means[k] for k in results if k in RULES]
    best_rule = min(rules) if rules else None
    out = []
    for name, runs in results.items():
        m = means[name]
        out.append([
            label(name), _figure(m / unit_s), _figure(statistics.median(r.makespan_s for r in runs) / unit_s),
            f"{100 * (m / optimum - 1):+.1f}%" if optimum else "—",
            f"{100 * (m / best_rule - 1):+.1f}%" if best_rule else "—",
            f"{100 * statistics.mean(r.utilisation for r in runs):.0f}%",
            f"{statistics.mean(r.degraded for r in runs):.1f}", f"{statistics.mean(r.lost for r in runs):.1f}",
            f"{statistics.mean(r.fallbacks for r in runs):.1f}",
            f"{statistics.median(r.decision_p50_ms for r in runs):.2f}/{max(r.decision_p99_ms for r in runs):.2f}",
        ])
    return out


#: What a directory of shops also holds that is not a shop: its notes, lists and tables.
NOT_SHOPS = {".md", ".json", ".yaml", ".yml", ".csv", ".py", ".sh"}


def shops(scenario: str | Path, files: list[str]) -> list[tuple[str, str | None]]:
    """The shops ``--jobshop`` names: each file's (file, None), or a collection's (file, instance) for each of its
    instances; a directory's files in name order (not its notes and tables, ``NOT_SHOPS``). A relative file is
    the scenario's, as ``jobshop.file`` is, or else the current directory's."""
    from twin.scenario.jobshop import instances, shop_path

    out: list[tuple[str, str | None]] = []
    for file in files:
        path = shop_path(Path(scenario).parent, file)
        if path.is_dir():
            inside = sorted(str(f) for f in path.iterdir()
                            if f.is_file() and not f.name.startswith(".") and f.suffix.lower() not in NOT_SHOPS)
            if not inside:
                raise TwinError(f"--jobshop {file}: the directory holds no job-shop file")
            out += shops(scenario, inside)
            continue
        names = instances(path)
        shown = file if path == Path(scenario).parent / file else str(path.resolve())  # as the lab will find it
        out += [(shown, name) for name in names] or [(shown, None)]
    return out


def _figure(x: float) -> str:
    """A makespan with the decimals its size needs: 46.37 lab-h, 930.5 or 1999999 lab-s (two decimals on a
    seven-figure number squeezed the scheduler's name to five letters a line at 80 columns)."""
    return f"{x:.2f}" if abs(x) < 100 else f"{x:.1f}" if abs(x) < 1000 else f"{x:.0f}"


def load_variant(path: str | Path, jobshop_file: str | None = None, budget: int | None = None,
                 changes: dict | None = None, instance: str | None = None) -> Scenario:
    over = dict(changes or {})
    if jobshop_file:
        over["jobshop.file"] = jobshop_file
    if instance:
        over["jobshop.instance"] = instance
    if budget:
        over["campaign.budget"] = budget
    return prepare(path, overrides=over or None)
