"""A flood of refused messages is counted whole and journalled sparingly: the first 1,000 of each kind one by one,
then one row in 1,000 saying how many it stands for; a live journal's inputs hold a batch's undecodable messages
from one sender as one entry, which a rebuilt campaign counts the same."""

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
