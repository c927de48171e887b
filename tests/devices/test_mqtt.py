"""The MQTT adapter against a real mosquitto and real instrument processes (examples/mqtt_instrument.py)."""

import asyncio
import os
import signal
import socket
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from tests.conftest import qd_lab
from twin.core.errors import ClockError
from twin.campaign.journal_read import read_events
from twin.runtime.lab import make_clock, prepare, run, run_async
from twin.scenario import parse

pytestmark = pytest.mark.process
ROOT = Path(__file__).resolve().parents[2]
SPEED = 100.0


def mqtt_lab(broker: str, prefix: str, **changes) -> dict:
    return qd_lab(**{
        "devices.spectrometer": {"driver": "mqtt", "instances": 2, "steps": ["measure"],
                                 "duration": {"mean_s": 60, "cv": 0},
                                 "options": {"broker": broker, "topic": f"{prefix}/{{name}}", "steps": ["measure"]}},
        "clock": {"mode": "scaled", "speed": SPEED}, "orchestrator.startup_s": 1000, **changes,
    })


def instrument(broker: str, topic: str, seconds: float = 0.3, cancel_seconds: float = 0.0) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "examples/mqtt_instrument.py", "--broker", broker, "--topic", topic,
                             "--seconds", str(seconds), "--cancel-seconds", str(cancel_seconds)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    assert proc.stdout.readline().decode().startswith("ready"), proc.stderr.read().decode()
    return proc


@pytest.fixture
def prefix():
    return f"test/{uuid.uuid4().hex[:8]}"  # topics unique to each test


def test_a_campaign_measures_through_mqtt_instruments(mosquitto, prefix, tmp_path):
    procs = [instrument(mosquitto, f"{prefix}/spectrometer-{i}") for i in (1, 2)]
    try:
        s = run(parse(mqtt_lab(mosquitto, prefix, **{"campaign.budget": 4})), journal=tmp_path / "j.db")
    finally:
        for p in procs:
            p.terminate()
            p.wait()
    assert s.done == 4 and s.failed_attempts == 0
    results = [e for e in read_events(tmp_path / "j.db") if e["kind"] == "experiment.done"]
    assert all('"peak_nm"' in e["detail"] and '"fwhm_nm"' in e["detail"] for e in results)


def test_a_killed_instrument_leaves_the_bus_by_its_last_will_and_its_work_moves(mosquitto, prefix, tmp_path):
    procs = {i: instrument(mosquitto, f"{prefix}/spectrometer-{i}", seconds=1.0) for i in (1, 2)}
    s = prepare(parse(mqtt_lab(mosquitto, prefix, **{"campaign.budget": 4, "campaign.max_in_flight": 1})))
    clock, db, seen = make_clock(s), tmp_path / "j.db", {}

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, db, on_start=lambda o: seen.setdefault("orch", o.core)))
        while "task" not in seen and not campaign.done():
            dev = seen["orch"].devices["spectrometer-1"] if "orch" in seen else None
            if dev is not None and dev.attempt is not None and dev.attempt.t_accepted is not None:
                seen["task"], seen["t"] = dev.attempt.task.id, clock.now()
                os.kill(procs[1].pid, signal.SIGKILL)
            await clock.sleep(1)
        return await campaign

    try:
        summary = clock.run(main())
    finally:
        for p in procs.values():
            p.kill()
            p.wait()
    assert "task" in seen, "spectrometer-1 never got a step"
    events = read_events(db)
    lost = [e for e in events if e["kind"] == "device.lost" and e["device"] == "spectrometer-1"]
    assert lost and lost[0]["t_lab"] - seen["t"] < 2.0 * SPEED  # the broker published the will at once
    redone = [e for e in events if e["kind"] == "attempt.done" and e["task"] == seen["task"]]
    assert redone and redone[0]["device"] == "spectrometer-2"
    assert summary.done == 4 and summary.devices_lost >= 1


def test_an_instrument_killed_mid_step_and_started_again_takes_work_at_once(mosquitto, prefix, tmp_path):
    """The adapter kept waiting for the dead instrument's answer: back on the bus, the device refused every step as
    "busy with" the lost one until a cancel nobody answered had waited out its 10 s of wall time."""
    topic = f"{prefix}/spectrometer"  # the one instance is named after its type
    procs = [instrument(mosquitto, topic, seconds=0.4)]
    lab = mqtt_lab(mosquitto, prefix, **{"campaign.budget": 3, "campaign.max_in_flight": 1})
    lab["devices"]["spectrometer"]["instances"] = 1
    s = prepare(parse(lab))
    clock, db, seen = make_clock(s), tmp_path / "j.db", {}

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, db, on_start=lambda o: seen.setdefault("orch", o.core)))
        while not campaign.done():
            dev = seen["orch"].devices["spectrometer"] if "orch" in seen else None
            if "killed" not in seen and dev is not None and dev.attempt is not None and dev.attempt.t_accepted:
                os.kill(procs[0].pid, signal.SIGKILL)
                seen["killed"] = clock.now()
            elif "killed" in seen and "again" not in seen and dev is not None and not dev.online:
                procs.append(await asyncio.to_thread(instrument, mosquitto, topic, 0.4))
                seen["again"] = clock.now()
            await clock.sleep(1)
        return await campaign

    try:
        summary = clock.run(main())
    finally:
        for p in procs:
            p.kill()
            p.wait()
    assert "again" in seen, "the instrument was never killed and started again"
    events = read_events(db)
    busy = [e for e in events if e["kind"] == "attempt.failed" and "busy with" in (e["detail"] or "")]
    assert busy == [] and summary.done == 3 and summary.devices_lost == 1, busy[:2]


def test_an_instrument_error_is_a_fault_with_its_reason_and_nothing_is_lost(mosquitto, prefix, tmp_path):
    procs = [instrument(mosquitto, f"{prefix}/spectrometer-{i}", seconds=0.05) for i in (1, 2)]
    lab = mqtt_lab(mosquitto, prefix, **{"campaign.budget": 2, "workflow": [{"step": "measure", "device": "spectrometer"}]})
    try:
        s = run(parse(lab), journal=tmp_path / "j.db")
    finally:
        for p in procs:
            p.terminate()
            p.wait()
    assert s.abandoned == 2 and s.done == 0
    faults = [e for e in read_events(tmp_path / "j.db") if e["kind"] == "attempt.failed"]
    assert faults and all("reported: nothing to measure" in e["detail"] for e in faults)


def test_a_virtual_clock_is_refused_for_real_instruments(mosquitto, prefix, tmp_path):
    with pytest.raises(ClockError, match="--clock scaled"):
        run(parse(mqtt_lab(mosquitto, prefix, clock={"mode": "virtual"})), journal=tmp_path / "j.db")


def test_the_adapter_comes_back_with_its_broker_and_nothing_is_lost(tmp_path, prefix):
    """A broker restarted (an upgrade, a reboot) took every instrument behind it off the lab for good: the adapter
    never connected again, and the campaign gave up on their steps. It now tries every second, as the example
    instrument does, and the instruments are back as soon as they say so on the broker that came back."""
    import time

    from tests.conftest import start_mosquitto

    proc, port = start_mosquitto(tmp_path, "allow_anonymous true\n")
    broker = f"127.0.0.1:{port}"
    procs = [instrument(broker, f"{prefix}/spectrometer-{i}") for i in (1, 2)]
    s = prepare(parse(mqtt_lab(broker, prefix, **{"campaign.budget": 6})))
    clock, db, seen = make_clock(s), tmp_path / "j.db", {}

    def restart_broker() -> None:
        nonlocal proc
        proc = subprocess.Popen(proc.args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)  # as it first started
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                assert proc.poll() is None and time.monotonic() < deadline, "mosquitto did not start again"
                time.sleep(0.05)

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, db, on_start=lambda o: seen.setdefault("core", o.core)))
        while not campaign.done() and not ("core" in seen and any(e.status == "done" for e in seen["core"].experiments)):
            await clock.sleep(10)
        seen["down"] = clock.now()
        proc.terminate()  # the broker goes (persistence off: its retained statuses with it)
        await asyncio.to_thread(proc.wait)
        await clock.sleep(300)  # five lab-minutes without a broker
        await asyncio.to_thread(restart_broker)  # on the same port; adapters and instruments connect again
        return await campaign

    try:
        summary = clock.run(main())
    finally:
        proc.terminate()
        for p in procs:
            p.kill()
            p.wait()
        proc.wait()
    events = read_events(db)
    for name in ("spectrometer-1", "spectrometer-2"):
        lost = [e["t_lab"] for e in events if e["kind"] == "device.lost" and e["device"] == name]
        back = [e["t_lab"] for e in events if e["kind"] == "device.online" and e["device"] == name]
        assert lost and lost[0] >= seen["down"] and back and back[-1] > lost[0] + 300, name
    assert summary.done == 6 and summary.abandoned == 0
    assert any(e["kind"] == "attempt.done" and e["device"].startswith("spectrometer") and e["t_lab"] > seen["down"]
               + 300 for e in events)


def test_the_brokers_patience_is_wall_seconds_however_fast_the_lab_clock_runs(mosquitto, prefix):
    """aiomqtt times a connect and its subscriptions on the running loop, whose time is lab time: at these tests'
    100× the 10 s of connect_timeout_s were 0.1 s of wall time, and a busy machine's broker missed them (a CI run
    failed so); at 10⁶× no broker can answer in time."""
    from twin.runtime.assembly import load_driver

    async def connected(driver) -> None:
        await driver.connect(lambda present: None)
        await driver.disconnect()

    s = parse(mqtt_lab(mosquitto, prefix, **{"clock.speed": 1e6}))
    make_clock(s).run(connected(load_driver(s, "spectrometer", "spectrometer-1")))
