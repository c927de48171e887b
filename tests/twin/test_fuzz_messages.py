"""A flood of malformed messages at a live lab over Zenoh: nothing crashes, every one is counted, and the journal has
the first 1,000 of each kind and one row in 1,000 after them."""

import asyncio
import json
import random

import zenoh

from tests.conftest import qd_lab
from tests.twin.test_device_process import free_port
from tests.twin.zenoh_clients import open_session, until_answered
from twin.campaign import floods
from twin.campaign.journal_read import read_events
from twin.core import keys
from twin.core.messages import MAX_MESSAGE_BYTES, Kind, pack
from twin.runtime.lab import make_clock, prepare, run_async
from twin.scenario import parse

N = 10_000
LAB = "fuzz"


def malformed(rng: random.Random, i: int) -> bytes:
    """One of the shapes a hostile or broken client sends; every one must fail validation or provenance."""
    valid = pack(Kind.RESULT, {"outputs": {"peak_nm": 600.0}, "sample": None}, id=f"f:{i}", sender="spectrometer",
                 t_lab=1.0, task="e0s1", attempt=1, token="0" * 32)
    shape = i % 12
    if shape == 0:
        return rng.randbytes(rng.randint(0, 300))
    if shape == 1:
        return valid[: rng.randint(0, len(valid) - 1)]
    if shape == 2:  # the right fields with the wrong types
        env = json.loads(valid)
        field = rng.choice(["kind", "attempt", "t_lab", "body", "sender", "v", "id"])
        env[field] = rng.choice([5, -1, "x", [], {}, None, 1e400 if field == "t_lab" else True])
        return json.dumps(env).encode()
    if shape == 3:
        return valid.replace(b'"result"', rng.choice([b'"explode"', b'"command"', b'"RESULT"']))
    if shape == 4:  # a body that is not the kind's
        return pack(Kind.FAULT, {"code": 5}, id=f"f:{i}", sender="spectrometer", t_lab=0.0)
    if shape == 5:
        depth = rng.randint(500, 20_000)
        return b'{"v":1,"kind":"result","id":"x","sender":"spectrometer","t_lab":0,"body":{"outputs":' + \
            b"[" * depth + b"]" * depth + b"}}"
    if shape == 6:
        return valid.replace(b'"sender":"spectrometer"', b'"sender":"\xff\xfe\xfd"')
    if shape == 7:  # well formed, but no attempt of this lab, or a guessed token
        return valid
    if shape == 8:
        return b'{"v":1,"kind":"result","id":"x","sender":"spectrometer","t_lab":NaN,"body":{}}'
    if shape == 9:
        return valid + b"trailing"
    if shape == 10:
        return json.dumps({"v": 2, "kind": "result", "id": "x", "sender": "spectrometer", "t_lab": 0}).encode()
    return b"[" + b"1," * rng.randint(0, 1000) + b"1]"


def test_ten_thousand_malformed_messages_at_a_live_lab(tmp_path):
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    s = prepare(parse({**qd_lab(**{
        "campaign.budget": 1000, "campaign.max_in_flight": 2,
        "clock": {"mode": "scaled", "speed": 100.0},
        "bus": {"kind": "zenoh", "listen": [endpoint]},
    }), "lab": LAB}))
    clock, db = make_clock(s), tmp_path / "j.db"
    rng = random.Random(7)
    sent = {"evt": 0, "cmd": 0, "oversized": 0}
    seen = {}

    def connect() -> zenoh.Session:
        """A session that has heard of the lab's subscribers: one of its devices answered a query."""
        session = open_session(connect=endpoint)
        try:
            until_answered(session, keys.health(LAB, "synthesiser"))
        except AssertionError:
            session.close()
            raise
        return session

    def send_oversized(session: zenoh.Session) -> None:
        for _ in range(3):  # refused before decoding
            session.put(keys.evt(LAB, "spectrometer-1"), b"x" * (MAX_MESSAGE_BYTES + 1),
                        congestion_control=zenoh.CongestionControl.BLOCK)
            sent["oversized"] += 1

    def flood(session: zenoh.Session) -> None:
        names = ["spectrometer-1", "spectrometer-2", "synthesiser", "ghost", "a" * 60]
        for i in range(N):
            payload = malformed(rng, i)
            if rng.random() < 0.8:
                key, counted = rng.choice([keys.evt, keys.telemetry])(LAB, rng.choice(names)), "evt"
            else:
                key, counted = keys.cmd(LAB, rng.choice(names[:3])), "cmd"
            attachment = rng.randbytes(rng.randint(0, 12)) if rng.random() < 0.3 else None
            session.put(key, payload, attachment=attachment, congestion_control=zenoh.CongestionControl.BLOCK)
            sent[counted] += 1

    async def until_counted(core, expected: int) -> None:
        """Wall time for the last of them to cross the loopback link; a minute is plenty on a loaded machine."""
        for _ in range(1200):
            if core.counts.invalid + core.counts.rejected >= expected:
                return
            await asyncio.sleep(0.05 * s.clock.speed)  # the loop keeps lab time: 50 ms of wall time
        bus = seen["camp"].bus  # where the rest could be: still queued here, or never arrived
        raise AssertionError(f"{core.counts.invalid} invalid and {core.counts.rejected} rejected messages "
                             f"counted a minute after the last of {expected} was sent; the campaign "
                             f"{'finished' if core.finished else 'running'}, {len(core._inbox)} inputs in its "
                             f"inbox, {len(getattr(bus, '_inbox', ()))} messages in the bus's")

    async def main():
        campaign = asyncio.ensure_future(run_async(s, clock, db, on_start=lambda c: seen.setdefault("camp", c)))
        while "camp" not in seen:
            await asyncio.sleep(0.05 * s.clock.speed)  # the loop keeps lab time: 50 ms of wall time
        core = seen["camp"].core
        session = await asyncio.to_thread(connect)
        try:
            await asyncio.to_thread(send_oversized, session)
            await until_counted(core, sent["oversized"])  # among the journal's first 1,000, whatever the flood's batches
            await asyncio.to_thread(flood, session)
        finally:
            session.close()
        await until_counted(core, sent["evt"] + sent["oversized"])
        for _ in range(400):  # and for the lab to finish some experiments of its own despite the flood
            if sum(e.status == "done" for e in core.experiments) >= 3:
                break
            await asyncio.sleep(0.05 * s.clock.speed)  # the loop keeps lab time: 50 ms of wall time
        reports = [json.loads(await seen["camp"].bus.request(keys.health(LAB, d), b"", 5.0 * clock.speed))
                   for d in ("synthesiser", "spectrometer-1", "spectrometer-2")]
        seen["dropped"] = sum(r["dropped"] for r in reports)
        seen["camp"].stop("fuzzing over")
        return await campaign

    summary = clock.run(main())
    refused = read_events(db, "message.invalid") + read_events(db, "message.rejected")
    assert summary.invalid_messages + summary.rejected_messages == sent["evt"] + sent["oversized"]
    for kind, counted in (("message.invalid", summary.invalid_messages),
                          ("message.rejected", summary.rejected_messages)):
        rows = [json.loads(e["detail"]) for e in read_events(db, kind)]
        stands_for = sum(1 + r.get("left_out", 0) for r in rows)  # each row, and those it stands for
        assert len(rows) == min(counted, floods.FULL) + max(0, counted - floods.FULL) // floods.EVERY
        assert stands_for <= counted < stands_for + floods.EVERY
    assert seen["dropped"] == sent["cmd"]  # what reached the devices' command keys: dropped and counted
    # the lab carried on: nothing failed but, on a loaded machine, a deadline the flood's backlog delayed
    assert summary.done > 0 and summary.abandoned == 0 and summary.failed_attempts == summary.timed_out
    oversized = [json.loads(e["detail"]) for e in read_events(db, "message.invalid") if "over the limit" in e["detail"]]
    assert len(oversized) == 3 and all(len(o["excerpt"]) < 300 for o in oversized)
    assert all(json.loads(e["detail"])["key"].startswith(f"labtwin/{LAB}/dev/") for e in refused)
