"""A flood of refused messages is counted whole and journalled sparingly: the first 1,000 of each kind one by one,
then one row in 1,000 saying how many it stands for; a live journal's inputs hold a batch's undecodable messages
from one sender as one entry, which a rebuilt campaign counts the same."""

import pytest

from tests.twin.test_core import msg, notes, started
from twin.campaign import floods
from twin.campaign.events import InvalidInput, Presence
from twin.campaign.replay import decode_input, encode_all
from twin.core.messages import Kind


def test_a_flood_of_undecodable_messages_is_counted_whole_and_noted_sparingly(scenario_of):
    core, _ = started(scenario_of)
    rows = []
    for i in range(2_500):
        core.feed(InvalidInput("spectrometer", f"not JSON ({i})", "labtwin/t/dev/spectrometer/evt", "garbage"))
        rows += notes(core.advance(0.0), "message.invalid")
    assert core.counts.invalid == 2_500
    assert len(rows) == floods.FULL + 1  # the first thousand, then the two-thousandth standing for 999 more
    assert [r.detail.get("left_out", 0) for r in rows[-2:]] == [0, floods.EVERY - 1]
    assert rows[-1].detail["reason"] == "not JSON (1999)"


def test_a_flood_of_messages_without_provenance_is_counted_whole_and_noted_sparingly(scenario_of):
    core, _ = started(scenario_of)
    rows = []
    for i in range(3_001):
        core.feed(msg(Kind.RESULT, "spectrometer", "e9s1", 1, token="forged", outputs={}))
        rows += notes(core.advance(0.0), "message.rejected")
    assert core.counts.rejected == 3_001
    assert len(rows) == floods.FULL + 2 and sum(1 + r.detail.get("left_out", 0) for r in rows) == 3_000


def test_a_batch_of_undecodable_messages_is_one_input_per_sender_counted_the_same_when_replayed(scenario_of):
    flood = [InvalidInput("spectrometer", "not JSON", "k", "x"), InvalidInput("ghost", "not JSON")] * 1_200
    entries = encode_all([*flood, Presence("synthesiser", False), InvalidInput("spectrometer", "not JSON")])
    assert [(e[0], e[1], e[5] if len(e) > 5 else 1) for e in entries] == [
        ("invalid", "spectrometer", 1_201), ("invalid", "ghost", 1_200), ("presence", "synthesiser", 1)]
    core, _ = started(scenario_of)
    for entry in entries:
        core.feed(decode_input(entry))
    core.advance(0.0)
    assert core.counts.invalid == len(flood) + 1 and not core.devices["synthesiser"].online


@pytest.mark.wall
def test_a_live_lab_says_the_first_ten_rejected_messages_each_with_its_own_count(tmp_path, caplog):
    """A batch of forged results off Zenoh was said as many times as it held messages, each "(N so far" with the
    batch's last count, and the rest of the first ten never: the log read the core's count once the batch was in."""
    import asyncio
    import logging
    import re

    import zenoh

    from tests.conftest import qd_lab
    from tests.twin.test_device_process import free_port
    from tests.twin.zenoh_clients import open_session, until_answered
    from twin.core import keys
    from twin.core.messages import pack
    from twin.runtime.lab import make_clock, prepare, run_async
    from twin.scenario import parse

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    s = prepare(parse({**qd_lab(**{"campaign.budget": 2, "clock": {"mode": "scaled", "speed": 50.0},
                                   "bus": {"kind": "zenoh", "listen": [endpoint]}}), "lab": "flood"}))
    clock, started = make_clock(s), {}

    def forge() -> None:
        session = open_session(connect=endpoint)
        try:
            until_answered(session, keys.health("flood", "synthesiser"))
            for i in range(30):  # on a real device's key, without the attempt's token: sent at once, a batch or two
                session.put(keys.evt("flood", "spectrometer-1"), pack(
                    Kind.RESULT, {"outputs": {"peak_nm": 630.0}, "sample": None}, id=f"forged:{i}",
                    sender="spectrometer-1", t_lab=60.0, task="e0s1", attempt=1, token="0" * 32),
                    congestion_control=zenoh.CongestionControl.BLOCK)
        finally:
            session.close()

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, tmp_path / "j.db",
                                                   on_start=lambda c: started.setdefault("camp", c)))
        while "camp" not in started:
            await asyncio.sleep(0.05 * s.clock.speed)  # the loop keeps lab time: 50 ms of wall time
        await asyncio.to_thread(forge)
        return await campaign

    with caplog.at_level(logging.WARNING, logger="twin.runtime.live"):
        summary = clock.run(main())
    said = [int(re.search(r"\((\d+) so far", r.getMessage()).group(1)) for r in caplog.records
            if r.getMessage().startswith("rejected a message")]
    assert summary.rejected_messages == 30 and said == list(range(1, 11)), said
