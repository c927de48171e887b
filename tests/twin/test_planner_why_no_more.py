"""A planner that has nothing more to propose may say why (`why_no_more`); the summary's `ended` carries it, through
the journal, and a planner's odd answer there says nothing rather than failing the campaign."""

import pytest

from tests.conftest import qd_lab
from twin.campaign.decisions import Proposal
from twin.campaign.journal_read import read_run
from twin.campaign.events import Proposed
from twin.campaign.replay import decode_input, encode
from twin.runtime.lab import run
from twin.scenario import parse

GOOD = {"concentration_mm": 10, "temperature_c": 250, "time_s": 100}


class Dries:
    """Three experiments, then nothing, saying ``WHY`` (a class attribute: text, something else, or a property that
    raises)."""

    WHY: object = "the three precursors in stock are used up"

    def __init__(self, parameters):
        self.left = 3

    def propose(self, n, history, pending):
        k = min(n, self.left)
        self.left -= k
        return [Proposal(dict(GOOD)) for _ in range(k)]

    @property
    def why_no_more(self):
        if isinstance(self.WHY, Exception):
            raise self.WHY
        return "" if self.left else self.WHY


class DriesOddly(Dries):
    WHY = {"not": "text"}


class DriesRaising(Dries):
    WHY = RuntimeError("no idea")


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_the_planners_reason_ends_the_summarys_ended_line(tmp_path, runtime):
    lab = parse(qd_lab(**{"campaign.planner": "tests.twin.test_planner_why_no_more:Dries", "campaign.budget": 10}))
    summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == 3 and not summary.stopped
    assert summary.ended == ("the planner proposed no more experiments after 3 of the budget's 10: the three "
                             "precursors in stock are used up")
    assert read_run(tmp_path / "j.db")["summary"]["ended"] == summary.ended


@pytest.mark.parametrize("planner", ["DriesOddly", "DriesRaising"])
def test_a_reason_that_is_not_text_is_left_out(tmp_path, planner):
    lab = parse(qd_lab(**{"campaign.planner": f"tests.twin.test_planner_why_no_more:{planner}",
                          "campaign.budget": 10}))
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.done == 3 and not summary.stopped
    assert summary.ended == "the planner proposed no more experiments after 3 of the budget's 10"


def test_a_fixed_planner_short_of_the_budget_says_its_list_ran_out(tmp_path):
    lab = parse(qd_lab(**{"campaign.planner": "fixed", "campaign.budget": 6,
                          "campaign.planner_options": {"proposals": [{"params": GOOD}, {"params": GOOD}]}}))
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.done == 2
    assert summary.ended.endswith("after 2 of the budget's 6: all 2 of campaign.planner_options.proposals were "
                                  "proposed")


def test_the_reason_survives_the_journal_a_resumed_core_is_rebuilt_from():
    back = decode_input(encode(Proposed([], why="no route to X")))
    assert back.proposals == [] and back.failed == "" and back.why == "no route to X"
    assert decode_input(encode(Proposed([], "it raised"))).failed == "it raised"
