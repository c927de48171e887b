"""A device written from docs/wire.md alone — its Python block, run as it stands, using nothing of labtwin —
serves a live campaign over Zenoh."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from tests.twin.test_device_process import free_port
from twin.campaign.journal_read import read_events
from twin.runtime.lab import make_clock, prepare, run_async

pytestmark = pytest.mark.process
ROOT = Path(__file__).resolve().parents[2]
SPEED = 100.0  # lab seconds per wall second


def documented(name: str) -> str:
    """The Python block of docs/wire.md whose first line is ``# name``."""
    blocks = {b.split("\n", 1)[0].removeprefix("# "): b
              for b in re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "wire.md").read_text(), re.S)}
    assert set(blocks) == {"device.py", "agent.py", "monitor.py"}, sorted(blocks)
    assert set(re.findall(r"^(?:import|from) (\w+)", blocks[name], re.M)) <= {"json", "queue", "signal", "sys",
                                                                              "time", "zenoh"}
    return blocks[name]


def run_with(tmp_path, script: str, args: list[str], external: set[str] = frozenset(), edit=lambda text: text,
             **changes):
    """A live qd_lab campaign on a scaled clock over Zenoh, with docs/wire.md's ``script`` started beside it
    (given the lab, ``args`` and the endpoint; ``edit``: a change to the script, a stranger's mistake) and stopped
    with SIGTERM after: (summary, journal, its stdout)."""
    port = free_port()
    raw = qd_lab(**{"lab": f"wire{port}", "clock": {"mode": "scaled", "speed": SPEED},
                    "bus": {"kind": "zenoh", "listen": [f"tcp/127.0.0.1:{port}"]}, "orchestrator.startup_s": 3000,
                    **changes})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    (tmp_path / script).write_text(edit(documented(script)))
    s = prepare(path)
    clock = make_clock(s)
    db = tmp_path / "j.db"
    proc = subprocess.Popen([sys.executable, script, s.lab, *args, f"tcp/127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        summary = clock.run(run_async(s, clock, db, set(external)))
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err  # SIGTERM: the token undeclared and the session closed, as documented
    return summary, db, out


def test_the_documented_device_measures_every_experiment_of_a_live_campaign(tmp_path):
    summary, db, _ = run_with(tmp_path, "device.py", ["spectrometer"], {"spectrometer"}, **{
        "campaign.budget": 4, "devices.spectrometer.instances": 1,
        "devices.spectrometer.duration": {"mean_s": 50, "cv": 0.0},
        "devices.synthesiser.duration": {"mean_s": 30, "cv": 0.0}})
    assert summary.done == 4 and summary.abandoned == 0, summary
    assert summary.invalid_messages == 0 and summary.rejected_messages == 0 and summary.failed_attempts == 0
    events = read_events(db)
    assert not [e for e in events if e["kind"] == "device.clock_off"]  # its lab time is the lab's
    results = [e for e in events if e["kind"] == "msg.result" and e["device"] == "spectrometer"]
    made = {e["task"].split("s")[0]: json.loads(e["detail"])["body"]["sample"]
            for e in events if e["kind"] == "msg.result" and e["device"] == "synthesiser"}
    assert len(results) == 4
    for r in results:  # what the device read off each sample is what the lab scored
        body = json.loads(r["detail"])["body"]
        sample = made[r["task"].split("s")[0]]
        assert body["outputs"] == {"peak_nm": sample["peak_nm"], "fwhm_nm": sample["fwhm_nm"],
                                   "intensity": sample["amplitude"]}
        assert body["sample"]["id"].endswith(f"/e{r['experiment']}")  # the id the lab gave it, handed back
    accepted = [e for e in events if e["kind"] == "msg.accepted" and e["device"] == "spectrometer"]
    assert len(accepted) == 4


def in_client_mode(script: str) -> str:
    """A stranger's choice the page allows: the session in Zenoh's client mode, as the page says to set it."""
    peer = """config.insert_json5("mode", '"peer"')"""
    assert script.count(peer) == 1
    return script.replace(peer, """config.insert_json5("mode", '"client"')\nconfig.insert_json5("connect/timeout_ms", "-1")""")


def test_the_documented_device_in_client_mode_started_before_its_lab_serves_it(tmp_path):
    """Without ``connect/timeout_ms: -1`` a client's session failed to open, the lab not being up yet."""
    summary, _, _ = run_with(tmp_path, "device.py", ["spectrometer"], {"spectrometer"}, edit=in_client_mode, **{
        "campaign.budget": 2, "devices.spectrometer.instances": 1,
        "devices.spectrometer.duration": {"mean_s": 50, "cv": 0.0},
        "devices.synthesiser.duration": {"mean_s": 30, "cv": 0.0}})
    assert summary.done == 2 and summary.abandoned == 0 and summary.failed_attempts == 0, summary


def test_the_documented_agent_schedules_a_live_campaign_and_the_lab_does_what_it_said(tmp_path):
    summary, db, out = run_with(tmp_path, "agent.py", [], **{
        "campaign.budget": 6, "campaign.max_in_flight": 3,
        "campaign.scheduler": "remote", "campaign.fallback_scheduler": "fifo"})
    assert summary.done == 6 and summary.abandoned == 0 and summary.scheduler_fallbacks == 0, summary
    said = [(a["task"], a["device"]) for line in out.splitlines() for a in json.loads(line)]
    dispatched = [(e["task"], e["device"]) for e in read_events(db) if e["kind"] == "attempt.dispatched"]
    assert dispatched and sorted(dispatched) == sorted(said)  # every pair it gave was carried out, and no other


def test_an_agent_of_ones_own_that_puts_another_lab_in_its_keys_is_named_when_the_lab_gives_up_waiting(tmp_path,
                                                                                                       caplog):
    """The agent of docs/wire.md started for lab 'other': the lab said only "no scheduler agent on the bus"."""
    elsewhere = "lab, endpoint = 'other', sys.argv[2]"
    summary, _, _ = run_with(tmp_path, "agent.py", [], edit=lambda text: text.replace(
        "lab, endpoint = sys.argv[1:3]", elsewhere, 1), **{
        "campaign.budget": 2, "campaign.scheduler": "remote", "campaign.fallback_scheduler": "fifo",
        "orchestrator.startup_s": 300})
    assert summary.done == 2, summary  # fifo decided
    said = [r.getMessage() for r in caplog.records if "no scheduler agent on the bus" in r.getMessage()]
    assert len(said) == 1 and "fifo decides (one is on it for lab 'other': " in said[0], said


def test_a_device_that_stamps_unix_time_is_named_once_and_its_results_still_count(tmp_path, caplog):
    """The likeliest mistake in a device written from docs/wire.md: t_lab as time.time(). The lab said nothing,
    and the viewer drew its results 56 years into the campaign."""
    unix = "\"t_lab\": time.time()"
    summary, db, _ = run_with(tmp_path, "device.py", ["spectrometer"], {"spectrometer"},
                              edit=lambda text: text.replace("\"t_lab\": lab_time() if anchor else 0.0", unix), **{
        "campaign.budget": 2, "devices.spectrometer.instances": 1,
        "devices.spectrometer.duration": {"mean_s": 50, "cv": 0.0},
        "devices.synthesiser.duration": {"mean_s": 30, "cv": 0.0}})
    assert summary.done == 2 and summary.invalid_messages == 0
    off = [json.loads(e["detail"]) for e in read_events(db, "device.clock_off")]
    assert len(off) == 1 and off[0]["sender"] == "spectrometer" and off[0]["off_s"] > 1e9, off
    assert sum("spectrometer stamps its messages" in r.getMessage() for r in caplog.records) == 1


def test_the_documented_monitor_prints_what_a_person_should_hear_of_as_the_journal_has_it(tmp_path):
    """A spectrometer left to another process that never comes: the lab says it is missing, then unavailable,
    gives up on the experiments waiting for it, and ends. The monitor hears it all from the decisions stream."""
    summary, db, out = run_with(tmp_path, "monitor.py", [], {"spectrometer"}, **{
        "campaign.budget": 2, "devices.spectrometer.instances": 1, "orchestrator.startup_s": 300,
        "campaign.give_up_after_s": 400, "devices.synthesiser.duration": {"mean_s": 30, "cv": 0.0}})
    assert summary.abandoned == 2, summary
    heard = [json.loads(line) for line in out.splitlines()]
    kinds = {"devices.missing", "devices.unavailable", "experiment.abandoned", "campaign.summary"}
    journalled = [(e["kind"], e["t_lab"], e["experiment"]) for e in read_events(db) if e["kind"] in kinds]
    assert {k for k, _, _ in journalled} == kinds
    assert [(h["what"], h["t_lab"], h["experiment"]) for h in heard] == journalled
    ours = {json.loads(e["detail"])["campaign"] for e in read_events(db) if e["kind"] == "msg.result"}
    assert len(ours) == 1 and {h["campaign"] for h in heard} == ours  # the campaign its devices' messages name


def test_the_documented_device_keeps_each_runs_time_when_its_lab_runs_again(tmp_path):
    """A device started before its lab, and the lab run twice: each run's first clock anchor went out before the
    device was linked to it, so until the next (5 s of wall time later) the device refused work for want of a clock
    (first run) or stamped it in the last run's time (second). It now asks when the lab's campaign comes."""
    port = free_port()
    raw = qd_lab(**{"lab": f"wire{port}", "clock": {"mode": "scaled", "speed": SPEED},
                    "bus": {"kind": "zenoh", "listen": [f"tcp/127.0.0.1:{port}"]}, "orchestrator.startup_s": 3000,
                    "campaign.budget": 2, "devices.spectrometer.instances": 1,
                    "devices.spectrometer.duration": {"mean_s": 50, "cv": 0.0},
                    "devices.synthesiser.duration": {"mean_s": 30, "cv": 0.0}})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    (tmp_path / "device.py").write_text(documented("device.py"))
    s = prepare(path)
    proc = subprocess.Popen([sys.executable, "device.py", s.lab, "spectrometer", f"tcp/127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        for run in ("first", "second"):
            clock = make_clock(s)
            summary = clock.run(run_async(s, clock, tmp_path / f"{run}.db", {"spectrometer"}))
            assert summary.done == 2, (run, summary)
            said = [e for e in read_events(tmp_path / f"{run}.db")
                    if e["kind"].startswith("msg.") and e["device"] == "spectrometer"]
            assert said and all(abs(json.loads(e["detail"])["t_lab"] - e["t_lab"]) < 0.2 * SPEED for e in said), \
                (run, [(json.loads(e["detail"])["t_lab"], e["t_lab"]) for e in said])
    finally:
        proc.terminate()
        proc.communicate(timeout=30)


@pytest.mark.parametrize("script, args", [("device.py", ["spectrometer"]), ("agent.py", []), ("monitor.py", [])])
def test_a_sigterm_as_the_documented_programs_declare_ends_them(tmp_path, script, args):
    """Their SIGTERM handler raises; it was set before the declarations and the `try` came after them, so a SIGTERM
    while they declared (a lab that ended as the monitor joined, in CI) escaped the `try` and left the Zenoh session
    open — the program died of the interrupt, or, with a callback declared already, hung (the monitor did not end
    within 30 s). Here the SIGTERM comes just before the first declaration."""
    text = documented(script)
    after = text.index("signal.signal(signal.SIGTERM, stop)")
    first = re.compile(r"^( *)\w+ = session\.(declare_|liveliness)", re.M).search(text, after)  # its first declaration
    assert first, text
    text = text[:first.start()] + f"{first.group(1)}signal.raise_signal(signal.SIGTERM)\n" + text[first.start():]
    (tmp_path / script).write_text(text)
    done = subprocess.run([sys.executable, script, "nolab", *args, f"tcp/127.0.0.1:{free_port()}"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
