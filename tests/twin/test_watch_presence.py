"""A watcher and its lab's presence: told when it comes, waited for until it does, given up on when it is gone."""

import asyncio
import json

from twin.core import keys
from twin.core.bus import MemoryBus
from twin.core.clock import LabClock
from twin.view.watch import RecordOptions, watch_async


def test_a_lab_that_dies_before_giving_its_history_ends_the_watch_within_the_grace(tmp_path):
    clock = LabClock("virtual")
    bus = MemoryBus()  # the lab's presence, and no history served yet: a lab killed while it starts
    gone: list[float] = []

    async def main():
        await bus.start()
        token = bus.declare_token(keys.orchestrator("qd"))
        watcher = asyncio.ensure_future(watch_async(bus, clock, "qd", RecordOptions(save=tmp_path / "w.rrd"),
                                                    on_gone=lambda: gone.append(clock.now())))
        await clock.sleep(5.0)
        killed = clock.now()
        token.close()
        observer = await asyncio.wait_for(watcher, timeout=None)
        return killed, observer

    killed, observer = clock.run(main())
    assert len(gone) == 1 and not observer.done
    assert gone[0] - killed < 5.0, f"told {gone[0] - killed:.1f} s after the lab went"  # the grace is 2 s; was 25


def watching(tmp_path, clock: LabClock, script, **watch):
    """Lab 'qd' watched on a memory bus while ``script(bus)`` runs on ``clock`` (it returns what it leaves open);
    what the watcher returned once stopped."""
    bus = MemoryBus()

    async def main():
        await bus.start()
        stop = asyncio.Event()
        watcher = asyncio.ensure_future(watch_async(bus, clock, "qd", RecordOptions(save=tmp_path / "w.rrd"),
                                                    stop=stop, **watch))
        left_open = await script(bus)
        stop.set()
        observer = await watcher
        for handle in left_open:
            handle.close()
        return observer

    return clock.run(main())


def test_a_lab_that_never_answers_for_its_history_is_given_the_patience_in_lab_time_then_recorded_live(tmp_path,
                                                                                                      caplog):
    """Each ask waits up to 2 s for its answer: counting asks, 30 s of patience was up to 150 s."""
    clock = LabClock("virtual")
    asked: list[float] = []

    async def hangs(key: str, payload: bytes) -> bytes:
        asked.append(clock.now())
        await asyncio.Event().wait()
        return b""

    async def lab(bus):
        left_open = [bus.declare_token(keys.orchestrator("qd")), bus.serve(keys.campaign("qd", "c", "history"), hangs)]
        await clock.sleep(90.0)
        return left_open

    watching(tmp_path, clock, lab)
    assert asked and max(asked) < 30.0, asked
    assert "lab 'qd' did not answer for its history in 30 s: recording from now on" in caplog.text


def test_a_following_watcher_is_told_when_its_lab_comes_and_when_it_comes_back(tmp_path):
    clock = LabClock("virtual")
    told: list[tuple[float, str]] = []

    async def lab(bus):
        await clock.sleep(3.0)  # started before its lab
        token = bus.declare_token(keys.orchestrator("qd"))
        await clock.sleep(5.0)
        token.close()  # killed
        await clock.sleep(10.0)
        token = bus.declare_token(keys.orchestrator("qd"))  # resumed
        await clock.sleep(5.0)
        return [token]

    watching(tmp_path, clock, lab, follow=True, on_gone=lambda: told.append((clock.now(), "gone")),
             on_present=lambda back: told.append((clock.now(), "back" if back else "found")))
    assert [what for _, what in told] == ["found", "gone", "back"], told
    assert [round(t) for t, _ in told][::2] == [3, 18]


def test_a_watcher_waits_for_a_lab_that_comes_late_and_reads_its_history_when_it_does(tmp_path, caplog):
    """Whether a lab is shared is known from its history's first page: a watcher that stopped asking for it 30 s
    after it started drew a shared lab that came later as one campaign."""
    clock = LabClock("virtual")
    asked: list[float] = []

    async def history(key: str, payload: bytes) -> bytes:
        asked.append(clock.now())
        return json.dumps({"items": [], "next": None, "shared": True, "campaign": "dots"}).encode()

    async def lab(bus):
        await clock.sleep(45.0)  # the lab comes after the watcher's 30 s of patience
        left_open = [bus.declare_token(keys.orchestrator("qd")),
                     bus.serve(keys.campaign("qd", "dots", "history"), history)]
        await clock.sleep(5.0)
        return left_open

    observer = watching(tmp_path, clock, lab)
    assert asked and min(asked) >= 45.0, asked
    assert type(observer).__name__ == "SharedLabObserver" and "dots" in observer.campaigns
    assert "did not answer for its history" not in caplog.text


def test_a_following_watcher_reads_the_history_of_a_lab_that_comes_back_long_after_it_first_came(tmp_path):
    clock = LabClock("virtual")
    asked: list[float] = []

    async def history(key: str, payload: bytes) -> bytes:
        asked.append(clock.now())
        return json.dumps({"items": [], "next": None}).encode()

    async def lab(bus):
        token, served = bus.declare_token(keys.orchestrator("qd")), bus.serve(keys.campaign("qd", "c", "history"),
                                                                              history)
        await clock.sleep(5.0)
        token.close()  # killed
        served.close()
        await clock.sleep(55.0)
        left_open = [bus.declare_token(keys.orchestrator("qd")),  # resumed, a minute after the lab first came
                     bus.serve(keys.campaign("qd", "c", "history"), history)]
        await clock.sleep(5.0)
        return left_open

    watching(tmp_path, clock, lab, follow=True)
    assert len(asked) == 2 and asked[0] < 1.0 and 60.0 <= asked[1] < 62.0, asked  # patience from its return
