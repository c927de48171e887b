"""A lab spread over processes through a `twin router`: kill one device, freeze another, restart the first."""

import asyncio
import csv
import json
import os
import signal
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
SPEED = 200.0
LEASE_S = 1.0


def start(args: list[str], ready: str | None) -> subprocess.Popen:
    """Start ``twin ARGS``; wait for its ``ready`` line unless None (never inside the running lab's loop)."""
    proc = subprocess.Popen([sys.executable, "-m", "twin", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    if ready is not None:
        line = proc.stdout.readline().decode()
        assert line.startswith(ready), line + proc.stderr.read().decode()
    return proc


def test_kill_freeze_restart_through_the_router(tmp_path):
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    raw = qd_lab(**{
        "campaign.budget": 10, "campaign.max_in_flight": 2,
        "devices.synthesiser.duration": {"mean_s": 20, "cv": 0.0},
        "devices.spectrometer.duration": {"mean_s": 200, "cv": 0.0},
        "clock": {"mode": "scaled", "speed": SPEED},
        "bus": {"kind": "zenoh", "listen": [], "connect": [router], "lease_ms": int(LEASE_S * 1000)},
        "orchestrator.startup_s": 4000,
    })
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    s = prepare(path)
    clock, db = make_clock(s), tmp_path / "j.db"

    def device(name: str, wait: bool = True) -> subprocess.Popen:
        return start(["device", "serve", str(path), "--id", name, "--connect", router, "--clock", "scaled",
                      "--speed", str(SPEED)], f"ready {name}" if wait else None)

    procs = {"router": start(["router", "--listen", router], "router")}
    procs["spec1"], procs["spec2"] = device("spectrometer-1"), device("spectrometer-2")
    marks: dict = {}

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, db, {"spectrometer-1", "spectrometer-2"},
                                                   on_start=lambda o: marks.setdefault("orch", o.core)))

        def running_on(name):
            orch = marks.get("orch")
            att = orch.devices[name].attempt if orch else None
            return att.task.id if att is not None and att.t_accepted is not None else None

        while not campaign.done():
            if "killed" not in marks and running_on("spectrometer-1"):
                marks["killed"] = (clock.now(), running_on("spectrometer-1"))
                os.kill(procs["spec1"].pid, signal.SIGKILL)
                procs["spec1"].wait()
                procs["spec1"] = device("spectrometer-1", wait=False)  # restarted: it must rejoin and get work
                marks["restarted"] = clock.now()
            elif "killed" in marks and "frozen" not in marks and running_on("spectrometer-2"):
                marks["frozen"] = (clock.now(), running_on("spectrometer-2"))
                os.kill(procs["spec2"].pid, signal.SIGSTOP)
            await clock.sleep(2)
        return await campaign

    try:
        summary = clock.run(main())
    finally:
        for p in procs.values():
            p.send_signal(signal.SIGCONT)
            p.kill()
            p.wait()
    assert "killed" in marks and "frozen" in marks
    events = read_events(db)

    def first(kind, device, after):
        return next(e for e in events if e["kind"] == kind and e["device"] == device and e["t_lab"] >= after)

    t_kill, killed_task = marks["killed"]
    assert first("device.lost", "spectrometer-1", t_kill)["t_lab"] - t_kill < 0.5 * SPEED
    t_freeze, frozen_task = marks["frozen"]
    detected = first("device.lost", "spectrometer-2", t_freeze)["t_lab"] - t_freeze
    assert detected < 2.5 * LEASE_S * SPEED, f"the frozen device was seen after {detected / SPEED:.2f} s wall"
    rejoined = first("device.online", "spectrometer-1", marks["restarted"] - 1)
    after_restart = [e for e in events if e["kind"] == "attempt.done" and e["device"] == "spectrometer-1"
                     and e["t_lab"] > rejoined["t_lab"]]
    assert after_restart, "the restarted device never got work"
    for task in (killed_task, frozen_task):
        assert any(e["kind"] == "attempt.done" and e["task"] == task for e in events), f"{task} was never redone"
    assert summary.done == 10 and summary.abandoned == 0 and summary.devices_lost >= 2


def test_twin_device_health_asks_the_devices_of_a_running_lab(tmp_path):
    router = f"tcp/127.0.0.1:{free_port()}"
    raw = qd_lab(**{"bus": {"kind": "zenoh", "listen": [], "connect": [router]}})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    procs = [start(["router", "--listen", router], "router")]
    procs.append(start(["device", "serve", str(path), "--id", "spectrometer-2", "--connect", router,
                        "--clock", "scaled", "--speed", "100"], "ready spectrometer-2"))
    env = {**os.environ, "COLUMNS": "80"}
    try:
        ask = [sys.executable, "-m", "twin", "device", "health", str(path), "--connect", router]
        up = subprocess.run([*ask, "--id", "spectrometer-2"], capture_output=True, text=True, cwd=ROOT, env=env,
                            timeout=60)
        both = subprocess.run([*ask, "--id", "spectrometer-2", "--id", "spectrometer-1"], capture_output=True,
                              text=True, cwd=ROOT, env=env, timeout=60)
        listed = subprocess.run([sys.executable, "-m", "twin", "devices", "--connect", router, "--lab", "t"],
                                capture_output=True, text=True, cwd=ROOT, env=env, timeout=60)
        other = subprocess.run([sys.executable, "-m", "twin", "devices", "--connect", router, "--lab", "elsewhere"],
                               capture_output=True, text=True, cwd=ROOT, env=env, timeout=60)
        # for a monitor: --json had been ignored with --connect (a table came out), and `device health` had none
        as_json = subprocess.run([*ask, "--id", "spectrometer-2", "--id", "spectrometer-1", "--json"],
                                 capture_output=True, text=True, cwd=ROOT, env=env, timeout=60)
        as_csv = subprocess.run([sys.executable, "-m", "twin", "devices", "--connect", router, "--lab", "t", "--json",
                                 "--csv", str(tmp_path / "d.csv")], capture_output=True, text=True, cwd=ROOT, env=env,
                                timeout=60)
    finally:
        for p in procs:
            p.terminate()
            p.wait()
    assert up.returncode == 0, up.stderr
    row = next(line for line in up.stdout.splitlines() if "spectrometer-2" in line)
    assert "yes" in row and "idle" in row
    assert both.returncode == 1
    assert any("spectrometer-1" in line and "no" in line for line in both.stdout.splitlines())
    # the lab's bus, without the scenario: only the device that is there, found by its presence
    assert listed.returncode == 0, listed.stderr
    rows = [line for line in listed.stdout.splitlines() if "spectrometer" in line]
    assert len(rows) == 1 and "spectrometer-2" in rows[0] and "yes" in rows[0] and "idle" in rows[0]
    assert other.returncode == 1 and "no device of lab 'elsewhere'" in other.stdout
    assert "(labs on it now: t)" in " ".join(other.stdout.split()), other.stdout  # what a mistyped name meant
    assert as_json.returncode == 1, as_json.stderr  # one did not answer
    reports = {d["device"]: d for d in json.loads(as_json.stdout)["devices"]}
    assert reports["spectrometer-1"] == {"device": "spectrometer-1", "answered": False, "report": None}
    assert reports["spectrometer-2"]["answered"] and reports["spectrometer-2"]["report"]["running"] is None
    assert as_csv.returncode == 0, as_csv.stderr
    assert [d["device"] for d in json.loads(as_csv.stdout)["devices"]] == ["spectrometer-2"]
    with open(tmp_path / "d.csv") as f:
        (row,) = list(csv.DictReader(f))
    assert row["device"] == "spectrometer-2" and row["answered"] == "True" and row["running"] == ""
