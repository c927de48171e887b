"""A second process that would serve a lab already on the router — its campaign, one of its devices, its
scheduler agent — is refused naming what holds it, and the lab that was there first loses nothing; so is one of
two started at the same moment; a watcher of a lab that is not there names the labs that are."""

import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from tests.twin.test_device_process import free_port
from tests.twin.test_distributed_lab import start
from twin.runtime.assembly import make_bus
from twin.runtime.lab import make_clock, prepare, run_async
from twin.runtime.lab_claim import Claims, LabTaken, refuse_if_taken

pytestmark = pytest.mark.process
ROOT = Path(__file__).resolve().parents[2]
SPEED = 200.0


def _lab(tmp_path: Path, router: str) -> Path:
    raw = qd_lab(**{
        "campaign.budget": 4, "campaign.max_in_flight": 2,
        "devices.synthesiser.duration": {"mean_s": 20, "cv": 0.0},
        # long enough that the first campaign is still measuring while the second process starts
        "devices.spectrometer.duration": {"mean_s": 4000, "cv": 0.0},
        "clock": {"mode": "scaled", "speed": SPEED},
        "bus": {"kind": "zenoh", "listen": [], "connect": [router], "lease_ms": 1000},
    })
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def _twin(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "twin", *args], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "COLUMNS": "300"}, timeout=120)


def _watch_first_lines(router: str, lab: str, save: Path) -> tuple[list[str], float]:
    """The first two lines `twin watch --lab LAB` prints, and the wall seconds it took to stop when told to
    (SIGTERM) while it still waited for the lab."""
    watcher = subprocess.Popen([sys.executable, "-m", "twin", "watch", "--lab", lab, "--connect", router, "--save",
                                str(save)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        lines = [watcher.stdout.readline(), watcher.stdout.readline()]
        told = time.monotonic()
        watcher.terminate()
        watcher.wait(timeout=60)
        return lines, time.monotonic() - told
    finally:
        watcher.kill()


def test_a_second_campaign_or_device_of_a_lab_on_the_bus_is_refused_and_the_first_loses_nothing(tmp_path):
    router = f"tcp/127.0.0.1:{free_port()}"
    path = _lab(tmp_path, router)
    procs = [start(["router", "--listen", router], "router")]
    procs.append(start(["device", "serve", str(path), "--id", "spectrometer-1", "--connect", router, "--clock",
                        "scaled", "--speed", str(SPEED)], "ready spectrometer-1"))
    s = prepare(path)
    seen: dict = {}
    try:
        # the same device served twice, and a second scheduler agent
        again = _twin("device", "serve", str(path), "--id", "spectrometer-1", "--connect", router,
                      "--clock", "scaled", "--speed", str(SPEED))
        procs.append(start(["scheduler", "serve", str(path), "--scheduler", "spt", "--connect", router, "--clock",
                            "scaled", "--speed", str(SPEED)], "ready scheduler"))
        agent = _twin("scheduler", "serve", str(path), "--scheduler", "fifo", "--connect", router, "--clock",
                      "scaled", "--speed", str(SPEED))
        # a campaign that would serve spectrometer-1 itself, while another process does
        clock = make_clock(s)
        with pytest.raises(LabTaken, match="device spectrometer-1 of lab 't' is already on this bus"):
            clock.run(run_async(s, clock, tmp_path / "own.db"))

        # the lab's campaign, using that device; a second campaign of the lab started while it runs
        clock = make_clock(s)

        async def second(camp) -> None:
            seen["second"] = await asyncio.to_thread(_twin, "run", str(path), "--journal", str(tmp_path / "b.db"),
                                                     "--external", "spectrometer-1")
            seen["watch"] = await asyncio.to_thread(_watch_first_lines, router, "tt", tmp_path / "w.rrd")  # a lab name mistyped
            camp.stop("the second campaign was turned away")

        def started(camp) -> None:
            seen["task"] = asyncio.ensure_future(second(camp))

        summary = clock.run(run_async(s, clock, tmp_path / "a.db", {"spectrometer-1"}, on_start=started))
    finally:
        for p in procs:
            p.terminate()
            p.wait()
    assert again.returncode == 2, again.stdout + again.stderr
    assert "device spectrometer-1 of lab 't' is already on this bus, served by another process: stop that " \
           "one first" in " ".join(again.stderr.split())
    assert agent.returncode == 2 and "lab 't' already has a scheduler agent on this bus" in agent.stderr, agent.stderr
    refused = seen["second"]
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert "lab 't' already has a campaign running on this bus" in refused.stderr and "--set lab=t-2" in refused.stderr
    assert not (tmp_path / "b.db").exists()
    lines, stopping_s = seen["watch"]
    assert lines == ["watching lab 'tt'\n", "no campaign of lab 'tt' is on this bus yet (labs on it now: t): "
                     "waiting for one (Ctrl-C to stop)\n"]
    assert stopping_s < 15, stopping_s  # it went on asking for the history for 30 s after SIGTERM
    # the first campaign saw nothing of the second: no foreign message, no attempt lost to it
    assert summary.rejected_messages == 0 and summary.failed_attempts == 0 and summary.abandoned == 0


async def test_of_processes_taking_a_lab_at_the_same_moment_one_goes_ahead_and_a_later_one_waits_for_it(tmp_path):
    router = f"tcp/127.0.0.1:{free_port()}"
    s = prepare(_lab(tmp_path, router))
    proc = start(["router", "--listen", router], "router")
    buses = [make_bus(s, make_clock(s)) for _ in range(5)]
    try:
        for bus in buses:
            await bus.start()
        # three campaigns of lab t at once (none holds the lab's token yet: they are all about to take it)
        got = await asyncio.gather(*(refuse_if_taken(bus, s, []) for bus in buses[:3]), return_exceptions=True)
        ahead = [g for g in got if isinstance(g, Claims)]
        assert len(ahead) == 1, got
        for g in got:
            if g is not ahead[0]:
                assert isinstance(g, LabTaken), g
                assert "lab 't': another process is starting its campaign on this bus at this same moment" in str(g)
                assert "--set lab=t-2" in str(g)
        # one that comes while the first is still starting is refused too, and one after it has gone is not
        with pytest.raises(LabTaken, match="another process is starting its campaign"):
            await refuse_if_taken(buses[3], s, [])
        ahead[0].close()
        await asyncio.sleep(0.5)  # the claim's undeclaration reaches the router (no lease: it was closed)
        (await refuse_if_taken(buses[3], s, [])).close()
        # a device served twice at once: one of the two serves it
        got = await asyncio.gather(*(refuse_if_taken(bus, s, ["spectrometer-1"], orchestrator=False)
                                     for bus in buses[3:]), return_exceptions=True)
        assert sorted(type(g).__name__ for g in got) == ["Claims", "LabTaken"], got
        assert "another process is starting device spectrometer-1" in \
            str(next(g for g in got if isinstance(g, LabTaken)))
    finally:
        for bus in buses:
            await bus.close()
        proc.terminate()
        proc.wait()


def test_two_runs_of_one_lab_started_together_one_runs_and_loses_nothing(tmp_path):
    router = f"tcp/127.0.0.1:{free_port()}"
    raw = yaml.safe_load(_lab(tmp_path, router).read_text())
    raw["devices"]["spectrometer"]["duration"] = {"mean_s": 200, "cv": 0.0}
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    procs = [start(["router", "--listen", router], "router")]
    try:
        runs = [subprocess.Popen([sys.executable, "-m", "twin", "run", str(path), "--json", "-q", "--journal",
                                  str(tmp_path / f"{k}.db")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True, cwd=ROOT) for k in range(2)]
        procs += runs
        outs = [r.communicate(timeout=120) for r in runs]
    finally:
        for p in procs:
            p.terminate()
            p.wait()
    (ran, _), (_, refused) = (outs[k] for k in sorted(range(2), key=lambda k: runs[k].returncode))
    assert sorted(r.returncode for r in runs) == [0, 2], outs
    summary = json.loads(ran)
    assert summary["done"] == 4 and summary["rejected_messages"] == 0 and summary["abandoned"] == 0, summary
    assert "lab 't'" in refused and ("at this same moment" in refused or "already has a campaign" in refused), refused
