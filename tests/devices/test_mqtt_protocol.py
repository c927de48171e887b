"""docs/mqtt.md, held to: presence that a clean exit cannot fake, broken results that fail the step at once,
and a slow instrument whose cancel is waited for (a real mosquitto, real instrument processes)."""

import asyncio
import json
import time

import aiomqtt
import pytest

from tests.devices.test_mqtt import SPEED, instrument, mqtt_lab, prefix  # noqa: F401 (a fixture)
from twin.campaign.journal_read import read_events
from twin.core.clock import wall_on_loop
from twin.runtime.assembly import load_driver
from twin.runtime.lab import make_clock, prepare, run_async
from twin.scenario import parse

pytestmark = pytest.mark.process


def _client(host: str, port: str) -> aiomqtt.Client:
    """A fake instrument's session. Those here run on the lab's loop, whose time is lab time: aiomqtt's own 10 s
    for a publish was 0.1 s of wall time at 100×, and on a loaded machine the fake died of it mid-campaign (its
    commands unanswered, a cancel never acknowledged; CI failed so once)."""
    return aiomqtt.Client(host, int(port), timeout=wall_on_loop(10.0))


async def _retained(broker: str, topic: str) -> str:
    host, _, port = broker.rpartition(":")
    async with _client(host, port) as c:
        await c.subscribe(topic, qos=1)
        async with asyncio.timeout(5):
            async for m in c.messages:
                return m.payload.decode()


async def _adapter(mosquitto: str, prefix: str):
    """The adapter of spectrometer-1, connected; and the presence it has reported, in order."""
    driver = load_driver(parse(mqtt_lab(mosquitto, prefix)), "spectrometer", "spectrometer-1")
    seen: list[bool] = []
    await driver.connect(seen.append)
    return driver, seen


async def _until(done, seconds: float = 10.0) -> None:
    """Wait (wall time: the instrument keeps it) until ``done()``, at most ``seconds``."""
    t0 = time.monotonic()
    while not done() and time.monotonic() - t0 < seconds:
        await asyncio.sleep(0.05)


def test_a_clean_exit_says_offline_and_a_stale_online_is_not_trusted_until_a_ping_is_answered(mosquitto, prefix):
    topic = f"{prefix}/spectrometer-1"
    proc = instrument(mosquitto, topic)
    proc.terminate()  # a clean exit: no last will
    proc.wait()
    assert asyncio.run(_retained(mosquitto, f"{topic}/status")) == "offline"

    async def stale_then_live():
        host, _, port = mosquitto.rpartition(":")
        async with _client(host, port) as c:  # a dead instrument's "online", left retained
            await c.publish(f"{topic}/status", "online", qos=1, retain=True)
        driver, seen = await _adapter(mosquitto, prefix)
        try:
            await asyncio.sleep(3.0)  # the adapter pings twice; nobody answers
            stale = (list(seen), (await driver.health())["present"])
            live = await asyncio.to_thread(instrument, mosquitto, topic)
            await _until(lambda: True in seen)
            return stale, list(seen), live
        finally:
            await driver.disconnect()

    stale, after, live = asyncio.run(stale_then_live())
    live.terminate()
    live.wait()
    assert stale == ([], None)  # neither present nor lost: unknown
    assert after == [True]


def _hostile_lab(mosquitto: str, prefix: str):
    return prepare(parse(mqtt_lab(mosquitto, prefix, **{
        "devices.spectrometer.instances": 1, "campaign.budget": 2, "campaign.max_in_flight": 1,
        "orchestrator.retry": {"max_attempts": 5, "backoff_s": 1, "jitter": 0},
        "orchestrator.quarantine_after": 10, "campaign.give_up_after_s": 600})))


async def _hostile_instrument(broker: str, topic: str, answers: list, ready: asyncio.Event) -> None:
    """Answers its n-th command with ``answers[n](cmd)`` (then properly), as a broken instrument would."""
    host, _, port = broker.rpartition(":")
    async with _client(host, port) as c:
        await c.subscribe(f"{topic}/command", qos=1)
        await c.publish(f"{topic}/status", "online", qos=1, retain=True)
        ready.set()
        n = 0
        async for m in c.messages:
            cmd = json.loads(m.payload)
            if cmd.get("ping"):
                await c.publish(f"{topic}/status", "online", qos=1, retain=True)
            if "step" not in cmd:
                continue
            good = {"id": cmd["id"], "outputs": {"peak_nm": 600.0, "fwhm_nm": 30.0}, "sample": cmd["sample"]}
            reply = answers[n](cmd) if n < len(answers) else json.dumps(good)
            n += 1
            await c.publish(f"{topic}/result", reply, qos=1)


def test_broken_results_fail_the_attempt_at_once_with_what_was_wrong(mosquitto, prefix, tmp_path):
    s = _hostile_lab(mosquitto, prefix)
    answers = [lambda cmd: "this is not json",
               lambda cmd: json.dumps({"id": "made-up", "outputs": {}, "sample": None}),
               lambda cmd: json.dumps({"id": cmd["id"], "outputs": {"peak_nm": 1.0}})]
    clock, db = make_clock(s), tmp_path / "j.db"

    async def main():
        ready = asyncio.Event()
        fake = asyncio.ensure_future(_hostile_instrument(mosquitto, f"{prefix}/spectrometer", answers, ready))
        await ready.wait()
        try:
            return await run_async(s, clock, db)
        finally:
            fake.cancel()

    summary = clock.run(main())
    assert summary.done == 2 and summary.abandoned == 0
    events = read_events(db)
    sent = {(e["task"], e["attempt"]): e["t_lab"] for e in events if e["kind"] == "attempt.dispatched"}
    failed = [e for e in events if e["kind"] == "attempt.failed"]
    reasons = [json.loads(e["detail"])["reason"] for e in failed]
    assert len(failed) == 3, reasons
    assert "not JSON" in reasons[0] and "never issued" in reasons[1] and "hand back \"sample\"" in reasons[2]
    deadline = json.loads(next(e for e in events if e["kind"] == "attempt.dispatched")["detail"])["deadline_s"]
    for e in failed:  # at once: well inside the deadline the attempt would otherwise have waited out
        assert e["t_lab"] - sent[(e["task"], e["attempt"])] < 0.1 * deadline


def test_commands_carry_deadline_expected_duration_and_clock_speed_in_wall_seconds(mosquitto, prefix, tmp_path):
    s = _hostile_lab(mosquitto, prefix)
    seen: list[dict] = []

    def record(cmd):
        seen.append(cmd)
        return json.dumps({"id": cmd["id"], "outputs": {"peak_nm": 600.0}, "sample": cmd["sample"]})

    clock = make_clock(s)

    async def main():
        ready = asyncio.Event()
        fake = asyncio.ensure_future(_hostile_instrument(mosquitto, f"{prefix}/spectrometer", [record], ready))
        await ready.wait()
        try:
            return await run_async(s, clock, tmp_path / "j.db")
        finally:
            fake.cancel()

    assert clock.run(main()).done == 2
    cmd = seen[0]
    o = s.orchestrator
    assert cmd["speed"] == SPEED
    assert cmd["expected_s"] == pytest.approx(60 / SPEED)
    assert cmd["deadline_s"] == pytest.approx((60 * o.timeout_factor + o.timeout_slack_s) / SPEED)
    assert cmd["sample"]["id"].endswith("/e0") and 0 < cmd["t_lab"]


def test_a_slow_instrument_is_given_nothing_until_it_has_acknowledged_the_cancel(mosquitto, prefix, tmp_path):
    # measurements take 3 s of wall time (300 lab-s), far past the 70 lab-s deadline; a cancel takes the instrument 1 s
    # (100 lab-s), longer than the lab's cancel grace (60 lab-s): the lab hears "busy" once, and waits again
    topic = f"{prefix}/spectrometer"
    proc = instrument(mosquitto, topic, seconds=3.0, cancel_seconds=1.0)
    s = prepare(parse(mqtt_lab(mosquitto, prefix, **{
        "devices.spectrometer.instances": 1, "campaign.budget": 2, "campaign.max_in_flight": 2,
        "devices.synthesiser.duration": {"mean_s": 60, "cv": 0},
        "orchestrator.timeout_factor": 1, "orchestrator.timeout_slack_s": 10, "orchestrator.cancel_grace_s": 60,
        "orchestrator.retry": {"max_attempts": 2, "backoff_s": 0, "jitter": 0},
        "orchestrator.quarantine_after": 100})))
    clock, db = make_clock(s), tmp_path / "j.db"
    try:
        summary = clock.run(run_async(s, clock, db))
    finally:
        proc.terminate()
        proc.wait()
    events = read_events(db)
    kinds = [e["kind"] for e in events]
    busy = [e for e in events if e["kind"] == "msg.rejected" and "busy" in e["detail"]]
    failed = [(e["task"], e["attempt"], json.loads(e["detail"])["code"]) for e in events
              if e["kind"] == "attempt.failed"]
    timed_out = [f for f in failed if f[2] == "timed_out"]
    # every experiment had its two attempts, both timed out: a "busy" answer used up none of them
    assert summary.abandoned == 2 and summary.timed_out == 4
    per_step = {}
    for t, n, _ in timed_out:
        per_step.setdefault(t, []).append(n)
    assert {t: len(ns) for t, ns in per_step.items()} == {"e0s1": 2, "e1s1": 2}  # numbered on past "busy" answers
    assert all(len(set(ns)) == len(ns) for ns in per_step.values())
    # the adapter waited for each of the instrument's acknowledgements (the campaign may end before the last)
    assert kinds.count("attempt.cancel_acknowledged") >= 3
    assert len(busy) <= kinds.count("attempt.cancel_unanswered")  # one "busy" per grace overrun, no retry storm
    assert summary.stuck == len(busy)  # each "busy" quarantined it until it answered the cancel


def test_a_late_last_will_does_not_keep_a_live_instrument_off_the_bus(mosquitto, prefix):
    """An instrument back on a new session (another client id) before the broker noticed its old one end: its old
    last will, "offline", comes after its new "online". The device went off the bus for good, with the instrument
    up and waiting for work; the adapter now pings after an "offline", and the instrument's answer brings it back."""
    topic = f"{prefix}/spectrometer-1"
    live = instrument(mosquitto, topic)

    async def late_will():
        driver, seen = await _adapter(mosquitto, prefix)
        try:
            await _until(lambda: seen == [True])
            host, _, port = mosquitto.rpartition(":")
            async with _client(host, port) as c:  # the broker giving out the old session's will
                await c.publish(f"{topic}/status", "offline", qos=1, retain=True)
            await _until(lambda: seen == [True, False, True])
            return list(seen), (await driver.health())["present"]
        finally:
            await driver.disconnect()

    try:
        seen, present = asyncio.run(late_will())
    finally:
        live.terminate()
        live.wait()
    assert seen == [True, False, True] and present is True


def test_an_instrument_not_present_is_said_once_with_the_topic_the_adapter_waits_on(mosquitto, prefix, monkeypatch,
                                                                                   caplog):
    """A lab whose instrument listens on another topic ({name} is "reader" for a type of one instance, not
    "reader-1") waited with the device "not on the bus" and no word of where it looked; now the adapter says, once,
    the topic, the broker and what it last heard there. A present instrument is not warned of."""
    import logging

    import devices.mqtt

    monkeypatch.setattr(devices.mqtt, "SILENT_SAY_AFTER_WALL_S", 0.3)
    live = instrument(mosquitto, f"{prefix}/spectrometer-3")

    async def three():
        host, _, port = mosquitto.rpartition(":")
        async with _client(host, port) as c:  # a dead instrument's "online", left retained
            await c.publish(f"{prefix}/spectrometer-2/status", "online", qos=1, retain=True)
        lab = parse(mqtt_lab(mosquitto, prefix, **{"devices.spectrometer.instances": 3}))
        drivers = [load_driver(lab, "spectrometer", f"spectrometer-{i}") for i in (1, 2, 3)]
        for d in drivers:
            await d.connect(lambda present: None)
        try:
            await _until(lambda: len([r for r in caplog.records if "no instrument present" in r.getMessage()]) == 2)
            await asyncio.sleep(0.5)  # a third would come by now
        finally:
            for d in drivers:
                await d.disconnect()

    try:
        with caplog.at_level(logging.WARNING, logger="devices.mqtt"):
            asyncio.run(three())
    finally:
        live.terminate()
        live.wait()
    said = {r.getMessage().split(":")[0]: r.getMessage() for r in caplog.records
            if "no instrument present" in r.getMessage()}
    assert sorted(said) == ["spectrometer-1", "spectrometer-2"]
    assert f"on {prefix}/spectrometer-1/status at the MQTT broker {mosquitto}" in said["spectrometer-1"]
    assert "nothing has been said there" in said["spectrometer-1"]
    named = f"options.topic '{prefix}/{{name}}'; {{name}} is this device's name, 'spectrometer-1'"
    assert named in said["spectrometer-1"]
    assert "an old retained online, and no ping has been answered" in said["spectrometer-2"]


def test_an_instrument_that_said_online_without_retain_before_the_lab_came_is_found_by_a_ping(mosquitto, prefix):
    """Its one "online" went by before the adapter subscribed, and nothing was retained: the device stayed off the
    bus for the whole campaign. The adapter now pings while it has heard nothing, and the answer brings it in."""
    topic = f"{prefix}/spectrometer-1"
    host, _, port = mosquitto.rpartition(":")

    async def unretained():
        ready, pinged = asyncio.Event(), asyncio.Event()

        async def instrument_without_retain():
            async with _client(host, port) as c:
                await c.subscribe(f"{topic}/command", qos=1)
                await c.publish(f"{topic}/status", "online", qos=1)  # not retained: nobody hears it
                ready.set()
                async for m in c.messages:
                    if json.loads(m.payload).get("ping"):
                        pinged.set()
                        await c.publish(f"{topic}/status", "online", qos=1)

        task = asyncio.ensure_future(instrument_without_retain())
        await ready.wait()
        driver, seen = await _adapter(mosquitto, prefix)
        try:
            await _until(lambda: seen == [True])
            return list(seen), pinged.is_set(), (await driver.health())["present"]
        finally:
            await driver.disconnect()
            task.cancel()

    assert asyncio.run(unretained()) == ([True], True, True)
