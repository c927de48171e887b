"""The history a late watcher asks for comes in bounded pages that add up to the journal."""

import json

from twin.campaign import Note
from twin.campaign.journal import Journal
from twin.campaign.journal_read import as_messages
from twin.core.bus import MemoryBus
from twin.core.clock import LabClock
from twin.runtime.decision_stream import PAGE_BYTES, PAGE_ROWS, DecisionStream


def test_the_history_is_served_in_pages_that_add_up_to_the_journal(tmp_path):
    clock = LabClock("virtual")
    journal = Journal(tmp_path / "j.db")
    for i in range(2 * PAGE_ROWS + 7):
        journal.note(Note(float(i), "task.ready", i, f"e{i}s0", detail={"pad": "x" * (400 if i % 3 else 10)}))
    stream = DecisionStream(journal, MemoryBus(), clock, "lab", "c1")

    async def pages():
        out, after = [], 0
        while after is not None:
            page = json.loads(await stream.history("k", json.dumps({"after": after}).encode()))
            out.append(page["items"])
            after = page["next"]
        return out

    got = clock.run(pages())
    assert len(got) >= 3 and all(len(p) <= PAGE_ROWS and len(json.dumps(p)) < 2 * PAGE_BYTES for p in got)
    assert [m for p in got for m in p] == as_messages(journal.rows())
    bad = clock.run(stream.history("k", b'{"after": "lots"}'))
    assert "error" in json.loads(bad)
    for past in (2 * PAGE_ROWS + 7, 10 ** 30, -5):  # the end, past it, before the start
        page = json.loads(clock.run(stream.history("k", json.dumps({"after": past}).encode())))
        assert page["items"] == (got[0] if past < 0 else []) and page["next"] == (None if past > 0 else len(got[0]))
    journal.close()
