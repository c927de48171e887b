"""A planner that proposes what cannot be run: nothing is sent, no device is blamed, and the runtimes agree."""

import pytest

from tests.conftest import qd_lab
from twin.campaign.decisions import Proposal
from twin.campaign.journal import read_events
from twin.runtime.lab import run
from twin.scenario import parse

GOOD = {"concentration_mm": 10, "temperature_c": 250, "time_s": 100}
ODD = [{**GOOD, "concentration_mm": float("nan")}, {**GOOD, "concentration_mm": "lots"},
       {k: v for k, v in GOOD.items() if k != "concentration_mm"}, {**GOOD, "temperature_c": 1e308},
       {**GOOD, "concentration_mm": [1]}, {**GOOD, "concentration_mm": True}, {**GOOD, "time_s": -1}]


class OddPlanner:
    """Every other proposal is one of ODD, in turn; the others are fine (an extra parameter is passed along)."""

    def __init__(self, parameters, seed, **_):
        self.n = 0

    def propose(self, n, history, pending):
        out = []
        for _ in range(n):
            self.n += 1
            out.append(Proposal(ODD[(self.n // 2) % len(ODD)] if self.n % 2 else {**GOOD, "colour": "blue"}))
        return out


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_proposals_that_cannot_be_run_are_abandoned_before_anything_is_sent(tmp_path, runtime):
    """Once they went to the synthesiser, which raised, and the devices were quarantined for the planner's fault
    (and the two runtimes differed: a NaN reached the device in-process, a null over the bus)."""
    lab = parse(qd_lab(**{"campaign.planner": "tests.twin.test_bad_planners:OddPlanner", "campaign.budget": 14}))
    summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == 7 and summary.abandoned == 7 and summary.failed_attempts == 0
    assert summary.quarantines == 0 and summary.attempts == 14  # two steps of each good experiment, no more
    assert summary.abandoned_reasons == {"the planner proposed what cannot be run": 7}
    said = [e["detail"] for e in read_events(tmp_path / "j.db", "planner.invalid")]
    assert len(said) == 7
    for words in ("concentration_mm = nan is not a finite number", "concentration_mm = 'lots' is not a number",
                  "concentration_mm is missing", "temperature_c = 1e+308 is outside", "'[1]' is not a number",
                  "'True' is not a number", "time_s = -1 is outside chemistry.parameters.time_s [10, 600]"):
        assert any(words in s for s in said), (words, said)
    sent = [e for e in read_events(tmp_path / "j.db", "attempt.dispatched")]
    abandoned = {e["experiment"] for e in read_events(tmp_path / "j.db", "planner.invalid")}
    assert not {e["experiment"] for e in sent} & abandoned
