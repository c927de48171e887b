"""`twin bench schedulers --shapes`: schedulers on a family of variants of one lab, with paired seeds.

The family: the lab as written; for each device type, twice its instances, a bottleneck (its steps' mean duration,
``duration.mean_s``, made at least twice as long, and long enough that the stage takes a quarter more lab time per
experiment than any other: ``bottleneck``) and a flaky stage (a fifth of its steps fail; not for people,
``driver: operator``); and, when samples degrade, samples that keep a quarter as long; with ``random_labs``, that
many whole other labs drawn as ``training.random_labs`` draws them (on seeds no training run draws:
``twin.scenario.random_labs.held_out``). Every scheduler runs the same seeds on every variant; each one is compared
with the variant's best rule (the rule with the lowest mean makespan there — or, with ``by="objective"``, the lowest
objective as the scenario's ``training.weights`` weigh makespan, degraded samples and abandoned experiments) seed by
seed, as a mean difference with a 95 % confidence interval — so "better" and "worse" mean outside the noise, not a
lucky seed.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass

from twin.campaign.human import DRIVER as HUMAN
from twin.core.errors import TwinError
from twin.runtime.lab import prepare
from twin.scenario import Scenario
from twin.scenario.bottleneck import bottleneck
from twin.scenario.objective import time_scale, weighted_objective
from twin.scenario.random_labs import held_out
from twin.tools.planner_bench import bench_pool
from twin.tools.pool import keep_done
from twin.tools.scheduler_bench import RULES, Run, bench

#: two-sided 95 % quantiles of Student's t for n − 1 degrees of freedom (n paired seeds), then the normal's
_T95 = {1: 12.71, 2: 4.30, 3: 3.18, 4: 2.78, 5: 2.57, 6: 2.45, 7: 2.36, 8: 2.31, 9: 2.26, 10: 2.23, 15: 2.13,
        20: 2.09, 30: 2.04}


def _t95(dof: int) -> float:
    return next((v for k, v in sorted(_T95.items()) if dof <= k), 1.96)


def variants(s: Scenario, random_labs: int = 0) -> list[tuple[str, Scenario]]:
    out = [("as written", s)]
    for name, d in s.devices.items():
        out.append((f"{name} ×2 instances", prepare(s, overrides={f"devices.{name}.instances": d.instances * 2})))
        factor = bottleneck(s, name)
        if factor:
            out.append((f"{name} bottleneck (mean_s ×{factor:g})",
                        prepare(s, overrides={f"devices.{name}.duration.mean_s": d.duration.mean_s * factor})))
        if d.driver != HUMAN:  # people are not simulated to fail
            out.append((f"{name} flaky (20 % fail)",
                        prepare(s, overrides={f"devices.{name}.faults.fail_p": max(d.faults.fail_p, 0.2)})))
    if s.chemistry.stability_s:
        out.append(("samples keep ¼ as long", prepare(s, overrides={"chemistry.stability_s": s.chemistry.stability_s / 4})))
    if random_labs:
        out += [(name, prepare(lab)) for name, lab in held_out(s, random_labs)]
    return out


@dataclass
class Comparison:
    shape: str
    best_rule: str
    best_mean_s: float
    diffs: dict[str, tuple[float, float]]  # scheduler -> (mean difference to the best rule, 95 % half-width), s
    runs: dict[str, list[Run]]  # scheduler -> its runs of this shape, one per seed


#: What ``--by`` compares schedulers on.
MEASURES = ("makespan", "objective")


def measure(lab: Scenario, by: str) -> Callable[[Run], float]:
    """A run's makespan, or its objective as ``training.weights`` weighs it (``twin.weighted_objective``) in lab-second
    equivalents: makespan + (``degraded`` × degraded samples + ``abandoned`` × abandoned experiments) typical steps
    ÷ ``time``."""
    if by not in MEASURES:
        raise TwinError(f"--by {by!r}: use one of {', '.join(MEASURES)}")
    if by == "makespan":
        return lambda r: r.makespan_s
    w = lab.training.weights
    if w.time <= 0:
        raise TwinError(f"{lab.name}: --by objective counts lab time in training.weights.time, which is {w.time}: "
                        "give it a positive weight, or compare --by makespan")
    unit = time_scale(lab)
    return lambda r: weighted_objective(lab, r.makespan_s, r.degraded, r.lost, unit) * unit / w.time


def compare(results: dict[str, list[Run]], shape: str, value: Callable[[Run], float] = lambda r: r.makespan_s
            ) -> Comparison:
    """Each scheduler against the shape's best rule by ``value`` (lab seconds, or their equivalent)."""
    means = {k: statistics.mean(value(r) for r in v) for k, v in results.items()}
    rules = [k for k in results if k in RULES] or list(results)
    best = min(rules, key=means.get)
    ref = {r.seed: value(r) for r in results[best]}
    diffs = {}
    for name, runs in results.items():
        d = [value(r) - ref[r.seed] for r in runs]
        half = _t95(len(d) - 1) * statistics.stdev(d) / math.sqrt(len(d)) if len(d) > 1 else float("inf")
        diffs[name] = (statistics.mean(d), half)
    return Comparison(shape, best, means[best], diffs, results)


def shapes(s: Scenario, schedulers: list[str], seeds: int, workers: int = 2,
           on_shape: Callable[[Comparison], None] | None = None, random_labs: int = 0,
           by: str = "makespan") -> list[Comparison]:
    out = []
    measure(s, by)  # an unknown measure, or one the lab cannot give, is refused before any run
    with bench_pool(workers) as pool:
        try:
            for shape, variant in variants(s, random_labs):
                out.append(compare(bench(variant, schedulers, seeds, workers, pool=pool), shape, measure(variant, by)))
                if on_shape is not None:
                    on_shape(out[-1])
        except KeyboardInterrupt as stop:  # the shapes finished are kept for the table
            keep_done(stop, out)
            raise
    return out


def verdict(diff: float, half: float) -> str:
    if diff + half < 0:
        return "better"
    if diff - half > 0:
        return "worse"
    return "same"
