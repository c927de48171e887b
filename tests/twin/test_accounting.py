"""Nothing vanishes: over many seeds of the flaky lab every experiment is accounted for."""

import json
import sqlite3
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from twin.runtime.lab import run

ROOT = Path(__file__).resolve().parents[2]


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(min_value=0, max_value=10**6), budget=st.integers(min_value=1, max_value=20))
def test_every_experiment_is_done_abandoned_with_reason_or_pending(tmp_path, seed, budget):
    db = tmp_path / f"{seed}-{budget}.db"
    summary = run(ROOT / "scenarios" / "flaky_lab.yaml", journal=db, seed=seed, bus="memory",
                  overrides={"campaign.budget": budget})  # run() itself checks the invariant
    with sqlite3.connect(db) as c:
        rows = c.execute("SELECT id, status, reason FROM experiments").fetchall()
        finals = c.execute(
            "SELECT experiment, COUNT(*) FROM events WHERE kind IN ('experiment.done', 'experiment.abandoned') "
            "GROUP BY experiment").fetchall()
        stored = json.loads(c.execute("SELECT value FROM run WHERE key='summary'").fetchone()[0])
    assert len(rows) == summary.proposed == budget
    for _id, status, reason in rows:
        assert status in ("done", "abandoned", "pending")
        if status == "abandoned":
            assert reason
    assert all(n == 1 for _, n in finals), "an experiment finished twice"
    assert summary.done + summary.abandoned + summary.pending == summary.proposed
    assert stored["done"] == summary.done


def test_an_interrupted_campaign_leaves_the_rest_pending(tmp_path):
    summary = run(ROOT / "scenarios" / "flaky_lab.yaml", journal=tmp_path / "j.db", bus="memory",
                  overrides={"campaign.max_lab_hours": 5, "campaign.budget": 40})
    assert summary.stopped == "max_lab_hours reached"
    assert summary.pending > 0
    assert summary.done + summary.abandoned + summary.pending == summary.proposed
