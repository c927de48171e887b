"""Route search methods on held-out targets with a known route (issue [5 of 7]).

    python bench/bench_routes.py [--targets 100] [--seconds 10] [--prior agents/policies/route_prior]

Targets are made forwards from the stock (``agents.routes.targets``, depths 1–6 in turn, seeds no training
draws), so a route of known length exists. Each method searches each target with a budget of ``--seconds``;
the table gives the share solved, the share whose route is no longer than the known one + 1, expansions (one
molecule: every template backwards) and wall time. Targets run in parallel (``--workers``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.tables import table  # noqa: E402

METHODS = ("breadth-first", "mcts (uniform)", "mcts (learned prior)", "random")


def _one(args: tuple) -> tuple[str, int, bool, int | None, int, float]:
    import torch

    from agents.routes import stock as stock_file
    from agents.routes import templates as template_file
    from agents.routes.mcts import mcts, random_search
    from agents.routes.policy import load_prior
    from agents.routes.search import breadth_first

    torch.set_num_threads(1)
    method, smiles, known, seconds, prior_path = args
    templates, stock = template_file.load(), stock_file.load()
    if method == "breadth-first":
        result = breadth_first(smiles, templates, stock, max_seconds=seconds)
    elif method == "random":
        result = random_search(smiles, templates, stock, max_seconds=seconds)
    elif method == "mcts (uniform)":
        result = mcts(smiles, templates, stock, max_seconds=seconds)
    else:
        result = mcts(smiles, templates, stock, prior=load_prior(Path(prior_path), templates), max_seconds=seconds)
    steps = result.route.steps if result.route else None
    return method, known, result.route is not None, steps, result.expansions, result.seconds


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--targets", type=int, default=100)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--prior", default=str(ROOT / "agents" / "policies" / "route_prior"))
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    from agents.routes import stock as stock_file
    from agents.routes import templates as template_file
    from agents.routes.targets import target_set

    targets = target_set(template_file.load(), stock_file.load(), args.targets, held_out=True)
    jobs = [(m, t.smiles, t.steps, args.seconds, args.prior) for m in METHODS for t in targets]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(_one, jobs, chunksize=4))
    rows = []
    for m in METHODS:
        mine = [r for r in results if r[0] == m]
        solved = [r for r in mine if r[2]]
        rows.append([m, f"{100 * len(solved) / len(mine):.0f}",
                     f"{100 * sum(r[3] <= r[1] + 1 for r in solved) / max(len(solved), 1):.0f}",
                     f"{statistics.mean(r[4] for r in mine):.1f}", f"{statistics.median(r[4] for r in mine):.0f}",
                     f"{statistics.median(r[5] for r in mine):.2f}", f"{max(r[5] for r in mine):.1f}"])
    table(f"{len(targets)} held-out targets (depths 1–6), {args.seconds:g} s each; {time.perf_counter() - t0:.0f} s",
          ["method", "solved %", "≤ known+1 %", "expansions", "median", "s median", "s max"], rows)


if __name__ == "__main__":
    main()
