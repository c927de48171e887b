"""A live campaign writes ahead: a command is on disk, with what caused it, before it is on the bus."""

import sqlite3

from tests.conftest import qd_lab
from twin.core import keys
from twin.runtime.lab import make_clock, run_async
from twin.scenario import parse


def test_every_command_is_journalled_before_it_is_published(tmp_path):
    s = parse(qd_lab(**{"campaign.budget": 3, "clock": {"mode": "scaled", "speed": 20000}}))
    db = tmp_path / "j.db"
    clock = make_clock(s)
    seen, missing = [], []

    def on_command(key, payload):
        import json

        env = json.loads(payload)
        if env["kind"] != "command":
            return
        seen.append((env["task"], env["attempt"]))
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as c:
            rows = c.execute("SELECT COUNT(*) FROM events WHERE kind='attempt.dispatched' AND task=? AND attempt=?",
                             (env["task"], env["attempt"])).fetchone()[0]
        if rows != 1:
            missing.append((env["task"], env["attempt"]))

    def watch(camp):
        camp.bus.subscribe(keys.cmd(s.lab, "*"), on_command)

    summary = clock.run(run_async(s, clock, db, on_start=watch))
    assert summary.done == 3 and len(seen) >= 6
    assert missing == []
