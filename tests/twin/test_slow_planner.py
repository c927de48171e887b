"""A planner that thinks for wall seconds on a scaled clock: the lab goes on, and no healthy step times out."""

import random
import time

from tests.conftest import qd_lab
from twin.campaign.decisions import Proposal
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run
from twin.scenario import parse

THINK_S = 1.0  # wall seconds per proposal: 3,600 lab-s at 3600x, ten times a step's deadline


class SlowPlanner:
    """Random proposals, after a long think (a GP fit on a big history, say)."""

    def __init__(self, parameters, seed, **_):
        self.box, self.rng = parameters, random.Random(seed)

    def propose(self, n, history, pending):
        time.sleep(THINK_S)
        return [Proposal({k: self.rng.uniform(p.low, p.high) for k, p in self.box.items()}) for _ in range(n)]


def test_a_slow_planner_on_a_scaled_clock_causes_no_false_timeout(tmp_path):
    # on Zenoh even an in-process device's result crosses a thread: were the planner on the loop, the
    # step's deadline would fire first when the loop woke up
    lab = parse(qd_lab(**{
        "campaign.planner": "tests.twin.test_slow_planner:SlowPlanner", "campaign.budget": 4,
        "campaign.max_in_flight": 2, "clock": {"mode": "scaled", "speed": 3600.0}, "bus": {"kind": "zenoh"},
        "devices.synthesiser.duration": {"mean_s": 60, "cv": 0}, "devices.spectrometer.duration": {"mean_s": 60, "cv": 0},
    }))
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.done == 4 and summary.timed_out == 0 and summary.failed_attempts == 0
    late = read_events(tmp_path / "j.db", "planner.late")
    assert late  # it thought past its deadline (300 lab-s) while the lab had work, and the lab went on
    proposed = read_events(tmp_path / "j.db", "experiment.proposed")
    assert len(proposed) == 4
