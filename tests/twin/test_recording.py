"""A campaign recorded to Rerun, read back with RrdReader, equals its journal; a replay equals the live run."""

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import twin_cli
from tests.rrd import read_rrd, rerun_verify, series
from tests.twin.shared_labs import lines_until, rest_of
from twin.campaign.journal_read import NotAJournal, read_events, read_experiments
from twin.runtime.lab import run
from twin.view.watch import RecordOptions

ROOT = Path(__file__).resolve().parents[2]
TWIN = [sys.executable, "-m", "twin"]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    summary = run(ROOT / "scenarios" / "flaky_lab.yaml", journal=d / "j.db", seed=5,
                  overrides={"campaign.budget": 16}, record=RecordOptions(save=d / "live.rrd"))
    return d, summary, read_rrd(d / "live.rrd")


def measurements(db):
    return [e for e in read_events(db, "msg.result") if "spectrum" in json.loads(e["detail"])["body"]["outputs"]]


def measured_yet(db) -> bool:
    """Whether a journal another process is writing holds a measurement yet (it may still be making its tables)."""
    from twin.campaign.journal_read import NotAJournal

    try:
        return db.exists() and db.stat().st_size > 0 and bool(measurements(db))
    except NotAJournal:  # read between the file's creation and its tables'
        return False


def test_the_recording_has_every_panel(live):
    d, summary, rrd = live
    for device in summary.utilisation:
        assert f"devices/{device}" in rrd
        assert f"utilisation/{device}" in rrd
    for path in ("objective/best", "objective/score", "spectra/measurement", "queue", "planner/proposals", "log", "summary",
                 "telemetry/reactor-1/temperature_k", "telemetry/reactor-1/setpoint_k"):
        assert path in rrd, path
    states = {r["StateChange:state"][0] for dev in summary.utilisation for r in rrd[f"devices/{dev}"]
              if "StateChange:state" in r}
    assert {"idle", "busy", "failed", "offline"} <= states
    queue = [r["Scalars:scalars"] for r in rrd["queue"] if "Scalars:scalars" in r]
    assert queue and all(len(row) == 3 and row[0] >= row[1] >= 0 for row in queue)  # ready steps ≥ samples waiting


def test_the_recording_carries_its_layout_and_each_panel_looks_where_the_campaign_drew(live):
    """The layout is what a viewer opens with: no test read it back, so a recording without it, or a panel
    over a path nothing is drawn on, would have passed."""
    from rerun.chunk import RrdReader

    d, _, rrd = live
    reader = RrdReader(d / "live.rrd")
    (layout,) = reader.blueprints()
    views = {}
    for chunk in reader.store(store=layout).stream():
        rb = chunk.to_record_batch()
        if "ViewBlueprint:display_name" in rb.schema.names:
            views[rb.column("ViewBlueprint:display_name")[0].as_py()[0]] = (
                rb.column("ViewBlueprint:space_origin")[0].as_py()[0].strip("/"))
    drawn = {"Devices", "Decisions and faults", "Summary", "Utilisation", "Queue", "Telemetry",
             "Objective (0 = target met) and best so far", "Spectra (latest, with targets)", "Measured outputs",
             "Proposals (normalised box)"}
    assert drawn <= set(views), views
    for name in drawn:
        assert any(path == views[name] or path.startswith(views[name] + "/") for path in rrd), (name, views[name])


def test_one_spectrum_per_measurement_at_the_same_lab_times(live):
    d, _, rrd = live
    journal = measurements(d / "j.db")
    spectra = rrd["spectra/measurement"]
    assert len(spectra) == len(journal) > 0
    sent = sorted(json.loads(e["detail"])["t_lab"] for e in journal)
    assert [r["lab_time"] for r in spectra] == pytest.approx(sent, abs=1e-6)
    assert len(spectra[0]["LineStrips2D:strips"][0]) == 176
    by_time = {r["lab_time"]: r["LineStrips2D:strips"][0] for r in spectra}
    for e in journal:  # each point where the device put it: x evenly spaced from start_nm, y flipped to screen
        msg = json.loads(e["detail"])
        spectrum = msg["body"]["outputs"]["spectrum"]
        drawn = min(by_time.items(), key=lambda kv: abs(kv[0] - msg["t_lab"]))[1]
        x = [spectrum["start_nm"] + i * spectrum["step_nm"] for i in range(len(spectrum["y"]))]
        assert [p[0] for p in drawn] == pytest.approx(x, rel=1e-6)
        assert [p[1] for p in drawn] == pytest.approx([300 * (1 - y) for y in spectrum["y"]], rel=1e-5, abs=1e-3)


def test_best_so_far_is_monotone_and_ends_at_the_journals_best(live):
    d, _, rrd = live
    best = [v for _, v in series(rrd["objective/best"])]
    assert best == sorted(best, reverse=True)
    scores = [min(json.loads(e["scores"]).values()) for e in read_experiments(d / "j.db") if e["scores"]]
    assert best[-1] == pytest.approx(min(scores))


def test_fault_log_matches_the_journals_faults(live):
    d, _, rrd = live
    faults = read_events(d / "j.db", "attempt.failed")
    logged = [r for r in rrd["log"] if r["TextLog:text"][0].startswith("attempt.failed")]
    assert len(logged) == len(faults) > 0
    assert {r["TextLog:level"][0] for r in logged} == {"WARN"}
    assert sorted(r["lab_time"] for r in logged) == pytest.approx(sorted(f["t_lab"] for f in faults), abs=1e-6)
    lost = read_events(d / "j.db", "device.lost")
    assert len([r for r in rrd["log"] if r["TextLog:text"][0].startswith("device.lost")]) == len(lost)


def test_the_log_names_each_finished_experiment_and_keeps_its_numbers_short(live):
    import re

    d, _, rrd = live
    done = [r["TextLog:text"][0] for r in rrd["log"] if r["TextLog:text"][0].startswith("experiment.done")]
    ids = [int(re.match(r"experiment\.done e(\d+):", line)[1]) for line in done]
    assert sorted(ids) == sorted(e["id"] for e in read_experiments(d / "j.db") if e["status"] == "done")
    numbers = [n for r in rrd["log"] for n in re.findall(r"\d+\.\d+", r["TextLog:text"][0])]
    assert numbers and all(len(n.replace(".", "").lstrip("0")) <= 6 for n in numbers)  # 131.741, not 131.7414949…


def test_the_summary_document_is_the_runs_summary(live):
    _, summary, rrd = live
    text = rrd["summary"][0]["TextDocument:text"][0]
    assert f"{summary.done} done" in text and f"{summary.lab_hours:.2f} h" in text


def test_replay_from_the_journal_equals_the_live_recording(live):
    d, _, rrd = live
    res = twin_cli("replay", d / "j.db", "--save", d / "replay.rrd")
    assert res.exit_code == 0, res.stderr
    replayed = read_rrd(d / "replay.rrd")
    assert set(replayed) - {"__properties"} == set(rrd) - {"__properties"}
    for path in rrd:
        if path != "__properties":
            assert replayed[path] == rrd[path], path
    # and the way Rerun itself compares recordings; another seed's recording does not pass
    def compare(a, b):
        return subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "compare", "--unordered", str(a),
                               str(b)], capture_output=True, text=True, timeout=120)

    same = compare(d / "live.rrd", d / "replay.rrd")
    assert same.returncode == 0, same.stdout[-2000:] + same.stderr[-2000:]
    run(ROOT / "scenarios" / "flaky_lab.yaml", journal=d / "other.db", seed=6, overrides={"campaign.budget": 16},
        record=RecordOptions(save=d / "other.rrd"))
    assert compare(d / "live.rrd", d / "other.rrd").returncode != 0


def test_rerun_verifies_the_live_and_the_replayed_recording_and_not_a_cut_one(live):
    """What a client that is not ours makes of a recording: Rerun's own `rrd verify` loads it and checks every
    column against its archetype (a recording cut short, as a killed process leaves one, fails it)."""
    d, _, _ = live
    assert twin_cli("replay", d / "j.db", "--save", d / "again.rrd").exit_code == 0
    for path in (d / "live.rrd", d / "again.rrd"):
        verified = rerun_verify(path)
        assert verified.returncode == 0, verified.stdout[-2000:] + verified.stderr[-2000:]
    data = (d / "live.rrd").read_bytes()
    (d / "cut.rrd").write_bytes(data[:len(data) // 2])
    assert rerun_verify(d / "cut.rrd").returncode != 0


def test_an_interrupted_replay_leaves_the_file_it_was_to_replace_as_it_was(live, monkeypatch):
    """Ctrl-C half-way through a replay left a recording of part of the run under the name asked for."""
    from twin.view.observer import LabObserver

    d, _, _ = live
    earlier = d / "earlier.rrd"
    earlier.write_bytes(b"a recording from before")
    seen = []
    real = LabObserver.on_message

    def interrupted(self, key, payload):
        seen.append(key)
        if len(seen) == 200:
            raise KeyboardInterrupt
        real(self, key, payload)

    monkeypatch.setattr(LabObserver, "on_message", interrupted)
    res = twin_cli("replay", str(d / "j.db"), "--save", str(earlier), columns=80)
    assert res.exit_code == 130 and len(seen) == 200, res.output
    assert f"interrupted: nothing saved ({earlier} is as it was)" in " ".join(res.output.split())
    assert earlier.read_bytes() == b"a recording from before"
    assert not [p for p in d.iterdir() if p.name.endswith(".partial")]
    monkeypatch.setattr(LabObserver, "on_message", real)
    res = twin_cli("replay", str(d / "j.db"), "--save", str(earlier), columns=80)
    assert res.exit_code == 0
    replayed, recorded = read_rrd(earlier), read_rrd(d / "live.rrd")
    assert {k: v for k, v in replayed.items() if k != "__properties"} == \
        {k: v for k, v in recorded.items() if k != "__properties"}  # the start time is the replay's own


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.process
def test_twin_watch_waits_for_its_lab_to_come_up_stops_at_ctrl_c_and_says_how_to_wait_longer(tmp_path):
    nobody = f"tcp/127.0.0.1:{free_port()}"
    watcher = subprocess.Popen([*TWIN, "watch", "--lab", "qd", "--connect", nobody, "--save", str(tmp_path / "w.rrd"),
                                "--wait", "120"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert f"connecting to {nobody} (waiting up to 120 s" in watcher.stderr.readline()
        watcher.send_signal(signal.SIGINT)  # Zenoh's own wait for the endpoint cannot be interrupted: ours can
        t0 = time.monotonic()
        _, err = watcher.communicate(timeout=60)
        stopped_s = time.monotonic() - t0
    finally:
        watcher.kill()
    assert watcher.returncode == 130 and f"interrupted while waiting for {nobody} to answer: nothing recorded" in err
    assert "Traceback" not in err and stopped_s < 10 and not (tmp_path / "w.rrd").exists()

    res = twin_cli("watch", "--lab", "qd", "--connect", nobody, "--save", str(tmp_path / "w.rrd"), "--wait", "1.5")
    assert res.exit_code == 2 and f"nothing answered at {nobody} within 1.5 s" in res.stderr
    assert "--wait SECONDS waits longer" in res.stderr and not (tmp_path / "w.rrd").exists()


@pytest.mark.process
def test_a_watcher_whose_router_restarts_waits_for_it_and_records_the_whole_campaign(tmp_path):
    """A router restarted under a watcher took every token from it at once: the watch said the lab had died
    ("finish it with twin resume") and ended, while the lab ran on. Now it tells its own lost link from a lost lab."""
    router_at = f"tcp/127.0.0.1:{free_port()}"
    router = [*TWIN, "router", "--listen", router_at]
    db = tmp_path / "j.db"
    procs = {"router": subprocess.Popen(router, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)}
    assert "listening" in procs["router"].stdout.readline()
    procs["lab"] = subprocess.Popen([*TWIN, "run", "scenarios/quantum_dots.yaml", "--budget", "6", "--planner",
                                     "random", "--clock", "scaled", "--speed", "400", "--connect", router_at,
                                     "--journal", str(db), "--quiet"], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, text=True, cwd=ROOT)
    # 400x: the lab runs ~13 s, ~9 of them after the first measurement, while the router restarts (~2 s)
    procs["watcher"] = subprocess.Popen([*TWIN, "watch", "--lab", "qd", "--connect", router_at, "--wait", "60",
                                         "--save", str(tmp_path / "w.rrd")], stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE, text=True, cwd=ROOT,
                                        env={**os.environ, "COLUMNS": "300"})  # a line each
    watcher = procs["watcher"]

    def next_said(words: str) -> str:
        for line in watcher.stderr:
            if words in line:
                return line
        raise AssertionError(f"the watcher ended without saying {words!r}")
    try:
        assert "watching lab 'qd'" in watcher.stdout.readline()
        deadline = time.monotonic() + 120
        while not measured_yet(db):
            assert procs["lab"].poll() is None and time.monotonic() < deadline, "the lab ended or was slow"
            time.sleep(0.05)
        procs["router"].kill()
        procs["router"].wait()
        said = next_said("lost the connection")
        assert f"lost the connection to {router_at}" in said and "the lab may be running still" in said, said
        procs["router"] = subprocess.Popen(router, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                           cwd=ROOT)  # on the same port
        assert "read from its history" in next_said(f"connected to {router_at} again")
        assert procs["lab"].wait(timeout=120) == 0, procs["lab"].stderr.read()[-2000:]
        out, err = watcher.communicate(timeout=120)
    finally:
        for p in procs.values():
            p.kill()
            p.wait()
    assert watcher.returncode == 0 and "left the bus" not in err, err
    assert "campaign ended: 6 experiments finished" in out, out
    rrd = read_rrd(tmp_path / "w.rrd")
    assert len(rrd["spectra/measurement"]) == len(measurements(db)) == 6


@pytest.mark.process
def test_a_watched_lab_that_dies_ends_the_watch_by_its_presence_and_a_following_watcher_records_its_resume(tmp_path):
    port = free_port()
    db = tmp_path / "j.db"
    watch = [*TWIN, "watch", "--lab", "qd", "--connect", f"tcp/127.0.0.1:{port}", "--wait", "60"]
    once = subprocess.Popen([*watch, "--save", str(tmp_path / "once.rrd")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT)
    following = subprocess.Popen([*watch, "--save", str(tmp_path / "all.rrd"), "--follow"], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, cwd=ROOT)
    lab = subprocess.Popen([*TWIN, "run", "scenarios/quantum_dots.yaml", "--budget", "6", "--planner", "random",
                            "--clock", "scaled", "--speed", "1000", "--listen", f"tcp/127.0.0.1:{port}", "--journal",
                            str(db), "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)

    def measured() -> bool:  # a spectrum measured
        try:
            return db.exists() and bool(measurements(db))
        except NotAJournal:  # its name claimed, nothing written yet
            return False

    try:
        # each watcher has seen the lab before it is killed: one that connected an instant before the kill, too
        # late for the lab's presence to reach it, never saw a lab, and rightly waits for one
        for watcher in (once, following):
            said = lines_until(watcher.stdout, {"is on the bus"}, 120)
            assert "lab 'qd' is on the bus: recording it" in said[-1], said
        deadline = time.monotonic() + 120
        while not measured():
            assert lab.poll() is None and time.monotonic() < deadline, lab.stderr.read() if lab.poll() else "slow"
            time.sleep(0.05)
        lab.kill()
        lab.wait()
        once.wait(timeout=60)  # no --follow: it ends by itself, the lab's presence gone
        err = once.stderr.read()
        assert once.returncode == 1, err
        assert "lab 'qd' left the bus before its campaigns ended" in err and "twin resume JOURNAL" in err, err
        assert "Traceback" not in err and "did not answer for its history" not in err, err  # gone, not waited for
        drawn = len(read_rrd(tmp_path / "once.rrd").get("spectra/measurement", []))  # saved, with what it had
        assert drawn < 6 and f"recorded {drawn} spectra" in err, err

        said = lines_until(following.stderr, {"left the bus"}, 120)  # within a deadline: a miss hung CI once
        assert "still watching, for it to come back (twin resume)" in said[-1], said
        resumed = subprocess.run([*TWIN, "resume", str(db), "--quiet"], capture_output=True, text=True, cwd=ROOT,
                                 timeout=180)
        assert resumed.returncode == 0, resumed.stderr[-2000:]
        line = lines_until(following.stdout, {"campaign ended"}, 120)[-1]
        assert "campaign ended: 6 experiments finished" in line, line
        # the lab run again, a new run and not a resume: the watch ends there, where it drew the new run into the
        # same recording as if resumed (a second summary, and a timeline that started again)
        again = subprocess.run([*TWIN, "run", "scenarios/quantum_dots.yaml", "--budget", "2", "--planner", "random",
                                "--clock", "scaled", "--speed", "1000", "--listen", f"tcp/127.0.0.1:{port}",
                                "--journal", str(tmp_path / "again.db"), "--quiet"], capture_output=True, text=True,
                               cwd=ROOT, timeout=180)
        assert again.returncode == 0, again.stderr[-2000:]
        following.wait(timeout=60)
        err = rest_of(following.stderr)
        assert "lab 'qd' came back with another run, not a resume of the one recorded" in err, err
    finally:
        for p in (lab, once, following):
            p.kill()
    assert following.returncode == 0, err
    # every spectrum, those before the kill and after the resume: a resumed lab's devices count their message ids
    # from 1 again, and the watcher tells them from the ones it had by their lab time
    rrd = read_rrd(tmp_path / "all.rrd")
    assert len(rrd["spectra/measurement"]) == len(measurements(db)) == 6
    assert "summary" in rrd and "6 done" in rrd["summary"][0]["TextDocument:text"][0]
    best = [v for _, v in sorted(series(rrd["objective/best"]))]  # by lab time: a file's chunks come in any order
    assert len(best) == 6 and best == sorted(best, reverse=True) and all(math.isfinite(v) for v in best)


def test_the_fast_runtime_records_in_process_and_its_recording_equals_the_replay(tmp_path):
    # runtime="fast" is refused for anything the fast runtime cannot do: recording is no longer one of them
    run(ROOT / "scenarios" / "flaky_lab.yaml", journal=tmp_path / "j.db", seed=5, bus="memory", runtime="fast",
        overrides={"campaign.budget": 16}, record=RecordOptions(save=tmp_path / "live.rrd"))
    res = twin_cli("replay", tmp_path / "j.db", "--save", tmp_path / "replay.rrd")
    assert res.exit_code == 0, res.stderr
    live, replayed = read_rrd(tmp_path / "live.rrd"), read_rrd(tmp_path / "replay.rrd")
    assert len(live["log"]) > 10 and len([p for p in live if p.startswith("devices/")]) == 6
    assert {p: rows for p, rows in live.items() if p != "__properties"} == \
        {p: rows for p, rows in replayed.items() if p != "__properties"}


class _Rows:
    """A canvas that keeps every row it is handed, in order."""

    def __init__(self):
        self.rows = []

    def __getattr__(self, name):
        if name == "flush":
            return lambda: None
        return lambda *args, **kwargs: self.rows.append((name, repr(args), repr(kwargs)))


def test_a_watcher_that_reads_a_history_three_times_draws_it_once_and_remembers_a_bounded_number(live):
    from twin.campaign.journal_read import as_messages
    from twin.view.observer import LabObserver
    from twin.view.repeats import Repeats

    d, _, _ = live
    messages = as_messages(read_events(d / "j.db"))
    once = LabObserver(_Rows())
    for m in messages:
        once.on_message("", m)
    watcher = LabObserver(_Rows(), dedupe=True)
    watcher._seen = Repeats(keep=40)  # the default keeps 200,000; this journal has a few hundred messages
    for _ in range(3):  # live and in its history, then all of it again when the lab came back
        for m in messages:
            watcher.on_message("", m)
    assert len(messages) > 200 and watcher.c.rows == once.c.rows
    assert len(watcher._seen) < 4 * 40  # each generation ends where lab time moves on: a little over 40
    assert watcher._seen.floor > 0
    # a message later than all of them is drawn; one at a time already forgotten is taken as drawn
    assert watcher._seen.fresh("spectrometer:99999", 1e9) and not watcher._seen.fresh("anyone:1", 0.0)


def test_a_message_stamped_far_off_neither_stops_a_watcher_forgetting_nor_hides_what_comes_after():
    from twin.view.repeats import Repeats

    seen = Repeats(keep=10)
    for i in range(25):
        assert seen.fresh(f"lab:{i}", float(i))
    assert seen.fresh("odd:1", 1.7e9)  # Unix time where lab time belongs
    for i in range(25, 100):
        assert seen.fresh(f"lab:{i}", float(i)), i  # drawn: the odd one made no later message look forgotten
    assert len(seen) <= 2 * 10 + 1 and 80 <= seen.floor < 99  # still forgetting
    assert not any(seen.fresh(f"lab:{i}", float(i)) for i in range(100))  # a history read again: nothing twice


@pytest.mark.process
def test_twin_watch_log_prints_the_decisions_and_faults_as_the_journal_has_them_and_nothing_else_on_stdout(tmp_path):
    """For a terminal with no display: `twin watch --log` (no recording) prints the viewer's log, a line each."""
    import re

    port = free_port()
    db = tmp_path / "j.db"
    watcher = subprocess.Popen([*TWIN, "watch", "--lab", "qd", "--connect", f"tcp/127.0.0.1:{port}", "--wait", "60",
                                "--log"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    lab = subprocess.Popen([*TWIN, "run", "scenarios/quantum_dots.yaml", "--budget", "6", "--planner", "random",
                            "--clock", "scaled", "--speed", "1000", "--listen", f"tcp/127.0.0.1:{port}", "--journal",
                            str(db), "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        out, err = watcher.communicate(timeout=180)
        lab.wait(timeout=60)
    finally:
        for p in (lab, watcher):
            p.kill()
    assert watcher.returncode == 0, err
    lines = out.splitlines()
    shape = re.compile(r"^ *\d+\.\d{3} h  (INFO |WARN |ERROR)  \S")
    assert lines and all(shape.match(line) for line in lines), lines  # stdout is the log's alone
    assert "watched 6 spectra, 6 finished experiments" in err and "campaign ended" in err, err
    done = [line for line in lines if " experiment.done e" in line]
    journalled = [e for e in read_events(db) if e["kind"] == "experiment.done"]
    assert [float(line.split()[0]) for line in done] == [round(e["t_lab"] / 3600, 3) for e in journalled]
    assert not [line for line in lines if "attempt.dispatched" in line]  # each dispatch: a debug row, left out
    assert any("campaign quantum_dots started" in line for line in lines)
