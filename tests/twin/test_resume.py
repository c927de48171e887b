"""A campaign killed at any point and resumed from its journal ends with the journal it would have had."""

import json
import multiprocessing
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.conftest import ctrl_c_at, twin_cli
from twin.campaign.journal import Journal
from twin.campaign.journal_read import read_run
from twin.runtime.lab import prepare, run
from twin.runtime.resume import ResumeError, resume

ROOT = Path(__file__).resolve().parents[2]
CAMPAIGNS = {"flaky_lab": {"campaign.budget": 30}, "quantum_dots": {"campaign.budget": 40}}


def tables(db):
    with sqlite3.connect(db) as c:
        return (c.execute("SELECT * FROM events ORDER BY seq").fetchall(),
                c.execute("SELECT * FROM experiments ORDER BY id").fetchall())


def scenario(name, seed):
    return prepare(ROOT / "scenarios" / f"{name}.yaml", seed=seed, bus="memory", overrides=CAMPAIGNS[name])


_unkilled: dict = {}


def unkilled(name, seed, tmp):
    if (name, seed) not in _unkilled:
        db = tmp / f"whole-{name}-{seed}.db"
        run(scenario(name, seed), journal=db)
        _unkilled[(name, seed)] = tables(db)
    return _unkilled[(name, seed)]


def _killed_at(s, db, row, flush_every):
    """In a child process: run the campaign and SIGKILL itself when the journal writes event ``row``."""
    Journal.FLUSH_EVERY = flush_every
    append = Journal._append

    def dying(self, *r):
        if self._seq + 1 == row:
            os.kill(os.getpid(), signal.SIGKILL)
        append(self, *r)

    Journal._append = dying
    run(s, journal=db)


@settings(max_examples=7, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(sorted(CAMPAIGNS)), seed=st.integers(0, 3), at=st.floats(0.0, 1.0),
       flush_every=st.integers(5, 400))
def test_killed_anywhere_and_resumed_the_journal_is_the_unkilled_one(tmp_path_factory, name, seed, at, flush_every):
    tmp = tmp_path_factory.mktemp("resume")
    whole = unkilled(name, seed, tmp_path_factory.getbasetemp())
    row = 1 + int(at * (len(whole[0]) - 1))
    db = tmp / "killed.db"
    child = multiprocessing.get_context("fork").Process(target=_killed_at, args=(scenario(name, seed), db, row,
                                                                                    flush_every))
    child.start()
    child.join(60)
    assert child.exitcode == -signal.SIGKILL
    assert "summary" not in read_run(db)
    summary = resume(db)
    assert tables(db) == whole
    assert summary.journal == str(db) and read_run(db)["summary"]["done"] == summary.done


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(sorted(CAMPAIGNS)), seed=st.integers(0, 3), at=st.floats(0.0, 0.95))
def test_stopped_by_ctrl_c_anywhere_and_resumed_the_journal_is_the_unstopped_one(tmp_path_factory, name, seed, at):
    tmp = tmp_path_factory.mktemp("stopped")
    whole = unkilled(name, seed, tmp_path_factory.getbasetemp())
    db = tmp / "stopped.db"
    with ctrl_c_at(1 + int(at * (len(whole[0]) - 1))):
        stopped = run(scenario(name, seed), journal=db)
    assert stopped.stopped == "interrupted (SIGINT)" and stopped.resumable
    assert tables(db) != whole
    summary = resume(db)
    assert tables(db) == whole
    assert not summary.stopped and read_run(db)["summary"]["done"] == summary.done


def test_a_campaign_that_stopped_itself_is_not_resumed(tmp_path):
    db = tmp_path / "j.db"
    summary = run(prepare(ROOT / "scenarios" / "flaky_lab.yaml", seed=0, bus="memory",
                          overrides={"campaign.max_lab_hours": 2}), journal=db)
    assert summary.stopped == "max_lab_hours reached" and not summary.resumable
    with pytest.raises(ResumeError, match=r"ended \(max_lab_hours reached\), not stopped from outside \(Ctrl-C, "
                                          r"SIGTERM, twin ctl stop\): resumed, it would end the same way"):
        resume(db)


def test_a_campaign_stopped_by_a_labtwin_that_did_not_say_where_the_stop_came_from_is_not_resumed(tmp_path):
    db = tmp_path / "j.db"
    with ctrl_c_at(40):
        run(scenario("flaky_lab", 1), journal=db)
    with sqlite3.connect(db) as c:  # as a journal of 2026-12-04 or before: no 'resumable' in its summary
        summary = json.loads(c.execute("SELECT value FROM run WHERE key='summary'").fetchone()[0])
        del summary["resumable"]
        c.execute("UPDATE run SET value=? WHERE key='summary'", (json.dumps(summary),))
    before = tables(db)
    with pytest.raises(ResumeError, match=r"stopped \(interrupted \(SIGINT\)\) by a labtwin older than the resume of "
                                          r"a stopped campaign.*run it again \(twin run\)"):
        resume(db)
    assert tables(db) == before


def test_a_resume_that_diverges_names_the_first_differing_event_and_keeps_the_journal(tmp_path):
    db = tmp_path / "j.db"
    run(scenario("flaky_lab", 1), journal=db)
    with sqlite3.connect(db) as c:  # as if killed, and recorded by code that behaved differently
        c.execute("DELETE FROM run WHERE key='summary'")
        c.execute("UPDATE events SET kind='device.lost' WHERE seq=40")
    before = tables(db)
    with pytest.raises(ResumeError, match=r"event 40 differs from the journal: it recorded 'device.lost'"):
        resume(db)
    assert tables(db) == before
    assert not (tmp_path / "j.db.resuming").exists()


def test_a_finished_run_is_not_resumed(tmp_path):
    db = tmp_path / "j.db"
    run(scenario("quantum_dots", 0), journal=db)
    with pytest.raises(ResumeError, match="finished; nothing to resume"):
        resume(db)


@pytest.mark.process
def test_twin_report_on_a_sigkilled_run_says_how_far_it_got_and_twin_resume_finishes_it(tmp_path):
    db = tmp_path / "j.db"
    args = ["run", "scenarios/flaky_lab.yaml", "--bus", "memory", "--journal", str(db), "--quiet",
            "--budget", "1000", "--seed", "2"]
    env = {**os.environ, "LABTWIN_FLUSH_EVERY": "50"}
    proc = subprocess.Popen([sys.executable, "-m", "twin", *args], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    while proc.poll() is None:  # kill it once something is on disk
        try:
            with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as c:
                if c.execute("SELECT COUNT(*) FROM events").fetchone()[0] > 200:
                    break
        except sqlite3.Error:
            pass
        time.sleep(0.01)  # a poll, not a wait for something: leave the CPU to the campaign
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL and "summary" not in read_run(db), "it finished before it was killed"
    report = twin_cli("report", str(db))
    assert report.exit_code == 0, report.output
    assert "interrupted" in report.output and f"twin resume {db}" in report.output.replace("\n", "")
    said = json.loads(twin_cli("report", str(db), "--json").stdout)  # for a script: `twin report` had no --json
    assert said["state"] == "interrupted" and said["resume_with"] == str(db) and said["so_far"]["events"] > 200
    several = tmp_path / "several"  # a directory of journals that is not a lab's: each resumes on its own
    several.mkdir()
    for suffix in ("", "-wal", "-shm"):
        if Path(f"{db}{suffix}").exists():
            shutil.copy(f"{db}{suffix}", f"{several / 'a.db'}{suffix}")
    told = " ".join(twin_cli("report", str(several), columns=300).output.split())
    assert f"Continue it with: twin resume {several / 'a.db'}" in told, told  # it named the directory
    resumed = twin_cli("resume", str(db), "--json", columns=80)
    assert resumed.exit_code == 0, resumed.output
    again = json.loads(twin_cli("report", str(db), "--json").stdout)
    assert again["state"] == "finished" and again["resume_with"] is None
    assert again["summary"] == json.loads(resumed.stdout)  # as `twin resume --json` (and `twin run --json`) print it
    fresh = tmp_path / "fresh.db"
    assert twin_cli(*args[:5] + [str(fresh)] + args[6:], columns=80).exit_code == 0
    assert tables(db) == tables(fresh)
