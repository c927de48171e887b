"""A live (scaled-clock) campaign SIGKILLed mid-step is resumed from its journal: nothing lost, nothing twice."""

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from twin.campaign.journal import read_events, read_run

ROOT = Path(__file__).resolve().parents[2]
TWIN = [sys.executable, "-m", "twin"]


def _count(db, sql):
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as c:
            return c.execute(sql).fetchone()[0]
    except sqlite3.Error:
        return 0


@pytest.mark.process
def test_a_killed_live_campaign_resumes_where_it_was(tmp_path):
    lab = qd_lab(**{"campaign.budget": 8, "clock": {"mode": "scaled", "speed": 600},
                    "devices.spectrometer.duration": {"mean_s": 120, "cv": 0.0}})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(lab))
    db = tmp_path / "j.db"
    proc = subprocess.Popen(TWIN + ["run", str(path), "--journal", str(db), "--quiet"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    in_lab = "SELECT COUNT(*) FROM events WHERE kind='attempt.running' AND task LIKE '%s1'"
    while proc.poll() is None and time.monotonic() < deadline:  # kill it with a measurement in the lab
        if _count(db, "SELECT COUNT(*) FROM events WHERE kind='experiment.done'") >= 2 and \
                _count(db, in_lab) > _count(db, "SELECT COUNT(*) FROM events WHERE kind='attempt.done' AND task LIKE '%s1'"):
            break
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert "summary" not in read_run(db), "the campaign finished before it could be killed"
    before = read_events(db)
    done_before = {e["experiment"] for e in before if e["kind"] == "experiment.done"}

    resumed = subprocess.run(TWIN + ["resume", str(db), "--json"], cwd=ROOT, capture_output=True, text=True,
                             timeout=120)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    summary = json.loads(resumed.stdout)
    events = read_events(db)
    assert any(e["kind"] == "campaign.resumed" for e in events)
    finals = [e["experiment"] for e in events if e["kind"] in ("experiment.done", "experiment.abandoned")]
    assert len(finals) == len(set(finals)), "an experiment finished twice"
    assert done_before <= set(finals)
    assert summary["proposed"] == 8 and summary["done"] + summary["abandoned"] + summary["pending"] == 8
    assert summary["done"] == 8, summary["abandoned_reasons"]
    # the measurement that was in the lab when the process died was taken up again after the resume
    resumed_at = next(e["t_lab"] for e in events if e["kind"] == "campaign.resumed")
    lost = [e for e in events if e["kind"] == "attempt.failed" and e["t_lab"] >= resumed_at
            and "when the campaign resumed" in (e["detail"] or "")]
    assert lost, "the in-process device died with the campaign: its step must be found lost and retried"
    assert all(any(x["kind"] == "attempt.done" and x["task"] == e["task"] for x in events) for e in lost)
