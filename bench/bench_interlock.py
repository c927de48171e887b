"""An interlocked device (issue [3 of 7]): refusals are not faults, and GP-BO learns where devices refuse.

    python bench/bench_interlock.py

Quantum dots, 30 experiments, seed 2, a measuring device that refuses samples made above 270 °C while the
planner's box goes to 320 °C: by its driver (`twin.Refused`), or by the scenario's safe `envelope`.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.twin.test_refusals import HOT_C, interlock_lab  # noqa: E402
from twin.campaign.journal_read import read_events  # noqa: E402
from twin.runtime.lab import run  # noqa: E402
from bench.tables import table  # noqa: E402


def main() -> None:
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for how in ("driver raises Refused", "scenario envelope", "none"):
            for planner in ("gp-bo", "random"):
                changes: dict = {"campaign.planner": planner}
                if how.startswith("driver"):
                    changes["devices.spectrometer.driver"] = "tests.twin.test_refusals:Interlocked"
                elif how.startswith("scenario"):
                    changes["devices.spectrometer.envelope"] = {"temperature_c": {"low": 200, "high": HOT_C}}
                db = Path(d) / f"{how[:6]}-{planner}.db"
                s = run(interlock_lab(**changes), journal=db)
                proposed = [json.loads(e["detail"]) for e in read_events(db, "experiment.proposed")]
                last = proposed[-10:]
                met = s.targets_met_h.get("G")
                rows.append([how, planner, s.done, s.infeasible, s.retried, s.quarantines, s.failed_attempts,
                             f"{sum(p['temperature_c'] <= HOT_C for p in last)}/{len(last)}",
                             f"{met:.2f} lab-h" if met is not None else "—"])
    table("An interlock at 270 °C inside a box to 320 °C (quantum dots, 30 experiments, seed 2)",
          ["interlock", "planner", "done", "infeasible", "retries", "quarantines", "failed attempts",
           "last 10 feasible", "target met"], rows)

if __name__ == "__main__":
    main()
