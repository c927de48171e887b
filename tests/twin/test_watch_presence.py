"""A watcher still waiting for a lab's history gives up as soon as the lab's presence is gone for good."""

import asyncio

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


def test_a_lab_that_never_answers_for_its_history_is_given_the_patience_in_lab_time_then_recorded_live(tmp_path,
                                                                                                      caplog):
    """Each ask waits up to 2 s for its answer: counting asks, 30 s of patience was up to 150 s."""
    clock = LabClock("virtual")
    bus = MemoryBus()
    asked: list[float] = []

    async def hangs(key: str, payload: bytes) -> bytes:
        asked.append(clock.now())
        await asyncio.Event().wait()
        return b""

    async def main():
        await bus.start()
        token = bus.declare_token(keys.orchestrator("qd"))
        served = bus.serve(keys.campaign("qd", "c", "history"), hangs)
        stop = asyncio.Event()
        watcher = asyncio.ensure_future(watch_async(bus, clock, "qd", RecordOptions(save=tmp_path / "w.rrd"),
                                                    stop=stop))
        await clock.sleep(90.0)
        stop.set()
        await watcher
        served.close()
        token.close()

    clock.run(main())
    assert asked and max(asked) < 30.0, asked
    assert "lab 'qd' did not answer for its history in 30 s: recording from now on" in caplog.text


def test_a_following_watcher_is_told_when_its_lab_comes_and_when_it_comes_back(tmp_path):
    clock = LabClock("virtual")
    bus = MemoryBus()
    told: list[tuple[float, str]] = []

    async def main():
        await bus.start()
        stop = asyncio.Event()
        watcher = asyncio.ensure_future(watch_async(
            bus, clock, "qd", RecordOptions(save=tmp_path / "w.rrd"), follow=True, stop=stop,
            on_gone=lambda: told.append((clock.now(), "gone")),
            on_present=lambda back: told.append((clock.now(), "back" if back else "found"))))
        await clock.sleep(3.0)  # started before its lab
        token = bus.declare_token(keys.orchestrator("qd"))
        await clock.sleep(5.0)
        token.close()  # killed
        await clock.sleep(10.0)
        token = bus.declare_token(keys.orchestrator("qd"))  # resumed
        await clock.sleep(5.0)
        stop.set()
        await watcher
        token.close()

    clock.run(main())
    assert [what for _, what in told] == ["found", "gone", "back"], told
    assert [round(t) for t, _ in told][::2] == [3, 18]
