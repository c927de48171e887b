"""A scheduler that thinks for wall time on a scaled clock decides off the event loop: no healthy step times
out; one that misses its deadline is replaced by the fallback rule for that decision, and the journal says so."""

import time

import pytest

from agents.schedulers import FifoScheduler
from tests.conftest import qd_lab
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run
from twin.scenario import parse


class SlowScheduler(FifoScheduler):
    """FIFO after a long think (a big solve, say), without saying it runs long."""

    think_s = 0.2  # 720 lab-s at 3600x: past a running measurement's deadline (200 x 2 + 60 lab-s) on the loop

    def decide(self, view):
        time.sleep(self.think_s)
        return super().decide(view)


@pytest.mark.parametrize("deadline_ms, late", [(2000, False), (50, True)])
def test_a_slow_scheduler_on_a_scaled_clock_causes_no_false_timeout(tmp_path, deadline_ms, late):
    lab = parse(qd_lab(**{
        "campaign.scheduler": "tests.twin.test_slow_scheduler:SlowScheduler", "campaign.budget": 4,
        "campaign.scheduler_deadline_ms": deadline_ms, "campaign.max_in_flight": 2,
        "clock": {"mode": "scaled", "speed": 3600.0}, "bus": {"kind": "zenoh"},
        "orchestrator.timeout_slack_s": 60,
        "devices.synthesiser.duration": {"mean_s": 60, "cv": 0}, "devices.spectrometer.duration": {"mean_s": 200, "cv": 0},
    }))
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.done == 4 and summary.timed_out == 0 and summary.failed_attempts == 0
    fallback = read_events(tmp_path / "j.db", "scheduler.fallback")
    assert bool(fallback) == late and (summary.scheduler_fallbacks > 0) == late
    if late:
        assert "did not decide within" in fallback[0]["detail"]
