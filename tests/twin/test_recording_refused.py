"""What a recording leaves out. What the lab refuses: a result or a reading forged on a device's key, refused for its
provenance, appears in neither the live recording nor its replay, which draw each measurement the journal holds
once. And what would swamp it: readings past a bound, said once in the log. And a recording file another run is
writing, refused before anything runs."""

import asyncio
import json
from pathlib import Path

import zenoh

from tests.conftest import qd_lab, twin_cli
from tests.rrd import read_rrd, rerun_verify
from tests.twin.test_device_process import free_port
from tests.twin.zenoh_clients import open_session, until_answered
from twin.campaign.journal_read import read_events
from twin.core import keys
from twin.core.messages import Kind, pack
from twin.runtime.lab import make_clock, prepare, run_async
from twin.scenario import parse
from twin.view.watch import RecordOptions, open_observer, replay, watch_async

ROOT = Path(__file__).resolve().parents[2]
LAB = "forged"
FORGED_Y = [7.0] * 50  # a spectrum no simulated measurement draws


def measurements(db) -> int:
    return sum("spectrum" in json.loads(e["detail"])["body"]["outputs"] for e in read_events(db, "msg.result"))


def test_a_forged_result_and_reading_are_refused_and_drawn_neither_live_nor_replayed(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    s = prepare(parse({**qd_lab(**{
        "campaign.budget": 4, "clock": {"mode": "scaled", "speed": 50.0},  # seconds of wall time to forge in
        "bus": {"kind": "zenoh", "listen": [endpoint]},
    }), "lab": LAB}))
    clock, db = make_clock(s), tmp_path / "j.db"
    observer, recording = open_observer(RecordOptions(save=tmp_path / "live.rrd"), "forged")
    seen = {}

    def forge() -> None:
        session = open_session(connect=endpoint)
        try:
            until_answered(session, keys.health(LAB, "synthesiser"))
            for i in range(5):  # well formed, on a real device's key, without the attempt's token
                session.put(keys.evt(LAB, "spectrometer-1"), pack(
                    Kind.RESULT, {"outputs": {"peak_nm": 630.0, "intensity": 1.0,
                                              "spectrum": {"start_nm": 400.0, "step_nm": 2.0, "y": FORGED_Y}},
                                  "sample": None},
                    id=f"forged:{i}", sender="spectrometer-1", t_lab=60.0, task="e0s1", attempt=1, token="0" * 32),
                    congestion_control=zenoh.CongestionControl.BLOCK)
            session.put(keys.telemetry(LAB, "spectrometer-1"), pack(  # another device's reading on this one's key
                Kind.TELEMETRY, {"readings": {"forged_reading": 1.0}}, id="forged:t", sender="spectrometer-2",
                t_lab=60.0), congestion_control=zenoh.CongestionControl.BLOCK)
        finally:
            session.close()

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, db, observer=observer,
                                                   on_start=lambda c: seen.setdefault("camp", c)))
        while "camp" not in seen:
            await asyncio.sleep(0.05 * s.clock.speed)  # the loop keeps lab time: 50 ms of wall time
        # and a watcher, as `twin watch` in another process: it hears the forged messages too
        watcher = asyncio.ensure_future(watch_async(seen["camp"].bus, clock, LAB,
                                                    RecordOptions(save=tmp_path / "watch.rrd")))
        await asyncio.to_thread(forge)
        done = await campaign
        await watcher
        return done

    try:
        summary = clock.run(main())
    finally:
        recording.close()
    assert summary.rejected_messages == 6 and summary.done == 4
    replay(db, RecordOptions(save=tmp_path / "replay.rrd"))
    for name in ("live.rrd", "replay.rrd", "watch.rrd"):
        rrd = read_rrd(tmp_path / name)
        drawn = rrd["spectra/measurement"]
        assert len(drawn) == measurements(db) >= 4, name
        ys = {point[1] for row in drawn for strip in row["LineStrips2D:strips"] for point in strip}
        assert 300.0 * (1.0 - FORGED_Y[0]) not in ys and len(ys) > 100, name  # the viewer draws y as 300·(1 − y) px
        assert not [path for path in rrd if "forged_reading" in path], name


def test_a_watcher_draws_each_reading_its_campaign_took_once_it_is_named(tmp_path):
    """Readings are named with the campaign's next decisions (a result sends them at once): a watcher draws every
    reading the journal holds, once, though it holds each until its campaign names it."""
    from pathlib import Path

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    s = prepare(Path(__file__).resolve().parents[2] / "scenarios" / "catalyst.yaml", clock="scaled", speed=2000,
                bus="zenoh", overrides={"campaign.budget": 2, "campaign.planner": "random", "bus.listen": [endpoint]})
    clock, db, seen = make_clock(s), tmp_path / "j.db", {}

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, db, on_start=lambda c: seen.setdefault("camp", c)))
        while "camp" not in seen:
            await asyncio.sleep(0.05 * s.clock.speed)
        watcher = asyncio.ensure_future(watch_async(seen["camp"].bus, clock, s.lab,
                                                    RecordOptions(save=tmp_path / "watch.rrd")))
        done = await campaign
        await watcher
        return done

    assert clock.run(main()).done == 2
    rrd = read_rrd(tmp_path / "watch.rrd")
    drawn = sum(len(rows) for path, rows in rrd.items() if path.startswith("telemetry/"))
    readings = sum(len(json.loads(e["detail"])["body"]["readings"]) for e in read_events(db, "msg.telemetry"))
    assert drawn == readings > 0


def test_a_lab_of_several_campaigns_draws_no_forged_result_either(tmp_path):
    import threading

    from tests.twin.shared_labs import LAB as SHARED
    from tests.twin.shared_labs import recorded_lab

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    s = prepare(SHARED, clock="scaled", speed=2000, bus="zenoh", seed=3,
                overrides={"bus.connect": [endpoint], "campaigns.0.campaign.budget": 3,
                           "campaigns.1.campaign.budget": 2})
    spectrometer = s.instance_names("spectrometer")[0]
    session = open_session(listen=endpoint)  # the forger is there first, and the lab connects to it
    sent = []

    def forge() -> None:
        until_answered(session, keys.health(s.lab, spectrometer))
        for i in range(5):
            session.put(keys.evt(s.lab, spectrometer), pack(
                Kind.RESULT, {"outputs": {"peak_nm": 630.0, "intensity": 1.0,
                                          "spectrum": {"start_nm": 400.0, "step_nm": 2.0, "y": FORGED_Y}},
                              "sample": None},
                id=f"forged:{i}", sender=spectrometer, t_lab=60.0, campaign="dots", task="e0s1", attempt=1,
                token="0" * 32), congestion_control=zenoh.CongestionControl.BLOCK)
            sent.append(i)

    forger = threading.Thread(target=forge)
    forger.start()
    try:
        out, rrd = recorded_lab(s, tmp_path)
    finally:
        forger.join()
        session.close()
    assert len(sent) == 5 and out.campaigns["dots"].rejected_messages == 5
    drawn = rrd["campaigns/dots/spectra/measurement"]
    assert len(drawn) == measurements(tmp_path / "runs" / "dots.db") >= 1
    assert 300.0 * (1.0 - FORGED_Y[0]) not in {p[1] for row in drawn for strip in row["LineStrips2D:strips"]
                                                for p in strip}


def test_what_waits_for_the_campaigns_next_turn_is_bounded_and_the_bound_said_once(caplog):
    from twin.runtime.event_decoder import MAX_HELD, EventDecoder

    decoder = EventDecoder(observer=object())

    def reading(i: int) -> bytes:
        return pack(Kind.TELEMETRY, {"readings": {"temperature_c": float(i)}}, id=f"t:{i}", sender="reactor",
                    t_lab=float(i))

    with caplog.at_level("WARNING"):
        for i in range(MAX_HELD + 50):
            decoder.event(keys.telemetry(LAB, "reactor"), reading(i))
        held = decoder.take()
        decoder.event(keys.telemetry(LAB, "reactor"), reading(-1))  # the campaign took its turn: held again
    assert len(held) == MAX_HELD and len(decoder.take()) == 1
    said = [r.getMessage() for r in caplog.records if "between two turns" in r.getMessage()]
    assert len(said) == 1 and "the journal has every one it accepts" in said[0]


def test_a_driver_naming_its_readings_afresh_draws_a_bounded_number_of_series_and_says_so_once(tmp_path, caplog):
    from twin.view.observer import MAX_TELEMETRY_SERIES

    observer, recording = open_observer(RecordOptions(save=tmp_path / "r.rrd"), "fresh-names")
    n = MAX_TELEMETRY_SERIES + 300
    with caplog.at_level("WARNING"):
        for i in range(n):  # a reading named by its time, beside one that keeps its name
            observer.on_message("", pack(Kind.TELEMETRY, {"readings": {"temperature_c": 20.0 + i, f"t{i}": 1.0}},
                                         id=f"r:{i}", sender="reactor", t_lab=float(i)))
            observer.on_message("", pack(Kind.TELEMETRY, {"readings": {"pressure_bar": 1.0, "stir_rpm": 300.0}},
                                         id=f"p:{i}", sender="reactor-2", t_lab=float(i)))  # a device that does not
        recording.close()
    rrd = read_rrd(tmp_path / "r.rrd")
    assert len([p for p in rrd if p.startswith("telemetry/reactor/")]) == MAX_TELEMETRY_SERIES
    assert len(rrd["telemetry/reactor/temperature_c"]) == n  # the first name: every row
    assert len(rrd["telemetry/reactor-2/pressure_bar"]) == len(rrd["telemetry/reactor-2/stir_rpm"]) == n
    said = [r.getMessage() for r in caplog.records if "telemetry series" in r.getMessage()]
    assert len(said) == 1 and "reactor's" in said[0] and "the journal has them all" in said[0]
    assert observer.undrawn_series == n - (MAX_TELEMETRY_SERIES - 1)


ODD_NAMES = ("a/b", "../up", "", "sp ace", "\x1b[2J", "é∂", "[0]", "#", "x" * 64)


def test_a_reading_of_any_name_is_one_series_of_its_device_drawn_as_named(tmp_path):
    """A driver (or a remote device) names its readings: 'a/b' was drawn as an entity b inside a, '' on the device's
    own entity, and 'sp ace' had Rerun warn on the terminal."""
    import rerun as rr

    from twin.view.observer import part

    observer, recording = open_observer(RecordOptions(save=tmp_path / "r.rrd"), "odd-names")
    for i in range(3):
        observer.on_message("", pack(Kind.TELEMETRY, {"readings": {name: float(i) for name in ODD_NAMES}},
                                     id=f"r:{i}", sender="reactor", t_lab=float(i)))
    recording.close()
    rrd = read_rrd(tmp_path / "r.rrd")
    drawn = {p for p in rrd if p.startswith("telemetry/")}
    assert drawn == {f"telemetry/reactor/{rr.escape_entity_path_part(n) or part(n)}" for n in ODD_NAMES}
    assert all(len(rrd[p]) == 3 for p in drawn)
    assert all(part(n) == rr.escape_entity_path_part(n) for n in ODD_NAMES if n)


def test_a_recording_another_run_is_writing_is_refused_before_anything_runs(tmp_path):
    import fcntl

    save, journal = tmp_path / "run.rrd", tmp_path / "j.db"
    args = ("run", ROOT / "scenarios" / "quantum_dots.yaml", "--budget", "2", "--save", save, "--journal", journal)
    save.write_bytes(b"a recording being written")
    with open(save, "ab") as other:
        fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as another run recording to it holds it
        refused = twin_cli(*args)
    assert refused.exit_code == 2, refused.output
    assert f"{save} is being recorded by another run: wait for that run to end, or --save another file" in \
        " ".join(refused.output.split())
    assert save.read_bytes() == b"a recording being written" and not journal.exists()
    ran = twin_cli(*args)  # and once that run has ended
    assert ran.exit_code == 0, ran.output
    assert rerun_verify(save).returncode == 0
