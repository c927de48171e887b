"""A watcher answered for its lab's history by a rogue or broken server: it says what was wrong with the answer and
records from then on — no crash, and no page asked for forever."""

import json

import pytest

from twin.core import keys
from twin.core.clock import LabClock
from tests.twin.test_watch_presence import watching

MESSAGE = json.dumps({"kind": "note"})  # a message, as far as a page's shape goes (the observer drops what it is not)


def watched(tmp_path, answer):
    """The lab's presence, its history answered by ``answer(payload) -> bytes``, a watcher for 40 lab-s; what the
    watcher returned and how often it asked."""
    clock = LabClock("virtual")
    asked: list[bytes] = []

    async def history(key: str, payload: bytes) -> bytes:
        asked.append(payload)
        if len(asked) > 100:  # a watcher asking without end gets an end here, so that the test fails, not hangs
            return json.dumps({"items": [], "next": None}).encode()
        return answer(payload)

    async def lab(bus):
        left_open = [bus.declare_token(keys.orchestrator("qd")),
                     bus.serve(keys.campaign("qd", "c", "history"), history)]
        await clock.sleep(40.0)
        return left_open

    return watching(tmp_path, clock, lab), asked


@pytest.mark.parametrize("reply, says", [
    (b"[1, 2]", "not a page but a list"),
    (b"\xff\xfe", "not JSON"),
    (b'{"items": "abc"}', "its items are not a list of messages"),
    (b'{"items": [5, null], "next": null}', "its items are not a list of messages"),
    (b'{"items": [], "next": 3}', "its next page (3) does not follow page 0"),
    (b'{"items": ["x"], "next": {"a": 1}}', "its next page ({'a': 1}) does not follow page 0"),
    (b'{"items": [], "shared": true, "campaign": "../../x"}', "its campaign ('../../x') is not a campaign's name"),
    (b'{"error": "no"}', "an error: no"),
])
def test_a_malformed_first_page_is_named_and_the_lab_recorded_from_then_on(tmp_path, caplog, reply, says):
    observer, asked = watched(tmp_path, lambda _: reply)
    assert type(observer).__name__ == "LabObserver" and 1 < len(asked) <= 61  # every 0.5 s until its patience ran out
    assert f"did not answer for its history in 30 s (its last answer: {says}" in caplog.text, caplog.text


def test_a_history_whose_next_page_does_not_move_on_is_not_asked_for_forever(tmp_path, caplog):
    def answer(payload: bytes) -> bytes:  # page 1 again and again: the watcher used to ask for it without end
        return json.dumps({"items": [MESSAGE], "next": 1, "campaign": "c", "shared": False}).encode()

    observer, asked = watched(tmp_path, answer)
    assert asked == [b"", b'{"after": 1}']
    assert "did not give all of its history (its next page (1) does not follow page 1)" in caplog.text
