"""`twin bench planners`: how fast each planner finds a scenario's targets, over many seeds.

Every run is a real campaign in virtual time over the memory bus. A planner
name may carry ``~seq`` to run it sequentially (one experiment in the lab at a
time, the same devices), e.g. ``gp-bo~seq`` against the asynchronous ``gp-bo``,
and ``@SCHEDULER`` to run it with another scheduler than the scenario's, e.g.
``gp-bo@fifo~seq`` against ``gp-bo@rl:P.zip``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import statistics
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.campaign.events import ALERT_LOGGER
from twin.core.plugins import CHECKS_LOGGER
from twin.core.telling import quiet_progress
from twin.runtime.lab import FALLBACK_LOGGER, prepare, run
from twin.scenario import Scenario
from twin.tools.pool import WorkerPool, keep_done

#: Why a bench or a what-if leaves the seed alone.
SEEDS_PAIRED = ("the runs' seeds are 0 to N−1 (--seeds N), the same for everything compared, so that each run has "
                "a pair to be compared with; leave campaign.seed out, and give --seeds")


@dataclass
class Trial:
    planner: str
    seed: int
    reached: bool
    experiments: int  # finished when the last target was met (the budget if never)
    lab_hours: float  # lab time until then (the whole run if never)
    experiments_run: int
    cost: float  # spent when the last target was met (all that was spent if never)
    stopped: str = ""  # why the campaign ended early, if it did (its planner failed, say)


def parse(planner: str) -> tuple[str, str | None, str]:
    """``gp-bo@fifo~seq`` → (planner, scheduler or None, variant)."""
    name, _, variant = planner.partition("~")
    name, at, scheduler = name.partition("@")
    return name, scheduler if at else None, variant


def trial(scenario: Scenario, planner: str, seed: int) -> Trial:
    """One campaign of ``planner`` on ``scenario`` with ``seed``."""
    name, scheduler, variant = parse(planner)
    overrides = {"campaign.planner": name, "campaign.stop_on_target": True}
    if scheduler:
        overrides["campaign.scheduler"] = scheduler
    if variant == "seq":
        overrides["campaign.max_in_flight"] = 1
    with tempfile.TemporaryDirectory() as d:
        s = run(scenario, journal=Path(d) / "j.db", seed=seed, bus="memory", clock="virtual", overrides=overrides,
                agent_in_process=True, handle_signals=False,
                options_checked=True)
    targets = [t.name for t in scenario.chemistry.targets]
    reached = all(t in s.targets_met_h for t in targets)
    if reached:
        return Trial(planner, seed, True, max(s.targets_met_after.values()), max(s.targets_met_h.values()),
                     s.proposed, max(s.targets_met_cost.values()), s.stopped)
    # ended early (its planner failed, a stall): at the budget it would have run to, not its end
    experiments = max(s.proposed, scenario.campaign.budget) if s.stopped else s.proposed
    return Trial(planner, seed, False, experiments, s.hours_compared(scenario.campaign.max_lab_hours), s.proposed,
                 s.cost, s.stopped)



def _trial(args: tuple) -> Trial:
    return trial(*args)


def quiet_alerts() -> None:
    """A bench runs hundreds of campaigns and its table counts what they lost: a warning for every device type
    gone, or every step a driver failed by raising, in every campaign would bury the progress bar under
    hundreds of lines (a training run logs those at debug for the same reason). What a plugin warns of when it is
    made (a policy trained on other labs) or tells as it plans (the rl scheduler playing a lab ahead) the command
    said when it checked the plugin, before the runs."""
    logging.getLogger(ALERT_LOGGER).setLevel(logging.ERROR)
    logging.getLogger(CHECKS_LOGGER).setLevel(logging.ERROR)
    logging.getLogger("twin.runtime.fast_device").setLevel(logging.ERROR)
    logging.getLogger("twin.device.actor").setLevel(logging.ERROR)  # the same, on the asyncio runtime
    quiet_progress()


def bench_pool(workers: int) -> WorkerPool:
    """The worker processes of a bench (alerts quiet; Ctrl-C stops them at once); one pool serves a bench of
    several labs, which would otherwise start (and import everything in) new workers for each."""
    return WorkerPool(workers, initializer=quiet_alerts, once=[FALLBACK_LOGGER])


def over_seeds(one: Callable[[tuple], Any], scenario: Scenario, names: list[str], seeds: int, workers: int,
               on_each: Callable[[Any], None] | None, pool: WorkerPool | None = None) -> dict[str, list[Any]]:
    """``one((scenario, name, seed))`` for every name and seed, in parallel processes (``pool``, or new ones),
    grouped by name (each in seed order). The runs go seed by seed, every name in each, so that the progress a
    caller shows from ``on_each`` is a fair share of the whole: name by name, ten runs of a slow one left last
    (online CP-SAT, a minute each) took 8 of a bench's 10 minutes after its bar said a minute and a half was left."""
    results: dict[str, list[Any]] = {name: [] for name in names}
    jobs = [(scenario, name, seed) for seed in range(seeds) for name in names]
    with contextlib.ExitStack() as stack:
        if pool is None:
            pool = stack.enter_context(bench_pool(workers))
        try:
            for (_, name, _), r in zip(jobs, pool.map(one, jobs)):
                results[name].append(r)
                if on_each:
                    on_each(r)
        except KeyboardInterrupt as stop:  # the seeds every name finished are kept for the table
            finished = min(len(v) for v in results.values())
            keep_done(stop, {name: v[:finished] for name, v in results.items()} if finished else None)
            raise
    return results


def bench(scenario: str | Path | Scenario, planners: list[str], seeds: int, workers: int = 2,
          on_trial: Callable[[Trial], None] | None = None) -> dict[str, list[Trial]]:
    """Each planner over ``seeds`` seeds of the scenario (a file, or one prepared with its overrides)."""
    return over_seeds(_trial, prepare(scenario), planners, seeds, workers, on_trial)


def quartiles(values: list[float]) -> tuple[float, float, float]:
    if len(values) == 1:
        return values[0], values[0], values[0]
    q = statistics.quantiles(values, n=4, method="inclusive")
    return q[0], statistics.median(values), q[2]


def rows(results: dict[str, list[Trial]], baseline: str = "random") -> list[list[str]]:
    """One row per planner: experiments and lab-hours to target (median [IQR]), success, acceleration."""
    base = results.get(baseline)
    # where experiments cost money (and DFT calculations do not), acceleration is measured in cost
    by_cost = bool(base) and statistics.median(t.cost for t in base) > 0
    measure = (lambda t: t.cost) if by_cost else (lambda t: t.experiments)
    base_median = statistics.median(measure(t) for t in base) if base else math.nan
    out = []
    for planner, trials in results.items():
        e = quartiles([t.experiments for t in trials])
        h = quartiles([t.lab_hours for t in trials])
        success = sum(t.reached for t in trials) / len(trials)
        censored = "≥" if success < 0.5 else ""
        mine = statistics.median(measure(t) for t in trials)
        accel = base_median / mine if mine else math.nan
        base_censored = bool(base) and sum(t.reached for t in base) / len(base) < 0.5
        if planner == baseline:
            speedup = "1.0×"
        elif math.isnan(accel) or (censored and base_censored):
            speedup = "—"  # no baseline row, no experiment to divide by, or two lower bounds: nothing to say
        else:  # the baseline's count a lower bound: so is the ratio; this planner's: the ratio an upper one
            speedup = f"{'≥' if base_censored else '≤' if censored else ''}{accel:.1f}×"
        out.append([label(planner), f"{censored}{e[1]:.0f} [{e[0]:.0f}–{e[2]:.0f}]", f"{censored}{h[1]:.1f} [{h[0]:.1f}–{h[2]:.1f}]",
                    f"{statistics.mean(t.experiments_run for t in trials):.0f}",
                    f"{statistics.median(t.cost for t in trials):,.0f}", f"{100 * success:.0f} %",
                    speedup + (" (cost)" if by_cost and speedup != "—" else "")])
    return out


def label(planner: str) -> str:
    """``rl:agents/policies/quantum_dots.zip@rl:P.zip~seq`` → ``rl:quantum_dots@rl:P~seq``."""
    name, scheduler, variant = parse(planner)
    return short(name) + (f"@{short(scheduler)}" if scheduler else "") + (f"~{variant}" if variant else "")


def short(spec: str) -> str:
    """``rl:agents/policies/quantum_dots.zip`` → ``rl:quantum_dots``."""
    kind, sep, policy = spec.partition(":")
    return f"{kind}:{Path(policy).stem}" if sep and policy.endswith(".zip") else spec


HEADER = ["planner", "exp. to target", "lab-h to target", "exp. run", "cost", "reached", "accel."]


def caption(costs: bool = True) -> str:
    """What the columns mean; ``costs``: whether the table has a cost column (something in the lab costs)."""
    cost = ("cost: at the last target (median)" if costs else
            "no device costs anything (devices.*.cost, cost_per_hour), so no cost column")
    return ("medians [IQR]; ≥: censored by the budget (reached in under half the runs, where the budget or the run's "
            "end is counted; a run ended early, at the budget and campaign.max_lab_hours); exp. run: experiments run "
            f"in all (mean); {cost}; reached: runs that met every target; accel.: random's median experiments (cost, "
            "where experiments cost) ÷ this planner's (≥ or ≤ where one side is censored; — where both are)")
