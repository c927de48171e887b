"""A bench's decision times, on this tree against an older revision: what one thread for each numerical library
in the workers of `twin bench` and `twin whatif` changes (twin/tools/pool.py, ``_one_thread_each``).

    python bench/bench_pool_threads.py 4275ee7            # the revision before it (~1 min)
    python bench/bench_pool_threads.py 4275ee7 --runs 3 --seeds 12

Each tree runs ``twin bench schedulers scenarios/catalyst.yaml --schedulers fifo,rl:<flaky policy> --json``
(GP-BO proposes, with scikit-learn and scipy's BLAS, in the same workers as the decisions), the trees taking
turns ``--runs`` times. The table gives, per tree and scheduler, the median of the runs' 99th-percentile decision
times and the worst of them (wall ms, as the bench measures each decision in its worker), the bench's own wall
seconds, and each against the revision's.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tables import table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
POLICY = ROOT / "agents" / "policies" / "flaky_scheduler.zip"


def bench(tree: Path, seeds: int) -> tuple[dict[str, list[float]], float]:
    """Each scheduler's runs' p99 decision times (ms), and the bench's wall seconds, with ``tree``'s code."""
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "twin", "bench", "schedulers", str(ROOT / "scenarios" /
                           "catalyst.yaml"), "--seeds", str(seeds), "--schedulers", f"fifo,rl:{POLICY}", "--json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=900,
                          env={**os.environ, "PYTHONPATH": str(tree)})
    took = time.perf_counter() - t0
    if done.returncode != 0:
        sys.exit(f"{tree}: the bench failed: {done.stderr[-800:]}")
    p99: dict[str, list[float]] = {}
    for run in json.loads(done.stdout)["runs"]:
        p99.setdefault(run["scheduler"].split("/")[-1], []).append(run["decision_p99_ms"])
    return p99, took


def main() -> None:
    rev = next((a for a in sys.argv[1:] if not a.startswith("--") and not a.isdigit()), "4275ee7")
    runs = int(sys.argv[sys.argv.index("--runs") + 1]) if "--runs" in sys.argv else 2
    seeds = int(sys.argv[sys.argv.index("--seeds") + 1]) if "--seeds" in sys.argv else 8
    with tempfile.TemporaryDirectory() as d:
        old = Path(d) / "old"
        subprocess.run(["git", "worktree", "add", "-q", "--detach", str(old), rev], cwd=ROOT, check=True)
        try:
            trees = {rev: old, "this tree": ROOT}
            p99: dict[str, dict[str, list[float]]] = {name: {} for name in trees}
            wall: dict[str, list[float]] = {name: [] for name in trees}
            for _ in range(runs):
                for name, tree in trees.items():
                    got, took = bench(tree, seeds)
                    for scheduler, values in got.items():
                        p99[name].setdefault(scheduler, []).extend(values)
                    wall[name].append(took)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, check=True)
    rows = []
    for name in trees:
        for scheduler, values in p99[name].items():
            base = statistics.median(p99[rev][scheduler])
            rows.append([name, scheduler, f"{statistics.median(values):.2f}", f"{max(values):.2f}",
                         f"{statistics.median(values) / base:.2f}", f"{statistics.median(wall[name]):.1f}",
                         f"{statistics.median(wall[name]) / statistics.median(wall[rev]):.2f}"])
    table(f"`twin bench schedulers` catalyst, {seeds} seeds, {runs} benches each, {rev} and this tree in turn: "
          "each run's p99 decision time (wall ms)", ["tree", "scheduler", "p99 median", "p99 worst", f"÷ {rev}",
                                                     "bench s", f"÷ {rev}"], rows)


if __name__ == "__main__":
    main()
