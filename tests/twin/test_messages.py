"""A message that fails validation is dropped and logged with its sender and reason; nothing crashes."""

import asyncio
import logging

import pytest

from twin.core import keys
from twin.core.bus import MemoryBus, MemoryHub
from twin.core.clock import LabClock
from twin.campaign.journal import Journal
from twin.campaign.journal_read import read_events
from twin.runtime.lab import build_actors, load_drivers, make_planner, make_scheduler
from twin.core.messages import InvalidMessage, Kind, decode, pack
from twin.runtime import LiveCampaign


def test_decode_names_sender_and_reason():
    good = pack(Kind.RESULT, {"outputs": {}}, id="a:1", sender="spec-1", t_lab=0.0, task="t", attempt=1)
    env, body = decode(good)
    assert env.sender == "spec-1" and body.outputs == {}
    with pytest.raises(InvalidMessage) as info:
        decode(b'{"v":1,"kind":"result","id":"x","sender":"spec-9","t_lab":"soon","body":{}}')
    assert info.value.sender == "spec-9" and "t_lab" in info.value.reason
    with pytest.raises(InvalidMessage) as info:
        decode(pack(Kind.FAULT, {"code": 3}, id="x", sender="spec-2", t_lab=1.0))
    assert info.value.sender == "spec-2" and "fault body" in info.value.reason
    with pytest.raises(InvalidMessage) as info:
        decode(b"\xff garbage", sender_hint="dev/spec-3")
    assert info.value.sender == "dev/spec-3"
    with pytest.raises(InvalidMessage, match="v"):
        decode(b'{"v":2,"kind":"result","id":"x","sender":"s","t_lab":0,"body":{}}')


@pytest.mark.parametrize("readings, says", [
    ({"lamp_c": 40.0, "trace": [1, 2]}, "telemetry body: readings['trace']: Expected `float`, got `array`"),
    ({"ok": True}, "readings['ok']: Expected `float`, got `bool`"),
    ({"t": float("nan")}, "readings['t']: Expected `float`, got `null`"),  # NaN goes on the wire as null
    ({"t": "31.2"}, "readings['t']: Expected `float`, got `str`"),
])
def test_an_invalid_reading_is_named(readings, says):
    """The reason said `readings[...]`: which of a driver's readings was wrong, it did not say."""
    with pytest.raises(InvalidMessage) as info:
        decode(pack(Kind.TELEMETRY, {"readings": readings}, id="x", sender="spec-1", t_lab=1.0))
    assert says in info.value.reason, info.value.reason
    with pytest.raises(InvalidMessage, match=r"fraction: Expected `float` <= 1.0 \(a fraction of the step, 0 to 1: "
                                              r"not a percentage\)"):
        decode(pack(Kind.PROGRESS, {"fraction": 50, "note": ""}, id="x", sender="spec-1", t_lab=1.0))


async def lab_on_a_memory_bus(s, clock):
    """A started memory bus with the scenario's device actors on it."""
    bus = MemoryBus(MemoryHub())
    await bus.start()
    actors = build_actors(s, load_drivers(s), bus, clock)
    for a in actors:
        await a.start()
    return bus, actors


def test_garbage_on_the_bus_is_dropped_and_the_campaign_goes_on(scenario_of, tmp_path, caplog):
    s = scenario_of(**{"campaign.budget": 4})
    clock = LabClock("virtual")
    db = tmp_path / "j.db"

    async def main():
        bus, actors = await lab_on_a_memory_bus(s, clock)
        journal = Journal(db)
        camp = LiveCampaign(s, bus, clock, journal, make_planner(s), make_scheduler(s))
        campaign = asyncio.ensure_future(camp.run())
        await clock.sleep(1)
        # an impostor sprays both directions during the campaign
        bus.publish(keys.cmd(s.lab, "synthesiser"), b'{"kind":"command","sender":"impostor"}')
        bus.publish(keys.evt(s.lab, "spectrometer-1"), b"not json at all")
        bus.publish(keys.evt(s.lab, "spectrometer-1"),
                    pack(Kind.RESULT, {"outputs": 5}, id="i:1", sender="impostor", t_lab=0.0, task="e0s0", attempt=1))
        await campaign
        for a in actors:
            await a.stop()
        journal.close()
        return camp.core, actors

    with caplog.at_level(logging.WARNING):
        core, actors = clock.run(main())
    assert [e.status for e in core.experiments] == ["done"] * 4
    assert core.counts.invalid == 2
    assert actors[0].dropped == 1
    invalid = read_events(db, "message.invalid")
    assert {e["device"] for e in invalid} == {"spectrometer-1", "impostor"}
    assert any("impostor" in r.message and "id: Field required" in r.message for r in caplog.records)


def test_a_result_on_another_devices_key_is_rejected_even_with_the_right_name_and_token(scenario_of, tmp_path):
    import json as _json

    s = scenario_of(**{"campaign.budget": 4})
    clock = LabClock("virtual")
    db = tmp_path / "j.db"
    forged = []

    def forger_on(bus):
        def forge(key, payload):  # the moment spectrometer-2 is given a step, answer for it from another key
            env = _json.loads(payload)
            if env["kind"] == "command":
                forged.append(env["task"])
                bus.publish(keys.evt(s.lab, "spectrometer-1"), pack(
                    Kind.RESULT, {"outputs": {"peak_nm": 999.0}, "sample": None}, id=f"x:{len(forged)}",
                    sender="spectrometer-2", t_lab=clock.now(), task=env["task"], attempt=env["attempt"],
                    token=env["token"]))

        bus.subscribe(keys.cmd(s.lab, "spectrometer-2"), forge)

    core = campaign_with_a_forger(s, clock, db, forger_on)
    assert forged, "spectrometer-2 must have been given a step for this to mean anything"
    assert all(e.outputs.get("peak_nm") != 999.0 for e in core.experiments)
    assert [e.status for e in core.experiments] == ["done"] * 4
    assert core.counts.rejected == len(forged) and core.counts.invalid == 0
    rejected = read_events(db, "message.rejected")
    assert len(rejected) == len(forged)
    assert all("own key" in e["detail"] and e["device"] == "spectrometer-1" for e in rejected)
    received = read_events(db, "msg.%")
    assert received and not any('"token"' in e["detail"] for e in received)  # tokens never reach the journal


def test_an_oversized_message_is_refused_before_it_is_decoded():
    from twin.core.messages import MAX_MESSAGE_BYTES

    big = pack(Kind.RESULT, {"outputs": {"blob": "x" * MAX_MESSAGE_BYTES}}, id="a", sender="spec-1", t_lab=0.0)
    with pytest.raises(InvalidMessage, match="over the limit") as info:
        decode(big, sender_hint="spec-1")
    assert info.value.sender == "spec-1"


def test_a_device_obeys_a_cancel_only_with_the_attempts_token(scenario_of, tmp_path):
    import json as _json

    s = scenario_of(**{"campaign.budget": 3})
    clock = LabClock("virtual")
    cancels = []

    def forger_on(bus):
        def forge(key, payload):  # every command is answered at once by a cancel that lacks (or guesses) the token
            env = _json.loads(payload)
            if env["kind"] == "command":
                for token in ("", "0" * 32):
                    cancels.append(env["task"])
                    bus.publish(key, pack(Kind.CANCEL, {"reason": "forged"}, id=f"x:{len(cancels)}",
                                          sender="orchestrator", t_lab=clock.now(), task=env["task"],
                                          attempt=env["attempt"], token=token))

        for dev in ("synthesiser", "spectrometer-1", "spectrometer-2"):
            bus.subscribe(keys.cmd(s.lab, dev), forge)

    core = campaign_with_a_forger(s, clock, tmp_path / "j.db", forger_on)
    assert len(cancels) >= 12
    assert [e.status for e in core.experiments] == ["done"] * 3 and core.counts.failed == 0


def campaign_with_a_forger(s, clock, db, forger_on):
    """A live campaign on a memory bus while ``forger_on(bus)`` subscribes a forger to the keys it wants."""

    async def main():
        bus, actors = await lab_on_a_memory_bus(s, clock)
        forger_on(bus)
        journal = Journal(db)
        camp = LiveCampaign(s, bus, clock, journal, make_planner(s), make_scheduler(s))
        await camp.run()
        for a in actors:
            await a.stop()
        journal.close()
        return camp.core

    return clock.run(main())


def test_a_drivers_outputs_that_json_cannot_hold_become_json_or_fail_naming_their_type():
    """What docs/drivers.md says of outputs: numpy's, sets, datetimes and bytes are made JSON; another object fails
    the step, naming its type."""
    import datetime
    import json

    import numpy as np

    def sent(value):
        return json.loads(pack(Kind.RESULT, {"outputs": {"x": value}}, id="d:1", sender="d", t_lab=0.0))["body"][
            "outputs"]["x"]

    assert sent(np.float32(1.5)) == 1.5 and sent(np.arange(3)) == [0, 1, 2] and sorted(sent({2, 1})) == [1, 2]
    assert sent(datetime.datetime(2026, 12, 6, 9, 30)) == "2026-12-06T09:30:00" and sent(b"ab") == "YWI="
    with pytest.raises(TypeError, match="cannot send an object of type complex in a message"):
        sent(1j)
    assert sent({1: 2, 1.5: 3}) == {"1": 2, "1.5": 3}
    for key in (None, True):  # was "cannot send an object of type NoneType", where None is a value it sends
        with pytest.raises(TypeError, match=f"cannot send a mapping whose key is {key} in a message: keys are text"):
            sent({key: 1})
