"""Schedulers on job shops they never trained on (issue [4 of 7]): gap to the known optimum per size class.

    python bench/bench_jobshops.py [--schedulers fifo,spt,mwkr,rl:P.zip,...] [--random 3]

Every instance in ../shared/data/jobshop/ (34, with optima from the literature) runs once per scheduler as a
lab (one device per machine, deterministic, no faults) on the fast runtime; the gap is makespan / optimum − 1.
Then `--random` random shops each of 10×10, 15×15 and 20×15 (or `--sizes 30x20,50x20,...`; durations 1–99), as
makespan relative to MWKR's (and,
with `--plan-seconds S`, CP-SAT's offline plan of each in S seconds: how far below MWKR any schedule gets). The p99 of
each scheduler's decision time (wall ms) is measured over every decision it made. `--samples K` adds, for each
rl policy, the lab run with ``campaign.rollouts: K`` (the best of K runs played ahead in the twin — the greedy one and
K−1 sampled from the policy — followed): an improvement at decision time that only a deterministic lab allows,
reported apart from the greedy policy; `--search active` plays them with the policy tuned on each shop between
rounds (``campaign.rollout_search: active``). `--local-search N` adds, for each rl column, its plan shortened by N
tabu-search swaps (``campaign.local_search: N``), and the same search from MWKR's schedule: what the search does
with a rule's start instead of the policy's.
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agents.cpsat_scheduler import CpSatScheduler  # noqa: E402
from agents.order_search import improve, shop_of  # noqa: E402
from agents.judging import campaign  # noqa: E402
from bench.tables import table  # noqa: E402
from twin import jobshop_as_lab, random_jobshop  # noqa: E402
from twin.runtime.lab import make_scheduler, prepare  # noqa: E402
from twin.tools.scheduler_bench import load_variant  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "jobshop"
OPTIMA = {"ft06": 55, "ft10": 930, "la01": 666, "la02": 655, "la03": 597, "la04": 590, "la05": 593,
          "la16": 945, "la17": 784, "la18": 848, "la19": 842, "la20": 902, "abz5": 1234, "abz6": 943,
          "orb01": 1059, "orb02": 888, "orb03": 1005, "orb04": 1005, "orb05": 887, "orb06": 1010, "orb07": 397,
          "orb08": 899, "orb09": 934, "orb10": 944, "la21": 1046, "la22": 927, "la23": 1032, "la24": 935,
          "la25": 977, "la36": 1268, "la37": 1397, "la38": 1196, "la39": 1233, "la40": 1222}
PUBLIC = ("ft06", "la01", "la02", "la03", "la04", "la05", "ft10")
SCENARIO = ROOT / "scenarios" / "jobshop.yaml"


def run(s, name: str, times: list[float], search: str = "sample") -> float:
    if name.startswith("ls-"):  # campaign.local_search: N swaps on the plan; on a rule's run, the same search
        n, _, name = name[len("ls-"):].partition(":")
        if name.startswith(("rl:", "best-of-")):
            s = prepare(s, overrides={"campaign.local_search": int(n)})
        else:
            return searched(s, name, int(n), times)
    if name.startswith("best-of-"):  # campaign.rollouts: K runs played ahead in the twin (before the campaign and
        k, _, name = name[len("best-of-"):].partition(":")  # its clock), the best one followed
        s = prepare(s, overrides={"campaign.rollouts": int(k), "campaign.rollout_search": search})
    return run_rule(s, make_scheduler(s, name).decide, times)


def searched(s, rule: str, swaps: int, times: list[float]) -> float:
    """The rule's run of the shop, its devices' orders then shortened as ``campaign.local_search`` shortens a
    plan's: how far the search goes from a rule's schedule (the lab-s of the orders found)."""
    orders: dict[str, list[str]] = {}

    def kept(view):
        out = scheduler(view)
        for a in out:
            orders.setdefault(a.device, []).append(a.task)
        return out

    scheduler = make_scheduler(s, rule).decide
    played = run_rule(s, kept, times)
    found = improve(shop_of(s), orders, swaps, s.campaign.seed)
    return min(played, found.length)


def run_rule(s, decide, times: list[float]) -> float:
    def timed(view):
        t0 = time.perf_counter()
        out = decide(view)
        times.append(time.perf_counter() - t0)
        return out

    return campaign(s, 0, timed).lab_hours * 3600


def instances(asked: str) -> list[str]:
    """The instances ``--instances`` names, checked against the ones with known optima."""
    if asked == "all":
        return sorted(OPTIMA)
    names = [] if asked == "none" else [n.strip() for n in asked.split(",") if n.strip()]
    unknown = [n for n in names if n not in OPTIMA]
    if unknown:
        raise SystemExit(f"--instances: {', '.join(unknown)} not among the instances with known optima "
                         f"({', '.join(sorted(OPTIMA))}); or give all, or none")
    return names


def gap_table(names: list[str], short: dict[str, str], gaps: dict[str, dict[str, float]],
              sizes: dict[str, str]) -> None:
    """Mean gap per group of the instances run: the public seven (if all were run), each size class, all."""
    ran = list(sizes)
    classes = sorted(set(sizes.values()), key=lambda c: [int(x) for x in c.split("×")])
    rows = [["public 7 (ft06, la01–05, ft10)",
             *[f"{100 * statistics.mean(gaps[n][i] for i in PUBLIC):.1f}" for n in names]]] \
        if set(PUBLIC) <= set(ran) else []
    for c in classes:
        members = [i for i in ran if sizes[i] == c]
        rows.append([f"{c} ({len(members)})", *[f"{100 * statistics.mean(gaps[n][i] for i in members):.1f}"
                                                 for n in names]])
    rows.append([f"all {len(ran)}", *[f"{100 * statistics.mean(gaps[n].values()):.1f}" for n in names]])
    table("Mean gap to the optimum, % (one run per instance; never trained on)", ["instances", *map(short.get, names)],
          rows)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--schedulers", default="fifo,spt,mwkr")
    ap.add_argument("--instances", default="all", help="which of the 34 instances to run: all, none, or names "
                                                         "(ft06,la01,...)")
    ap.add_argument("--random", type=int, default=3)
    ap.add_argument("--sizes", default="10x10,15x15,20x15", help="the random shops' sizes, jobs x machines (the "
                                                                "policies trained on 6x6 to 20x15)")
    ap.add_argument("--plan-seconds", type=float, default=0.0, help="also CP-SAT's offline plan of each random shop "
                                                                    "(this many seconds, one worker): what any "
                                                                    "schedule can reach there")
    ap.add_argument("--samples", type=int, default=0, help="also K rollouts of each rl policy, keeping the best "
                                                           "(deterministic shops only), as its own column")
    ap.add_argument("--search", choices=("sample", "active"), default="sample", help="how the K rollouts are played "
                                                                                     "(campaign.rollout_search)")
    ap.add_argument("--local-search", type=int, default=0, help="also N tabu-search swaps on each rl column's plan "
                                                                  "(campaign.local_search), and on MWKR's schedule, "
                                                                  "each as its own column")
    args = ap.parse_args()
    torch.set_num_threads(1)
    names = [n.strip() for n in args.schedulers.split(",") if n.strip()]
    if args.samples > 1:
        names += [f"best-of-{args.samples}:{n}" for n in names if n.startswith("rl:")]
    if args.local_search:
        names += [f"ls-{args.local_search}:{n}" for n in dict.fromkeys([*names, "mwkr"])
                  if n.startswith(("rl:", "best-of-")) or n == "mwkr"]
    short = {n: (Path(n.partition(":")[2]).stem if n.startswith("rl:") else n) for n in names}
    active = " (active)" if args.search == "active" else ""
    short.update({n: f"{Path(n.rpartition(':')[2]).stem} best of {args.samples}{active}" for n in names
                  if n.startswith("best-of-")})
    short.update({n: f"{short.get(n.partition(':')[2], 'mwkr')} + {args.local_search} swaps" for n in names
                  if n.startswith("ls-")})
    times: dict[str, list[float]] = {n: [] for n in names}
    gaps: dict[str, dict[str, float]] = {n: {} for n in names}
    sizes: dict[str, str] = {}
    for inst in instances(args.instances):
        s = load_variant(SCENARIO, str(DATA / f"{inst}.txt"))
        sizes[inst] = f"{len(s.campaign.planner_options['proposals'])}×{len(s.devices)}"
        for n in names:
            gaps[n][inst] = run(s, n, times[n], args.search) / OPTIMA[inst] - 1
        print(f"{inst:6} {sizes[inst]:6} " + "  ".join(f"{short[n]} {100 * gaps[n][inst]:5.1f}%" for n in names),
              file=sys.stderr, flush=True)
    if sizes:
        gap_table(names, short, gaps, sizes)
    base = load_variant(SCENARIO)
    rand_rows = []
    sizes_asked = [tuple(int(x) for x in size.split("x")) for size in args.sizes.split(",") if size.strip()]
    for jobs, machines in sizes_asked if args.random > 0 else ():
        ratios: dict[str, list[float]] = {n: [] for n in names}
        for k in range(args.random):
            s = jobshop_as_lab(base, random_jobshop(jobs, machines, 1, 99, random.Random(f"bench:{jobs}x{machines}:{k}")))
            spans = {n: run(s, n, times[n], args.search) for n in names}
            ref = spans["mwkr"] if "mwkr" in spans else run(s, "mwkr", [])  # the reference, asked for or not
            for n in names:
                ratios[n].append(spans[n] / ref)
            if args.plan_seconds:
                plan = CpSatScheduler.offline_bound(s, args.plan_seconds)
                ratios.setdefault("plan", []).append(plan / ref)
        rand_rows.append([f"{jobs}×{machines} ({args.random})", *[f"{statistics.mean(ratios[n]):.3f}" for n in names],
                          *([f"{statistics.mean(ratios['plan']):.3f}"] if args.plan_seconds else [])])
    if rand_rows and args.random:
        plan_header = [f"cp-sat plan ({args.plan_seconds:g} s)"] if args.plan_seconds else []
        table("Random shops: makespan relative to MWKR's (mean)", ["shops", *map(short.get, names), *plan_header],
              rand_rows)
    table("Decision time, wall ms", ["scheduler", "p50", "p99", "decisions"],
          [[short[n], f"{1000 * statistics.median(times[n]):.2f}",
            f"{1000 * sorted(times[n])[int(0.99 * (len(times[n]) - 1))]:.2f}", len(times[n])] for n in names])


if __name__ == "__main__":
    main()
