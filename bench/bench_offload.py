"""Decisions off the loop (issue [3 of 7]): on the loop, in a worker thread, or in a worker process?

    python bench/bench_offload.py [--calls 5]

Three decisions a lab makes: an online CP-SAT schedule (ft10, 0.3 s limit; OR-Tools releases the GIL), a GP-BO
proposal after 60 experiments (scikit-learn: numpy, and Python in the optimiser), and a pure-Python decision
(a rule over a large view, holding the GIL). Each is run `--calls` times while the event loop runs a 1 ms
ticker, as it would serve devices; the table gives the ticker's lateness (how long the loop could not serve a
device: at 3600× a 100 ms stall is 360 lab-s) and each call's wall time.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures as cf
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.tables import table  # noqa: E402


def cpsat_decision() -> float:
    from agents.cpsat import jobshop
    from twin.scenario.jobshop import read

    inst = read(ROOT.parent / "shared" / "data" / "jobshop" / "ft10.txt")
    return float(jobshop(inst.jobs, inst.machines, time_limit_s=0.3).makespan)


_GP = {}


def gp_decision() -> float:
    import numpy as np

    from agents.gp_bo import GpBoPlanner
    from twin import Outcome
    from twin.scenario import parse
    from tests.conftest import qd_lab

    if "s" not in _GP:
        _GP["s"] = parse(qd_lab())
    s = _GP["s"]
    rng = np.random.default_rng(0)
    box = {k: (v.low, v.high) for k, v in s.chemistry.parameters.items()}
    history = []
    for _ in range(60):
        p = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in box.items()}
        history.append(Outcome(p, {"peak_nm": 500 + p["temperature_c"] / 3 + rng.normal()}, 1.0))
    planner = GpBoPlanner(s.chemistry.parameters, 0, s.chemistry.targets, refit_every=1)
    return float(len(planner.propose(2, history, [])))


def python_decision() -> float:
    total = 0
    for i in range(1_500_000):  # a rule scoring a large view, in Python
        total += (i * 7919) % 13
    return float(total)


WORKLOADS = {"CP-SAT schedule (ft10, 0.3 s)": cpsat_decision, "GP-BO proposal (60 points)": gp_decision,
             "pure-Python decision": python_decision}


async def _measure(fn, where: str, calls: int, pool) -> tuple[list[float], list[float]]:
    loop = asyncio.get_running_loop()
    lags: list[float] = []
    stop = False

    async def ticker() -> None:
        while not stop:
            t = time.perf_counter()
            await asyncio.sleep(0.001)
            lags.append(max(0.0, time.perf_counter() - t - 0.001))

    tick = asyncio.ensure_future(ticker())
    await asyncio.sleep(0.05)
    durations = []
    for _ in range(calls):
        t0 = time.perf_counter()
        if where == "on the loop":
            fn()
        else:
            await loop.run_in_executor(pool, fn)
        durations.append(time.perf_counter() - t0)
        await asyncio.sleep(0.01)
    stop = True
    await tick
    return lags, durations


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--calls", type=int, default=5)
    args = ap.parse_args()
    rows = []
    thread = cf.ThreadPoolExecutor(1)
    process = cf.ProcessPoolExecutor(1)
    for fn in WORKLOADS.values():  # warm both workers (imports, the process's start)
        thread.submit(fn).result()
        process.submit(fn).result()
    for name, fn in WORKLOADS.items():
        base = None
        for where, pool in (("on the loop", None), ("worker thread", thread), ("worker process", process)):
            lags, durations = asyncio.run(_measure(fn, where, args.calls, pool))
            worst = max(lags) * 1000
            base = base or worst
            rows.append([name, where, f"{statistics.median(lags) * 1000:.2f}",
                         f"{sorted(lags)[int(0.99 * (len(lags) - 1))] * 1000:.1f}", f"{worst:.1f}",
                         f"{worst / base:.3f}×", f"{statistics.median(durations) * 1000:.0f}"])
    thread.shutdown()
    process.shutdown()
    table(f"Loop lateness while deciding ({args.calls} calls each; wall ms; 2 cores)",
          ["decision", "where", "lag p50", "lag p99", "lag max", "max vs on loop", "call ms"], rows)


if __name__ == "__main__":
    main()
