"""One contract, every bus: what an actor may rely on whichever bus carries it."""

import asyncio
import logging
import time

import pytest

from twin.core.bus import NoReplyError
from twin.core.clock import LabClock


def run(clock: LabClock, make_bus, body):
    async def main():
        bus = await make_bus(clock)
        try:
            return await body(bus)
        finally:
            await bus.close()

    return clock.run(main())


async def settle(clock: LabClock, seconds: float = 1.0) -> None:
    await clock.sleep(seconds)


def test_fan_out_reaches_every_subscriber(virtual_clock, make_bus):
    async def body(bus):
        a, b = [], []
        bus.subscribe("lab/x", lambda k, p: a.append(p))
        bus.subscribe("lab/x", lambda k, p: b.append(p))
        bus.publish("lab/x", b"1")
        await settle(virtual_clock)
        return a, b

    assert run(virtual_clock, make_bus, body) == ([b"1"], [b"1"])


def test_wildcards_match_one_or_many_chunks(virtual_clock, make_bus):
    async def body(bus):
        one, many = [], []
        bus.subscribe("lab/dev/*/evt", lambda k, p: one.append(k))
        bus.subscribe("lab/**", lambda k, p: many.append(k))
        for key in ["lab/dev/r1/evt", "lab/dev/r1/cmd", "lab/dev/a/b/evt", "other/dev/r1/evt"]:
            bus.publish(key, b"")
        await settle(virtual_clock)
        return one, sorted(many)

    one, many = run(virtual_clock, make_bus, body)
    assert one == ["lab/dev/r1/evt"]
    assert many == ["lab/dev/a/b/evt", "lab/dev/r1/cmd", "lab/dev/r1/evt"]


def test_one_sender_is_delivered_in_order(virtual_clock, make_bus):
    async def body(bus):
        got = []
        bus.subscribe("lab/seq", lambda k, p: got.append(int(p)))
        for i in range(500):
            bus.publish("lab/seq", str(i).encode())
        await settle(virtual_clock)
        return got

    assert run(virtual_clock, make_bus, body) == list(range(500))


def test_request_gets_the_reply(virtual_clock, make_bus):
    async def body(bus):
        async def echo(key, payload):
            await virtual_clock.sleep(5)
            return b"echo:" + payload

        bus.serve("lab/svc/echo", echo)
        await settle(virtual_clock)
        reply = await bus.request("lab/svc/echo", b"hi", timeout=10)
        return reply, virtual_clock.now()

    reply, t = run(virtual_clock, make_bus, body)
    assert reply == b"echo:hi"
    assert t == pytest.approx(6.0)


def test_a_request_with_a_wildcard_reaches_a_replier_of_a_key_it_covers(virtual_clock, make_bus):
    """How a watcher finds a lab's campaign: it asks ``campaign/*/history`` of a replier on ``campaign/c1/...``."""
    async def body(bus):
        async def page(key, payload):
            return b"c1's history"

        bus.serve("lab/campaign/c1/history", page)
        await settle(virtual_clock)
        reply = await bus.request("lab/campaign/*/history", b"", timeout=10)
        with pytest.raises(NoReplyError):
            await bus.request("lab/campaign/*/decisions", b"", timeout=2)
        return reply

    assert run(virtual_clock, make_bus, body) == b"c1's history"


def test_request_times_out_in_lab_time(virtual_clock, make_bus):
    async def body(bus):
        async def slow(key, payload):
            await virtual_clock.sleep(100)
            return b"late"

        bus.serve("lab/svc/slow", slow)
        await settle(virtual_clock)
        t0 = virtual_clock.now()
        with pytest.raises(NoReplyError, match="within 3"):
            await bus.request("lab/svc/slow", b"", timeout=3)
        return virtual_clock.now() - t0

    assert run(virtual_clock, make_bus, body) == pytest.approx(3.0)


def test_request_without_replier_fails_clearly(virtual_clock, make_bus):
    async def body(bus):
        with pytest.raises(NoReplyError, match="lab/svc/none"):
            await bus.request("lab/svc/none", b"", timeout=2)

    run(virtual_clock, make_bus, body)


def test_tokens_report_presence_and_loss(virtual_clock, make_bus):
    async def body(bus):
        early = bus.declare_token("lab/alive/r1")
        seen = []
        bus.watch_tokens("lab/alive/*", lambda k, alive: seen.append((k, alive)))
        await settle(virtual_clock)
        late = bus.declare_token("lab/alive/r2")
        await settle(virtual_clock)
        early.close()
        await settle(virtual_clock)
        late.close()
        await settle(virtual_clock)
        return seen

    assert run(virtual_clock, make_bus, body) == [
        ("lab/alive/r1", True),
        ("lab/alive/r2", True),
        ("lab/alive/r1", False),
        ("lab/alive/r2", False),
    ]


def test_virtual_time_never_jumps_past_a_message_in_flight(virtual_clock, make_bus):
    async def body(bus):
        arrivals = []
        bus.subscribe("lab/ping", lambda k, p: arrivals.append(virtual_clock.now()))
        sleeper = asyncio.ensure_future(virtual_clock.sleep(3600))
        for _ in range(20):
            bus.publish("lab/ping", b"x")
            await asyncio.sleep(0)
        await sleeper
        return arrivals

    arrivals = run(virtual_clock, make_bus, body)
    assert arrivals == [0.0] * 20


def test_wants_is_true_whenever_a_subscriber_could_receive(virtual_clock, make_bus, bus_kind):
    async def body(bus):
        before = bus.wants("lab/d/decisions")
        sub = bus.subscribe("lab/*/decisions", lambda k, p: None)
        during = bus.wants("lab/d/decisions")
        sub.close()
        return before, during, bus.wants("lab/d/decisions")

    before, during, after = run(virtual_clock, make_bus, body)
    assert during is True
    if bus_kind == "memory":  # in one process nobody else can listen: encoding can be skipped
        assert before is False and after is False


def test_a_foreign_attachment_is_delivered_not_raised(virtual_clock, caplog):
    """A message from outside the bus with an attachment of another shape must not break the bus's drain; a flood
    of them is said in a few lines, not one each."""
    import json as _json
    import socket

    import zenoh

    from twin.core.bus import open_bus

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"

    async def body():
        bus = open_bus("zenoh", virtual_clock, listen=[endpoint])
        await bus.start()
        got = []
        bus.subscribe("lab/x", lambda k, p: got.append(p))
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("listen/endpoints", "[]")
        cfg.insert_json5("connect/endpoints", _json.dumps([endpoint]))
        outsider = zenoh.open(cfg)
        try:
            for _ in range(200):  # until the outsider's publications reach us (wall time, bounded)
                outsider.put("lab/x", b"odd", attachment=b"\x01\x02\x03")
                await asyncio.sleep(0)
                await settle(virtual_clock, 0.01)
                if got:
                    break
                time.sleep(0.01)
            for _ in range(2_500):
                outsider.put("lab/x", b"odd", attachment=b"\x01\x02\x03",
                             congestion_control=zenoh.CongestionControl.BLOCK)
            for _ in range(500):  # wall time for the flood to cross the loopback link
                await settle(virtual_clock, 0.01)
                if len(got) >= 2_500:
                    break
                time.sleep(0.01)
            bus.publish("lab/x", b"ours")
            await settle(virtual_clock)
        finally:
            outsider.close()
            await bus.close()
        return got

    with caplog.at_level(logging.WARNING):
        got = virtual_clock.run(body())
    assert b"odd" in got and b"ours" in got
    assert not [r for r in caplog.records if "Exception in callback" in r.getMessage()]
    said = [r.getMessage() for r in caplog.records if "3-byte attachment" in r.getMessage()]
    assert got.count(b"odd") > 2_500 and 11 <= len(said) <= 13, len(said)
    assert "(2000 so far" in said[-1]


def test_another_processs_requests_and_messages_leave_a_virtual_clock_alone(virtual_clock, caplog):
    """A watcher, `twin ctl` or any other labtwin process asking a virtual-clock lab: its bus stamps its messages
    as the lab's bus does, yet neither its requests nor the replies sent back to it are held on the lab's clock
    (a reply that never comes back would stop lab time for 5 s of wall time, then warn)."""
    import socket
    import threading

    from twin.core.bus import open_bus

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    answers: list[bytes] = []

    def other_process() -> None:
        clock = LabClock("wall")

        async def ask() -> None:
            other = open_bus("zenoh", clock, mode="client", listen=[], connect=[endpoint])
            await other.start()
            try:
                for i in range(5):
                    answers.append(await other.request("lab/history", str(i).encode(), 10.0))
            finally:
                await other.close()

        clock.run(ask())

    async def body():
        bus = open_bus("zenoh", virtual_clock, listen=[endpoint])
        await bus.start()

        async def page(key: str, payload: bytes) -> bytes:
            return b"page " + payload

        bus.serve("lab/history", page)
        asker = threading.Thread(target=other_process)
        asker.start()
        try:
            while asker.is_alive():  # wall time, bounded by the asker's own timeouts
                await settle(virtual_clock, 0.01)
                time.sleep(0.005)
            await settle(virtual_clock)
            return virtual_clock._base.in_flight
        finally:
            asker.join()
            await bus.close()

    with caplog.at_level(logging.WARNING):
        in_flight = virtual_clock.run(body())
    assert answers == [f"page {i}".encode() for i in range(5)]
    assert in_flight == 0 and not [r for r in caplog.records if "in flight" in r.getMessage()]


def test_a_replier_still_at_work_when_the_bus_closes_is_ended_with_it(make_bus, caplog):
    """A reply still being made when its bus closed (a driver's health() that never returns, asked by `twin device
    health`) was left to the garbage collector: "Task was destroyed but it is pending!" at the end of the run."""
    import gc

    clock = LabClock("scaled", speed=100.0)
    ended = []

    async def body(bus):
        async def never(key, payload):
            try:
                await asyncio.Event().wait()
            finally:
                ended.append(key)

        bus.serve("lab/svc/never", never)
        await settle(clock)
        with pytest.raises(NoReplyError):
            await bus.request("lab/svc/never", b"", timeout=1)
        gc.collect()

    with caplog.at_level(logging.ERROR, logger="asyncio"):
        run(clock, make_bus, body)
        gc.collect()
    assert ended == ["lab/svc/never"] and "destroyed" not in caplog.text


def test_a_token_another_process_declares_and_drops_under_a_name_this_bus_holds_leaves_it_present():
    """Zenoh says a token left when another session's token of the same name goes, though this session still holds
    its own (two remote tokens of one name are counted; a local and a remote one are not): a lab whose device runs
    in its process saw that device lost, and never back, when a stranger's process (or a duplicate of the device)
    came and went under its name."""
    import socket

    from tests.twin.zenoh_clients import open_session
    from twin.core.bus import open_bus

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    clock = LabClock("scaled", speed=1.0)

    async def body():
        bus = open_bus("zenoh", clock, listen=[endpoint])
        await bus.start()
        seen: list[tuple[str, bool]] = []
        own = bus.declare_token("lab/alive/dev1")
        watch = bus.watch_tokens("lab/alive/*", lambda key, alive: seen.append((key, alive)))
        outsider = open_session(connect=endpoint)
        try:
            async def until(what):
                for _ in range(500):  # wall time for the outsider's tokens to cross the link, bounded
                    if what in seen:
                        return
                    await asyncio.sleep(0.01)
                raise AssertionError(f"{what} never came: {seen}")

            twin = outsider.liveliness().declare_token("lab/alive/dev1")
            marker = outsider.liveliness().declare_token("lab/alive/marker")
            await until(("lab/alive/marker", True))
            twin.undeclare()
            marker.undeclare()  # after the duplicate's going, on the same link
            await until(("lab/alive/marker", False))
            assert ("lab/alive/dev1", False) not in seen, seen
            own.close()  # this session's own token going is a loss as before
            await until(("lab/alive/dev1", False))
        finally:
            watch.close()
            outsider.close()
            await bus.close()
        return seen

    assert clock.run(body()) == [("lab/alive/dev1", True), ("lab/alive/marker", True), ("lab/alive/marker", False),
                                 ("lab/alive/dev1", False)]
