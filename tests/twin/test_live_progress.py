"""A live campaign's progress says the lab's time between events: a step of hours left the progress line at the
lab time of the last event (a furnace's 4-hour hold on a scaled clock: "lab 1.4 h" for a wall minute while the lab
went on to 2.8 h)."""

from tests.conftest import qd_lab
from twin.runtime import live
from twin.runtime.lab import prepare, run
from twin.runtime.live import lab_elapsed

SPEED = 20_000.0
LONG_S = 10_000.0  # lab seconds of the one step: 0.5 s of wall time, a tick each 0.02 s of it


def test_progress_between_events_moves_with_the_lab_clock(tmp_path, monkeypatch):
    monkeypatch.setattr(live, "PROGRESS_TICK_S", 0.02)
    s = prepare(qd_lab(**{"devices.synthesiser.duration": {"mean_s": LONG_S, "cv": 0},
                          "devices.spectrometer.duration": {"mean_s": 1, "cv": 0},
                          "campaign.budget": 1, "campaign.planner": "random"}),
                seed=1, clock="scaled", speed=SPEED, bus="memory")
    seen: list[tuple[int, float, float]] = []
    summary = run(s, journal=tmp_path / "j.db", runtime="asyncio",
                  on_progress=lambda core: seen.append((core.finished_count, core.elapsed_s, lab_elapsed(core))))
    assert summary.done == 1
    # while the long step runs nothing happens, and the core's own time stays where it began; the lab's moves on
    during = [lab_s for finished, core_s, lab_s in seen if finished == 0 and core_s < 0.1 * LONG_S]
    assert max(during) > 0.5 * LONG_S
    assert during == sorted(during)
    assert all(lab_s >= core_s for _, core_s, lab_s in seen)


def test_virtual_time_progress_is_the_cores_own(tmp_path):
    s = prepare(qd_lab(**{"campaign.budget": 3}), seed=1, bus="memory")
    seen: list[tuple[float, float]] = []
    run(s, journal=tmp_path / "j.db", on_progress=lambda core: seen.append((core.elapsed_s, lab_elapsed(core))))
    assert seen and all(a == b for a, b in seen)
