"""What replaying a lab's planner saves the scheduler's teacher: labelled states per second of `twin train`'s
best-rule work on a lab (each rule run on it to find the teacher, then the teacher's rollout), its planner run in
every run (baseline) or once per lab and replayed (`agents/planned_labs.py`, as `twin train` does).

    python bench/bench_planned_labs.py [--labs N]     # about 2 minutes with 8 labs

One process, one torch thread; the two ways alternate lab by lab, on the same labs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.tables import table  # noqa: E402
import agents.imitation as imitation  # noqa: E402
import agents.planned_labs as planned_labs  # noqa: E402
import agents.train_scheduler as train_scheduler  # noqa: E402
from agents.candidates import ENCODING  # noqa: E402
from twin.runtime.lab import prepare  # noqa: E402

LABS = {  # GP-BO plans both; flaky_lab's own planner is random
    "quantum_dots": (ROOT / "scenarios" / "quantum_dots.yaml", {}),
    "flaky_lab, GP-BO": (ROOT / "scenarios" / "flaky_lab.yaml", {"campaign.planner": "gp-bo"}),
}


def one_lab(base, seed: int, replay: bool) -> tuple[int, float]:
    """The teacher's work on lab ``seed``: labelled states, wall seconds."""
    real = planned_labs.planned
    way = real if replay else (lambda lab: lab)
    imitation.planned = train_scheduler.planned = way
    planned_labs._PLANNED.clear()  # each lab is new to the trainer's worker
    try:
        t = time.perf_counter()
        samples, _ = imitation.lab_task((base, seed, ("teacher",), None, 1.0, ENCODING))
        return len(samples), time.perf_counter() - t
    finally:
        imitation.planned = train_scheduler.planned = real


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--labs", type=int, default=8)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for name, (path, changes) in LABS.items():
        base = prepare(path, overrides=changes or None)
        done = {False: [0, 0.0], True: [0, 0.0]}
        for seed in range(args.labs):
            for replay in ((False, True) if seed % 2 == 0 else (True, False)):
                n, s = one_lab(base, seed, replay)
                done[replay][0] += n
                done[replay][1] += s
        live = done[False][0] / done[False][1]
        for replay in (False, True):
            n, s = done[replay]
            rows.append([name, "replayed (twin train)" if replay else "planner in every run (baseline)",
                         f"{n:,}", f"{s:.1f}", f"{n / s:,.0f}", f"{n / s / live:.2f}"])
    table(f"the best-rule teacher's labelled states per second, {args.labs} labs each, 1 thread",
          ["lab", "planner", "states", "wall s", "states/s", "÷ baseline"], rows)


if __name__ == "__main__":
    main()
