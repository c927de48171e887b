"""A device actor in its own OS process, killed with SIGKILL mid-task: loss is seen, work moves on."""

import asyncio
import logging
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from tests.twin.shared_labs import lines_until
from twin.campaign.journal_read import read_events
from twin.runtime.lab import make_clock, prepare, run_async
from twin.scenario import parse

pytestmark = pytest.mark.process
ROOT = Path(__file__).resolve().parents[2]
SPEED = 200.0  # lab seconds per wall second


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_sigkilled_device_process_is_detected_and_its_work_moves(tmp_path, caplog):
    port = free_port()
    raw = qd_lab(**{
        "campaign.budget": 6,
        "devices.spectrometer.duration": {"mean_s": 200, "cv": 0.0},
        "devices.synthesiser.duration": {"mean_s": 20, "cv": 0.0},
        "clock": {"mode": "scaled", "speed": SPEED},
        "bus": {"kind": "zenoh", "listen": [f"tcp/127.0.0.1:{port}"]},
        "orchestrator.startup_s": 2000,
    })
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    s = prepare(path)
    clock = make_clock(s)
    db = tmp_path / "j.db"
    device = subprocess.Popen(
        [sys.executable, "-m", "twin", "device", "serve", str(path), "--id", "spectrometer-2",
         "--connect", f"tcp/127.0.0.1:{port}", "--clock", "scaled", "--speed", str(SPEED)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT,
    )
    killed = {}

    async def main():
        captured = {}

        def on_progress(orch):
            captured["orch"] = orch

        campaign = asyncio.ensure_future(run_async(s, clock, db, {"spectrometer-2"}, on_progress))
        while "t" not in killed and not campaign.done():
            orch = captured.get("orch")
            if orch and orch.devices["spectrometer-2"].attempt and orch.devices["spectrometer-2"].attempt.t_accepted:
                killed["t"] = clock.now()
                killed["task"] = orch.devices["spectrometer-2"].attempt.task.id
                os.kill(device.pid, signal.SIGKILL)
            await clock.sleep(1)
        return await campaign

    try:
        with caplog.at_level(logging.WARNING, logger="twin.alerts"):
            summary = clock.run(main())
    finally:
        device.kill()
        device.wait()
    assert "t" in killed, "the remote spectrometer never got a step"
    said = [r.getMessage() for r in caplog.records if r.name == "twin.alerts"]  # a person may have one to restart
    assert any(m.startswith("device.lost spectrometer-2: left the bus") and "twin device serve" in m
               for m in said), said
    events = read_events(db)
    lost = [e for e in events if e["kind"] == "device.lost" and e["device"] == "spectrometer-2"]
    assert lost, "the kill must be seen through liveliness"
    assert lost[0]["t_lab"] - killed["t"] < 0.05 * SPEED + 1  # within 50 ms of wall time
    failed = [e for e in events if e["kind"] == "attempt.failed" and e["task"] == killed["task"]]
    assert '"device_lost"' in failed[0]["detail"]
    redone = [e for e in events if e["kind"] == "attempt.done" and e["task"] == killed["task"]]
    assert redone and redone[0]["device"] == "spectrometer-1"
    assert summary.done == 6 and summary.devices_lost >= 1


def test_virtual_clock_refuses_devices_in_other_processes(tmp_path):
    from twin.core.clock import LabClock
    from twin.core.errors import ClockError

    s = parse(qd_lab())
    clock = LabClock("virtual")
    with pytest.raises(ClockError, match="--clock scaled"):
        clock.run(run_async(s, clock, tmp_path / "j.db", {"spectrometer-2"}))


def test_a_device_started_before_its_lab_waits_for_it_with_wait_and_says_how_when_nothing_answers(tmp_path, caplog):
    port = free_port()
    raw = qd_lab(**{"campaign.budget": 4, "clock": {"mode": "scaled", "speed": SPEED},
                    "devices.spectrometer.duration": {"mean_s": 200, "cv": 0.0},  # both spectrometers needed
                    "devices.synthesiser.duration": {"mean_s": 20, "cv": 0.0},
                    "bus": {"kind": "zenoh", "listen": [f"tcp/127.0.0.1:{port}"]}, "orchestrator.startup_s": 2000})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    serve = [sys.executable, "-m", "twin", "device", "serve", str(path), "--id", "spectrometer-2",
             "--connect", f"tcp/127.0.0.1:{port}"]
    # nothing there: the device gives up after --wait and says how to wait longer
    alone = subprocess.run(serve + ["--wait", "1"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert alone.returncode == 2
    assert "waiting up to 1 s" in alone.stderr and "within 1 s" in alone.stderr, alone.stderr
    assert "--wait SECONDS waits longer" in alone.stderr
    # started first, with time to wait: it joins the lab that comes after it and takes its share of the work
    device = subprocess.Popen(serve + ["--wait", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              cwd=ROOT)
    try:
        assert "connecting to" in device.stderr.readline()  # from now on it is waiting for the lab
        s = prepare(path)
        clock = make_clock(s)
        summary = clock.run(run_async(s, clock, tmp_path / "j.db", {"spectrometer-2"}))
        # the lab ended: the device says so, and that it serves on for a resume (it said nothing, and served on)
        said = lines_until(device.stderr, {"left the bus"}, 30)
        assert "lab t's campaign is on the bus" in "".join(said)
        assert "`twin resume` brings it back); serving on until Ctrl-C" in said[-1], said
        # the lab runs again, its time from 0: the device keeps it from the start (it kept the last run's time until
        # the lab's next publication, 5 s of wall time on, and stamped this run's work thousands of lab-s off)
        caplog.clear()
        clock = make_clock(s)
        again = clock.run(run_async(s, clock, tmp_path / "k.db", {"spectrometer-2"}))
        assert again.done == 4 and "off the lab's time" not in caplog.text, caplog.text
        assert any("moved -" in line for line in lines_until(device.stderr, {"moved -"}, 30))
    finally:
        device.send_signal(signal.SIGTERM)
        device.wait(timeout=30)
    done = [e for e in read_events(tmp_path / "j.db") if e["kind"] == "attempt.done"]
    assert summary.done == 4 and any(e["device"] == "spectrometer-2" for e in done)
