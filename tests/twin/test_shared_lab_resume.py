"""A lab of several campaigns killed and resumed: in virtual time, on a live clock, served."""

import json
import sqlite3
from pathlib import Path

import pytest

from twin.runtime.lab import prepare
from twin.runtime.shared_run import run_shared

from twin.campaign.journal_read import read_run
from tests.twin.shared_labs import (LAB, ROOT, SMALL, assert_one_step_at_a_time, journal_tables, kill_all, wait_until_ended)
from tests.conftest import assert_adopted_once, ctrl_c_at, twin_cli


def _lab_killed_at(s, where: Path, row: int) -> None:
    """In a child process: run the lab and SIGKILL itself when its campaigns have written ``row`` events."""
    import os
    import signal

    from twin.campaign.journal import Journal

    written = [0]
    append = Journal._append

    def dying(self, *r):
        written[0] += 1
        if written[0] == row:
            os.kill(os.getpid(), signal.SIGKILL)
        append(self, *r)

    Journal._append = dying
    run_shared(s, where, handle_signals=False)


@pytest.mark.parametrize("at", [0.1, 0.5, 0.9])
def test_a_lab_killed_anywhere_and_resumed_ends_with_the_journals_of_the_unkilled_one(tmp_path, at):
    import multiprocessing
    import signal

    from twin.runtime.resume_lab import resume_lab

    s = prepare(LAB, seed=3, overrides=SMALL)
    run_shared(s, tmp_path / "whole", handle_signals=False)
    whole = journal_tables(tmp_path / "whole")
    row = max(1, int(at * sum(len(t[0]) for t in whole.values())))
    child = multiprocessing.get_context("fork").Process(target=_lab_killed_at, args=(s, tmp_path / "killed", row))
    child.start()
    child.join(60)
    assert child.exitcode == -signal.SIGKILL
    assert any("summary" not in read_run(db) for db in (tmp_path / "killed").glob("*.db"))
    told = twin_cli("report", str(tmp_path / "killed"), columns=300)
    assert told.exit_code == 0 and f"Continue it with: twin resume {tmp_path / 'killed'}" in told.output
    out = resume_lab(tmp_path / "killed", handle_signals=False)
    assert journal_tables(tmp_path / "killed") == whole
    assert out.journals == str(tmp_path / "killed") and set(out.campaigns) == {"dots", "catalyst"}
    assert not (tmp_path / "killed.resuming").exists()


def test_twin_resume_of_a_lab_that_diverges_names_the_campaign_and_event_and_keeps_the_journals(tmp_path):
    run_shared(prepare(LAB, seed=3, overrides=SMALL), tmp_path, handle_signals=False)
    for db in tmp_path.glob("*.db"):
        with sqlite3.connect(db) as c:
            c.execute("DELETE FROM run WHERE key='summary'")
    with sqlite3.connect(tmp_path / "catalyst.db") as c:
        c.execute("UPDATE events SET kind='device.lost' WHERE seq=12")
    before = journal_tables(tmp_path)
    result = twin_cli("resume", str(tmp_path))
    assert result.exit_code == 2
    assert "catalyst.db: event 12 differs from the journal: it recorded 'device.lost'" in " ".join(result.output.split())
    assert journal_tables(tmp_path) == before


def test_twin_resume_of_a_finished_lab_says_so(tmp_path):
    run_shared(prepare(LAB, seed=3, overrides=SMALL), tmp_path, handle_signals=False)
    result = twin_cli("resume", str(tmp_path))
    assert result.exit_code == 2 and "every campaign of the lab finished" in " ".join(result.output.split())


@pytest.mark.process
@pytest.mark.parametrize("ends, one", [(("KILL",), None), (("KILL", "KILL"), "rl:agents/policies/flaky_scheduler.zip"),
                                       (("INT", "KILL"), None)])
def test_a_live_lab_sigkilled_and_resumed_finishes_every_campaign_and_keeps_what_its_journals_held(tmp_path, ends,
                                                                                                  one):
    """A lab on a scaled clock, SIGKILLed once experiments have finished (and, the second time, its resumed
    process SIGKILLed too), is rebuilt by `twin resume` from the inputs it journalled: every campaign's journal
    keeps what it held, the steps it had in the lab are asked after (here its in-process devices died with it:
    the steps are retried), and every campaign ends with its accounting invariant and no device running two
    steps. ``one``: the lab's one scheduler (``orchestrator.lab_scheduler``), whose answers are replayed too.
    ``INT``: the lab is first stopped by Ctrl-C; resumed, the steps the stop cancelled are sent again."""
    import signal
    import subprocess
    import sys
    import time

    import yaml
    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (4, 3)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    if one:
        raw["orchestrator"]["lab_scheduler"] = f"rl:{ROOT / one.removeprefix('rl:')}"
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    where = tmp_path / "j"
    lab = subprocess.Popen([sys.executable, "-m", "twin", "run", str(tmp_path / "lab.yaml"), "--clock", "scaled",
                            "--speed", "4000", "--bus", "memory", "--journal", str(where), "--quiet"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)

    def finished() -> int:
        n = 0
        for db in where.glob("*.db"):
            try:
                with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
                    n += con.execute("SELECT COUNT(*) FROM experiments WHERE status='done'").fetchone()[0]
            except sqlite3.Error:
                pass
        return n

    kills = len(ends)
    try:
        for kill, end in enumerate(ends):
            if kill:  # the resumed lab dies too, once it finished more
                lab = subprocess.Popen([sys.executable, "-m", "twin", "resume", str(where), "--quiet"],
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
            deadline, wanted = time.monotonic() + 60, 2 + 2 * kill
            while finished() < wanted and time.monotonic() < deadline and lab.poll() is None:
                time.sleep(0.05)
            assert lab.poll() is None, "the lab ended before it could be killed: " + lab.stderr.read()[-1000:]
            lab.send_signal(getattr(signal, f"SIG{end}"))
            lab.communicate(timeout=30)
            assert lab.returncode == (130 if end == "INT" else -signal.SIGKILL)
            if end == "INT":
                told = twin_cli("report", str(where / "dots.db"), columns=300)
                assert "interrupted (SIGINT)" in told.output and read_run(where / "dots.db")["summary"]["resumable"]
    finally:
        kill_all(lab)
    held = journal_tables(where)
    assert all("summary" not in read_run(db) for db in where.glob("*.db"))
    result = twin_cli("resume", str(where), "--json")
    assert result.exit_code == 0, result.output
    out = json.loads(result.output[result.output.index("{"):])
    for name, budget in (("dots", 4), ("catalyst", 3)):
        c = out["campaigns"][name]
        assert c["done"] + c["abandoned"] == budget == c["proposed"] and c["pending"] == 0, (name, c)
        events_now = journal_tables(where)[name][0]
        assert events_now[:len(held[name][0])] == held[name][0], name  # what the journal held is kept
        assert len([e for e in events_now if e[2] == "campaign.resumed"]) == kills, name
        # the steps in the lab died with the process: lost and retried, no cancel left unanswered
        assert "attempt.cancel_unanswered" not in [e[2] for e in events_now[len(held[name][0]):]], name
        # the resumed random planners went on drawing: a new one drew its first experiments again
        proposed = [e[7] for e in events_now if e[2] == "experiment.proposed"]
        assert len(set(proposed)) == len(proposed) == budget, (name, proposed)
        if "INT" in ends:  # the rebuilt journal has no stop: the steps it cancelled were sent again, no attempt used
            assert not [e for e in events_now if e[2] == "campaign.stopping" and "SIGINT" in (e[7] or "")], name
            assert not [e for e in events_now if e[2] == "attempt.failed" and '"cancelled"' in (e[7] or "")], name
    if "INT" in ends:
        sent_again = [e for n in ("dots", "catalyst") for e in journal_tables(where)[n][0]
                      if e[2] == "task.refused" and "campaign was stopped" in e[7]]
        assert sent_again, "the steps the stop cancelled are sent again"
        from twin.campaign.journal_read import read_inputs

        stopped_at = next(t for t, b in read_inputs(where / "lab.inputs") if ["stop", "interrupted (SIGINT)"] in
                          b.get("items", []))
        resumed_at = min(e[1] for e in journal_tables(where)["dots"][0] if e[2] == "campaign.resumed")
        assert resumed_at >= stopped_at, "lab time went on to the stop; the resumed lab starts there"
    assert_one_step_at_a_time(where)


@pytest.mark.process
def test_a_shared_lab_killed_with_a_step_on_a_device_of_another_process_adopts_its_result_once(tmp_path):
    """Over Zenoh, a router and the spectrometer in other processes: the lab is SIGKILLed while the spectrometer
    measures one campaign's sample; the measurement finishes while nobody listens; `twin resume` asks the device
    and takes that result, once, for the campaign it was for."""
    import os
    import signal
    import subprocess
    import sys
    import time

    import yaml

    from twin.campaign.journal_read import read_events
    from tests.twin.test_device_process import free_port
    from tests.twin.test_distributed_lab import start

    router, speed = f"tcp/127.0.0.1:{free_port()}", 1000.0
    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (3, 2)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    raw["devices"]["spectrometer"]["duration"] = {"mean_s": 1500, "cv": 0.0}
    raw["devices"]["synthesiser"]["duration"] = {"mean_s": 200, "cv": 0.0}
    raw["campaigns"][1]["chemistry"]["parameters"]["time_s"].update(low=60, high=600)  # a reaction, not 1.5 lab-h
    for d in raw["devices"].values():
        d["faults"] = {}
    raw.update(clock={"mode": "scaled", "speed": speed},
               bus={"kind": "zenoh", "listen": [], "connect": [router], "lease_ms": 1000},
               orchestrator={**raw["orchestrator"], "startup_s": 40000, "orphan_grace_s": 10 ** 6,
                             "timeout_slack_s": 40000})
    path, where = tmp_path / "lab.yaml", tmp_path / "j"
    path.write_text(yaml.safe_dump(raw))
    procs = {"router": start(["router", "--listen", router], "router")}
    procs["spec"] = start(["device", "serve", str(path), "--id", "spectrometer", "--connect", router, "--clock",
                           "scaled", "--speed", str(speed)], "ready spectrometer")
    # what is dispatched is on disk before the command leaves (write-ahead); a measurement takes 1.5 s of wall time
    running = ("SELECT COUNT(*) FROM events d WHERE d.kind='attempt.dispatched' AND d.device='spectrometer' AND NOT "
               "EXISTS (SELECT 1 FROM events e WHERE e.task=d.task AND e.attempt=d.attempt AND e.seq>d.seq)")
    try:
        lab = subprocess.Popen([sys.executable, "-m", "twin", "run", str(path), "--journal", str(where), "--quiet",
                                "--external", "spectrometer"], cwd=ROOT, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE)
        deadline, on_spec = time.monotonic() + 90, []
        while lab.poll() is None and time.monotonic() < deadline and not on_spec:
            for db in where.glob("*.db"):
                try:
                    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
                        if con.execute(running).fetchone()[0]:
                            on_spec.append(db.stem)
                except sqlite3.Error:
                    pass
            time.sleep(0.01)
        time.sleep(0.4)  # the spectrometer has the command and measures
        os.kill(lab.pid, signal.SIGKILL)  # the lab dies with a measurement running on the remote spectrometer
        lab.wait()
        assert on_spec, "no measurement ran before the deadline: " + lab.stderr.read().decode()[-1000:]
        campaign = on_spec[0]
        killed = next(e["task"] for e in reversed(read_events(where / f"{campaign}.db"))
                      if e["kind"] == "attempt.dispatched" and e["device"] == "spectrometer")
        time.sleep(2.0)  # the measurement (1.5 s of wall time) finishes while nobody listens
        resumed = subprocess.run([sys.executable, "-m", "twin", "resume", str(where), "--json"], cwd=ROOT,
                                 capture_output=True, text=True, timeout=180)
        assert resumed.returncode == 0, resumed.stderr[-3000:]
    finally:
        for p in procs.values():
            p.kill()
            p.wait()
    out = json.loads(resumed.stdout)
    assert_adopted_once(read_events(where / f"{campaign}.db"), killed, "spectrometer")
    for name, budget in (("dots", 3), ("catalyst", 2)):
        c = out["campaigns"][name]
        assert c["done"] + c["abandoned"] == budget == c["proposed"] and c["pending"] == 0, (name, c)
    assert_one_step_at_a_time(where)


@pytest.mark.process
@pytest.mark.parametrize("with_campaigns", [True, False])
def test_a_served_lab_sigkilled_and_resumed_goes_on_serving_and_takes_submissions(tmp_path, with_campaigns):
    """A served lab killed with campaigns under way (or before any came) is resumed by `twin resume` of its
    journals' directory, serves again, and takes a submission; SIGTERM ends it with every campaign accounted."""
    import signal
    import subprocess
    import sys
    import time

    import yaml

    from tests.twin.test_device_process import free_port

    port = free_port()
    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (3, 2)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    late = {**raw["campaigns"][0], "name": "late"}
    late["campaign"] = {**late["campaign"], "budget": 2}
    budgets = {"dots": 3, "catalyst": 2, "late": 2} if with_campaigns else {"late": 2}
    if not with_campaigns:
        del raw["campaigns"]
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    (tmp_path / "late.yaml").write_text(yaml.safe_dump(late))
    where = tmp_path / "runs"
    serve = [sys.executable, "-m", "twin", "lab", "serve", str(tmp_path / "lab.yaml"), "--listen",
             f"tcp/127.0.0.1:{port}", "--speed", "3000", "--journal", str(where)]
    connect = ["--lab", "shared", "--connect", f"tcp/127.0.0.1:{port}"]
    first = subprocess.Popen(serve, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
    again = None
    try:
        assert "serving lab shared" in first.stderr.readline()
        if with_campaigns:  # a campaign paused by an operator is still paused after the lab is resumed
            paused = twin_cli("ctl", "pause", "--campaign", "catalyst", "--as", "alice", *connect, columns=80)
            assert paused.exit_code == 0, paused.output
        deadline = time.monotonic() + 60
        what = ((where / "dots.db", "SELECT COUNT(*) FROM experiments WHERE status='done'") if with_campaigns else
                (where / "lab.inputs", "SELECT COUNT(*) FROM inputs"))  # killed once it did something
        while time.monotonic() < deadline:
            try:
                with sqlite3.connect(f"file:{what[0]}?mode=ro", uri=True) as con:
                    if con.execute(what[1]).fetchone()[0]:
                        break
            except sqlite3.Error:
                pass
            time.sleep(0.05)
        first.send_signal(signal.SIGKILL)
        first.communicate(timeout=30)
        again = subprocess.Popen([sys.executable, "-m", "twin", "resume", str(where), "--json"],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
        line = again.stderr.readline()
        while line and "resumed lab shared" not in line:
            line = again.stderr.readline()
        assert "serving again" in line, again.stderr.read()[-2000:] if again.poll() is not None else line
        if with_campaigns:
            states = {c["campaign"]: c["state"] for c in json.loads(
                twin_cli("ctl", "status", "--json", *connect, columns=80).output)["campaigns"]}
            assert states["catalyst"] == "paused by alice", states
            assert twin_cli("ctl", "resume", "--campaign", "catalyst", *connect, columns=80).exit_code == 0
        sub = twin_cli("submit", str(tmp_path / "late.yaml"), *connect, columns=80)
        assert sub.exit_code == 0 and "campaign late started" in sub.output, sub.output
        wait_until_ended(lambda: json.loads(twin_cli("ctl", "status", "--json", *connect, columns=80).output),
                         len(budgets))
        again.send_signal(signal.SIGTERM)
        out, err = again.communicate(timeout=60)
    finally:
        kill_all(first, again)
    assert again.returncode == 0, err[-2000:]
    summary = json.loads(out)
    assert set(summary["campaigns"]) == set(budgets)
    for name, budget in budgets.items():
        c = summary["campaigns"][name]
        assert c["done"] + c["abandoned"] == budget == c["proposed"], (name, c)
    assert_one_step_at_a_time(where)


@pytest.mark.parametrize("batches, words", [
    ([], "do not begin with its start"),
    ([(0.0, {"start": True, "secrets": {}}), (5.0, {"items": [["bogus", 1]]})], "lab input batch 2 of 2"),
    ([(0.0, {"start": True, "secrets": {}}), (5.0, {"items": [["seat", "dots"]]})], "lab input batch 2 of 2"),
])
def test_damaged_lab_inputs_are_named(batches, words):
    from twin.campaign.journal import NullJournal
    from twin.campaign.lab_replay import rebuild_lab
    from twin.campaign.replay import ReplayError
    from twin.scenario.sharing import campaign_scenarios

    s = prepare(LAB, clock="scaled", bus="memory")
    with pytest.raises(ReplayError, match=words):
        rebuild_lab(s, campaign_scenarios(s, s.name), batches, lambda name, cs: NullJournal())


@pytest.mark.parametrize("row", [30, 100])
def test_a_lab_stopped_by_ctrl_c_resumes_to_the_journals_of_the_unstopped_one(tmp_path, row):
    """At row 30 of a journal the second campaign has not started (it starts 1 lab-h in): it says so, and the
    resumed lab starts it."""
    from twin.runtime.resume import ResumeError, resume
    from twin.runtime.resume_lab import resume_lab

    s = prepare(LAB, seed=3, overrides=SMALL)
    run_shared(s, tmp_path / "whole", handle_signals=False)
    whole = journal_tables(tmp_path / "whole")
    with ctrl_c_at(row):
        stopped = run_shared(s, tmp_path / "lab")
    assert any(c.stopped == "interrupted (SIGINT)" and c.resumable for c in stopped.campaigns.values())
    assert bool(stopped.not_started) == (row == 30)
    cut_short = next(n for n, c in stopped.campaigns.items() if c.resumable)
    for shown in (tmp_path / "lab", tmp_path / "lab" / f"{cut_short}.db"):  # a campaign's journal names its lab
        told = twin_cli("report", str(shown), columns=300).output
        assert f"continue it with twin resume {tmp_path / 'lab'})" in told and f"{cut_short}.db)" not in \
            told.split("continue it with")[-1], told
    said = json.loads(twin_cli("report", str(tmp_path / "lab"), "--json").stdout)["campaigns"]
    assert said[cut_short]["state"] == "finished" and said[cut_short]["resume_with"] == str(tmp_path / "lab")
    assert said[cut_short]["summary"]["stopped"] == "interrupted (SIGINT)"
    assert set(said) == {"dots", "catalyst"} and all(c["state"] in ("finished", "never_started")
                                                     for c in said.values())
    with pytest.raises(ResumeError, match=rf"a campaign of a lab of several, which resumes as one: twin resume "
                                          rf"{tmp_path / 'lab'}"):
        resume(tmp_path / "lab" / "dots.db")
    resume_lab(tmp_path / "lab", handle_signals=False)
    assert journal_tables(tmp_path / "lab") == whole


def test_a_lab_that_ended_itself_is_not_resumed_and_says_why(tmp_path):
    from twin.runtime.resume import ResumeError
    from twin.runtime.resume_lab import resume_lab

    run_shared(prepare(LAB, seed=3, overrides={**SMALL, "campaigns.0.campaign.max_lab_hours": 0.5}), tmp_path,
               handle_signals=False)
    with pytest.raises(ResumeError, match=r"the lab ended \(max_lab_hours reached\): its campaigns ended on their "
                                          r"own or their operators stopped them, not the lab as a whole by Ctrl-C"):
        resume_lab(tmp_path, handle_signals=False)


def test_a_lab_stopped_by_a_labtwin_that_did_not_say_where_the_stop_came_from_is_not_resumed(tmp_path):
    import sqlite3

    from twin.runtime.resume import ResumeError
    from twin.runtime.resume_lab import resume_lab

    with ctrl_c_at(100):
        run_shared(prepare(LAB, seed=3, overrides=SMALL), tmp_path)
    for db in tmp_path.glob("*.db"):  # as the journals of 2026-12-04 or before: no 'resumable' in a summary
        with sqlite3.connect(db) as c:
            row = c.execute("SELECT value FROM run WHERE key='summary'").fetchone()
            if row:
                summary = json.loads(row[0])
                del summary["resumable"]
                c.execute("UPDATE run SET value=? WHERE key='summary'", (json.dumps(summary),))
    with pytest.raises(ResumeError, match=r"stopped \(interrupted \(SIGINT\)\) by a labtwin older than the resume "
                                          r"of a stopped lab.*run the lab again"):
        resume_lab(tmp_path, handle_signals=False)


@pytest.mark.process
def test_an_operator_stopping_each_campaign_of_a_lab_is_answered_and_the_lab_is_not_resumed(tmp_path):
    """The last stop ends the lab, whose campaign journals close at once: the answer's flush had found the journal
    closed and the operator was told the journal could not be written (a full disk?). A campaign its operator
    stopped stays stopped: the lab says nothing of resuming, and its resume is refused."""
    import subprocess
    import sys
    import time

    import yaml

    from tests.twin.test_device_process import free_port

    port, where = free_port(), tmp_path / "j"
    raw = yaml.safe_load(LAB.read_text())
    for c in raw["campaigns"]:
        c["campaign"].update(budget=40, planner="random", stop_on_target=False)
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    lab = subprocess.Popen([sys.executable, "-m", "twin", "run", str(tmp_path / "lab.yaml"), "--clock", "scaled",
                            "--speed", "500", "--listen", f"tcp/127.0.0.1:{port}", "--journal", str(where),
                            "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
    connect = ["--lab", "shared", "--connect", f"tcp/127.0.0.1:{port}"]
    try:
        deadline = time.monotonic() + 60
        while len(_status(connect)["campaigns"]) < 2 and time.monotonic() < deadline:  # until it answers
            time.sleep(0.2)
        for name in ("dots", "catalyst"):
            stopped = twin_cli("ctl", "stop", "--campaign", name, "--as", "alice", *connect, columns=200)
            assert stopped.exit_code == 0 and "operator.stop by alice" in stopped.output, stopped.output
        out, err = lab.communicate(timeout=60)
    finally:
        kill_all(lab)
    assert lab.returncode == 0, err[-2000:]
    assert "twin resume" not in out and "cannot write the journal" not in err
    refused = twin_cli("resume", str(where), columns=300)
    assert refused.exit_code == 2 and "the lab ended (stopped by alice): its campaigns ended on their own or their " \
        "operators stopped them" in " ".join(refused.output.split()), refused.output


def _status(connect: list[str]) -> dict:
    import json

    answer = twin_cli("ctl", "status", "--json", *connect, columns=200)
    return json.loads(answer.output) if answer.exit_code == 0 else {"campaigns": []}
