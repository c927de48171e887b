"""What the tests of labs shared by several campaigns share: the lab file, journal readers, the invariants."""

import queue
import sqlite3
import threading
from pathlib import Path

import pytest

from twin.runtime.shared_run import run_shared

ROOT = Path(__file__).resolve().parents[2]
LAB = ROOT / "scenarios" / "shared_lab.yaml"
NO_FAULTS = {f"devices.{d}.faults": {} for d in ("synthesiser", "reactor", "spectrometer")}


def events(db: Path, *kinds: str) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        marks = ",".join("?" * len(kinds))
        return con.execute(f"SELECT t_lab, kind, experiment, task, attempt, device, detail, seq FROM events "
                           f"WHERE kind IN ({marks}) ORDER BY seq", kinds).fetchall()
    finally:
        con.close()


def device_jobs(journals: Path) -> dict[str, list[tuple[float, float, str]]]:
    """Per device, (accepted at, ended at, campaign) of every step it ran, from every campaign's journal: a step
    ends with its result or fault, when its device leaves the bus, or when its campaign cancels it (at the end,
    or at its deadline: an in-process device stops at once, and a campaign that ends then journals no answer), or
    with a "not now" (a lab resumed after Ctrl-C sends the steps the stop cancelled again so)."""
    jobs: dict[str, list[tuple[float, float, str]]] = {}
    for db in journals.glob("*.db"):
        started: dict[tuple, tuple[float, str]] = {}
        for t, kind, _, task, attempt, device, detail, _ in events(
                db, "msg.accepted", "msg.result", "msg.fault", "msg.rejected", "device.lost", "attempt.cancelled",
                "attempt.failed"):
            if kind == "attempt.failed" and "timed_out" not in detail:
                continue
            if kind == "msg.accepted":
                started[(task, attempt)] = (t, device)
            elif kind == "device.lost":
                for key in [k for k, (_, d) in started.items() if d == device]:
                    jobs.setdefault(device, []).append((started.pop(key)[0], t, db.stem))
            elif (task, attempt) in started:
                jobs.setdefault(device, []).append((started.pop((task, attempt))[0], t, db.stem))
        assert not started, f"{db.stem}: steps accepted and never ended: {started}"
    return jobs


def assert_one_step_at_a_time(journals: Path) -> None:
    for device, runs in device_jobs(journals).items():
        runs.sort()
        for (s0, e0, c0), (s1, e1, c1) in zip(runs, runs[1:]):
            assert s1 >= e0 - 1e-9, f"{device} ran {c0}'s step [{s0}, {e0}] and {c1}'s [{s1}, {e1}] at once"


def assert_accounted(summary) -> None:
    for name, c in summary.campaigns.items():
        assert c.done + c.abandoned + c.pending == c.proposed, name
        assert c.proposed > 0, f"{name} proposed nothing"
        if not c.stopped:
            assert c.pending == 0, name


def wait_until_ended(status, campaigns: int, seconds: float = 90) -> dict:
    """Poll ``status()`` (a lab's `twin ctl status --json`) until ``campaigns`` campaigns have all ended."""
    import time

    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        now = status()
        if len(now["campaigns"]) == campaigns and all(c["state"] == "ended" for c in now["campaigns"]):
            return now
        time.sleep(0.5)
    pytest.fail(f"the campaigns did not end: {now}")


def lines_until(stream, wanted: set[str], seconds: float = 60) -> list[str]:
    """Read a process's text ``stream`` until a line holding each of ``wanted`` has come (or fail: none came, or
    ``seconds`` passed with no line); the lines read. Called again on the same stream, it goes on from there."""
    lines = _line_queue(stream)
    seen, missing = [], set(wanted)
    while missing:
        try:
            line = lines.get(timeout=seconds)
        except queue.Empty:
            break
        if not line:
            lines.put("")  # the end, for a later call too
            break
        seen.append(line)
        missing -= {w for w in missing if w in line}
    if missing:
        pytest.fail(f"no line with {sorted(missing)} in {seen}")
    return seen


def rest_of(stream, seconds: float = 60) -> str:
    """What is left of a stream :func:`lines_until` has read from, to its end (or ``seconds`` with no line)."""
    lines, rest = _line_queue(stream), []
    try:
        while (line := lines.get(timeout=seconds)):
            rest.append(line)
        lines.put("")
    except queue.Empty:
        rest.append(f"(no more in {seconds:g} s, and no end)")
    return "".join(rest)


_readers: dict = {}  # stream -> its lines, read by one thread (two would each take some of its lines)


def _line_queue(stream) -> queue.Queue:
    if stream not in _readers:
        lines: queue.Queue = queue.Queue()
        _readers[stream] = lines
        threading.Thread(target=lambda: [lines.put(line) for line in iter(stream.readline, "")] + [lines.put("")],
                         daemon=True).start()
    return _readers[stream]


def kill_all(*procs) -> None:
    for proc in procs:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.communicate()


def recorded_lab(s, where: Path, runtime: str = "auto"):
    """Run ``s`` with its recording saved, and read the recording back (Rerun's own `rrd verify` passing it)."""
    from tests.rrd import read_rrd, rerun_verify
    from twin.view.watch import RecordOptions, open_lab_observer

    devices = {name: dtype for dtype in s.devices for name in s.instance_names(dtype)}
    observer, recording = open_lab_observer(RecordOptions(save=where / "lab.rrd"), "t",
                                            [c.name for c in s.campaigns], devices)
    try:
        out = run_shared(s, where / "runs", handle_signals=False, observer=observer, runtime=runtime)
    finally:
        recording.close()
    verified = rerun_verify(where / "lab.rrd")
    assert verified.returncode == 0, verified.stdout[-2000:] + verified.stderr[-2000:]
    return out, read_rrd(where / "lab.rrd", row_ids=True)


def states(rows: list[dict]) -> list[tuple[float, str]]:
    """A device's (lab time, state) changes in the order they were drawn."""
    changes = [r for r in rows if "StateChange:state" in r]
    return [(r["lab_time"], r["StateChange:state"][0]) for r in sorted(changes, key=lambda r: (r["lab_time"],
                                                                                               r["row_id"]))]


def busy_spells(rows: list[dict]) -> list[tuple[float, float]]:
    """(from, to) of each busy spell of a device's state rows; a second 'busy' before the first ended fails."""
    spells, since = [], None
    for t, state in states(rows):
        if state == "busy":
            assert since is None, f"busy again at {t} while busy since {since}: two steps at once"
            since = t
        elif since is not None:
            spells.append((since, t))
            since = None
    return spells


SMALL = {"campaigns.0.campaign.budget": 6, "campaigns.1.campaign.budget": 4, "campaigns.1.start_h": 1.0}


def journal_tables(journals: Path) -> dict[str, tuple]:
    out = {}
    for db in sorted(journals.glob("*.db")):
        with sqlite3.connect(db) as c:
            out[db.stem] = (c.execute("SELECT * FROM events ORDER BY seq").fetchall(),
                            c.execute("SELECT * FROM experiments ORDER BY id").fetchall())
    return out
