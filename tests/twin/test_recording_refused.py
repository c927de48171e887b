"""What the lab refuses is not drawn: a result or a reading forged on a device's key, refused for its provenance,
appears in neither the live recording nor its replay, which draw each measurement the journal holds once."""

import asyncio
import json

import zenoh

from tests.conftest import qd_lab
from tests.rrd import read_rrd
from tests.twin.test_device_process import free_port
from twin.campaign.journal import read_events
from twin.core import keys
from twin.core.messages import Kind, pack
from twin.runtime.lab import make_clock, prepare, run_async
from twin.scenario import parse
from twin.view.watch import RecordOptions, open_observer, replay

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
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
        session = zenoh.open(cfg)
        try:
            for _ in range(100):  # until a device of the lab answers: its subscribers are known
                if any(r.ok is not None for r in session.get(keys.health(LAB, "synthesiser"), timeout=1.0)):
                    break
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
        await asyncio.to_thread(forge)
        return await campaign

    try:
        summary = clock.run(main())
    finally:
        recording.close()
    assert summary.rejected_messages == 6 and summary.done == 4
    replay(db, RecordOptions(save=tmp_path / "replay.rrd"))
    for name in ("live.rrd", "replay.rrd"):
        rrd = read_rrd(tmp_path / name)
        drawn = rrd["spectra/measurement"]
        assert len(drawn) == measurements(db) >= 4, name
        ys = {point[1] for row in drawn for strip in row["LineStrips2D:strips"] for point in strip}
        assert 300.0 * (1.0 - FORGED_Y[0]) not in ys and len(ys) > 100, name  # the viewer draws y as 300·(1 − y) px
        assert not [path for path in rrd if "forged_reading" in path], name
