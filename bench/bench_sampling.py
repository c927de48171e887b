"""How far a policy's sampled rollouts get past its greedy one, by temperature (issue [4 of 7]).

    python bench/bench_sampling.py agents/policies/jobshop_scheduler.zip [--temperatures 1,0.5,0.25]
        [--shops 8] [--samples 16]

Random job shops of the sizes the scenario trains on (seeds no training draws) are each rolled out ``--samples``
times in lockstep (``agents.imitation.sampled_runs``): the greedy run and the others sampled from the policy's
scores ÷ the temperature. The table gives, per temperature, the best run's makespan ÷ the greedy run's (mean and
worst shop) and the sampled runs' mean ÷ greedy. Self-labelling (``training.teacher: self``) learns from the best
run, so the first column is how much one of its rounds can teach.
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

from agents.train_scheduler import initial_state  # noqa: E402
from agents.imitation import _scorer, sampled_runs  # noqa: E402
from bench.tables import table  # noqa: E402
from agents.candidates import trained_encoding  # noqa: E402
from twin import jobshop_as_lab, prepare, random_jobshop, read_meta  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("policy", type=Path)
    ap.add_argument("--scenario", type=Path, default=ROOT / "scenarios" / "jobshop.yaml")
    ap.add_argument("--temperatures", default="1,0.5,0.25")
    ap.add_argument("--shops", type=int, default=8)
    ap.add_argument("--samples", type=int, default=16)
    args = ap.parse_args()
    torch.set_num_threads(1)
    s = prepare(args.scenario)
    state = initial_state(args.policy, s, "candidates", part="action_net")
    encoding = trained_encoding(read_meta(args.policy).get("signature", {}).get("encoding"))  # as it decides
    sizes = s.training.jobshop_sizes or [[10, 10]]
    low, high = (int(x) for x in (s.training.operation_s or (1, 99)))
    shops = []
    for k in range(args.shops):
        rng = random.Random(f"bench-sampling:{k}")
        jobs, machines = sizes[k % len(sizes)]
        shops.append(prepare(jobshop_as_lab(s, random_jobshop(jobs, machines, low, high, rng)), seed=0))
    rows = []
    for temperature in (float(x) for x in args.temperatures.split(",")):
        best, sampled, t0 = [], [], time.perf_counter()
        for k, lab in enumerate(shops):
            spans = [summary.lab_hours for _, summary in
                     sampled_runs(lab, _scorer(state, k), args.samples, temperatures=(temperature,),
                                  encoding=encoding)]
            best.append(min(spans) / spans[0])
            sampled.append(statistics.mean(spans[1:]) / spans[0])
        rows.append([f"{temperature:g}", f"{statistics.mean(best):.3f}", f"{max(best):.3f}",
                     f"{statistics.mean(sampled):.3f}", f"{time.perf_counter() - t0:.1f}"])
    table(f"{args.policy.name}: {args.shops} random shops ({', '.join(f'{j}×{m}' for j, m in sizes)}), "
          f"{args.samples} runs each", ["temperature", "best ÷ greedy", "worst shop", "sampled ÷ greedy", "wall s"],
          rows)


if __name__ == "__main__":
    main()
