"""A planner that proposes what cannot be run: nothing is sent, no device is blamed, and the runtimes agree."""

import pytest

from tests.conftest import qd_lab
from twin.campaign.decisions import Proposal
from twin.campaign.journal_read import read_events
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


class GivesOut:
    """Proposes good experiments until its third question, then raises (or, ``WRONG``, answers bare dicts)."""

    WRONG = False

    def __init__(self, parameters):  # takes only what it reads: the kernel gives what its constructor names
        self.asked = 0

    def propose(self, n, history, pending):
        self.asked += 1
        if self.asked >= 3:
            if self.WRONG:
                return [dict(GOOD)]
            raise RuntimeError("out of ideas")
        return [Proposal(dict(GOOD)) for _ in range(n)]


class GivesWrong(GivesOut):
    WRONG = True


class LongestFirst:  # no constructor at all
    def decide(self, view):
        from twin import Assignment, capable

        free, out = list(view.free), []
        for step in sorted(view.ready, key=lambda r: -r.expected_s):
            fits = capable(step, tuple(free))
            if fits:
                free.remove(fits[0])
                out.append(Assignment(step.task, fits[0].name))
        return out


@pytest.mark.parametrize("planner, says", [("GivesOut", "planner 'tests.twin.test_bad_planners:GivesOut' raised "
                                                        "RuntimeError('out of ideas')"),
                                           ("GivesWrong", "GivesWrong' answered ")])
@pytest.mark.parametrize("runtime, clock", [("auto", "virtual"), ("asyncio", "virtual"), ("asyncio", "scaled")])
def test_a_planner_that_fails_ends_the_campaign_after_what_it_proposed_is_run(tmp_path, planner, says, runtime,
                                                                               clock):
    """It crashed `twin run` with a traceback (and a planner that returned dicts, with an AttributeError in the
    core); on a scaled clock it ended the campaign with its error, leaving what was in the lab."""
    lab = parse(qd_lab(**{"campaign.planner": f"tests.twin.test_bad_planners:{planner}", "campaign.budget": 12,
                          "campaign.planner_options": {"n_init": 2},  # another planner's: not handed to this one
                          "campaign.scheduler": "tests.twin.test_bad_planners:LongestFirst",
                          "clock": {"mode": clock, "speed": 20000}}))
    summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.proposed > 0 and summary.done == summary.proposed and summary.pending == 0  # nothing lost
    assert summary.proposed < 12 and says in summary.stopped and "run to their end" in summary.stopped
    if planner == "GivesWrong":
        assert "not a list of Proposal(params): return [twin.Proposal({name: value, ...}), ...]" in summary.stopped
    failed = [e["detail"] for e in read_events(tmp_path / "j.db", "planner.failed")]
    assert len(failed) == 1 and says in failed[0]
    assert summary.scheduler_fallbacks == 0  # the scheduler without a constructor decided every time


def test_a_planners_failure_is_an_input_a_resumed_campaign_replays():
    from twin.campaign.events import Proposed
    from twin.campaign.replay import decode_input, encode

    for answer in (Proposed([], "planner 'x' raised RuntimeError()"), Proposed([Proposal(dict(GOOD))])):
        assert decode_input(encode(answer)) == answer


class Shapeless:
    """Answers proposals whose shape is wrong (``KIND``), or whose route the lab cannot run."""

    KIND = "list"

    def __init__(self, parameters):
        pass

    def propose(self, n, history, pending):
        from twin import RouteStep

        if self.KIND == "list":
            return [Proposal([1, 2])]
        if self.KIND == "none":
            return [Proposal(None)]
        if self.KIND == "strings":
            return [Proposal(dict(GOOD), route=("synthesise", "measure"))]
        return [Proposal(dict(GOOD), route=(RouteStep("synthesise", "synthesiser"), RouteStep("fly", "nowhere")))
                for _ in range(n)]


class ListParams(Shapeless):
    KIND = "list"


class NoParams(Shapeless):
    KIND = "none"


class StringRoute(Shapeless):
    KIND = "strings"


class NowhereRoute(Shapeless):
    KIND = "nowhere"


@pytest.mark.parametrize("planner, says", [
    ("ListParams", "malformed proposal (item 0): params is '[1, 2]', not a mapping of parameter names to values"),
    ("NoParams", "malformed proposal (item 0): params is 'None'"),
    ("StringRoute", "route item 0 is 'synthesise', not a RouteStep(step, device_type, params={})"),
])
def test_a_proposal_of_the_wrong_shape_is_the_planners_failure_not_a_crash(tmp_path, planner, says):
    lab = parse(qd_lab(**{"campaign.planner": f"tests.twin.test_bad_planners:{planner}", "campaign.budget": 3}))
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.proposed == 0 and says in summary.stopped


def test_a_route_the_lab_cannot_run_abandons_its_experiment_before_anything_is_sent(tmp_path):
    lab = parse(qd_lab(**{"campaign.planner": "tests.twin.test_bad_planners:NowhereRoute", "campaign.budget": 3}))
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.abandoned == summary.proposed == 3 and summary.attempts == 0 and not summary.stopped
    said = [e["detail"] for e in read_events(tmp_path / "j.db", "planner.invalid")]
    assert len(said) == 3 and all("route step 1: no device type 'nowhere' in the lab" in s for s in said)


class NumpyPlanner:
    """Proposes as a GP library hands its numbers back: numpy float32 and int64, a 0-d array, a float32 cost."""

    def __init__(self, parameters, seed):
        import numpy as np

        self.np, self.box = np, parameters

    def propose(self, n, history, pending):
        np = self.np
        return [Proposal({"concentration_mm": np.float32(10.5), "temperature_c": np.int64(250),
                          "time_s": np.array(100.0)}, cost=np.float32(2.5)) for _ in range(n)]


def test_numpy_numbers_from_a_planner_are_numbers(tmp_path):
    """np.float32 is no Python float: each such proposal was abandoned, "'10.5' is not a number"."""
    lab = parse(qd_lab(**{"campaign.planner": "tests.twin.test_bad_planners:NumpyPlanner", "campaign.budget": 3}))
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.done == 3 and summary.abandoned == 0 and summary.cost >= 3 * 2.5


class AwaitableAnswer(Shapeless):
    def propose(self, n, history, pending):
        import asyncio

        return asyncio.sleep(0, result=[])


def test_an_awaitable_answer_is_the_planners_failure_without_a_never_awaited_warning(tmp_path):
    import gc
    import warnings

    lab = parse(qd_lab(**{"campaign.planner": "tests.twin.test_bad_planners:AwaitableAnswer", "campaign.budget": 3}))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = run(lab, journal=tmp_path / "j.db")
        gc.collect()
    assert summary.proposed == 0
    assert "answered an awaitable (coroutine): propose() must answer at once" in summary.stopped
    assert not [w for w in caught if "never awaited" in str(w.message)]


class WholeBatch:
    """Answers every question with a batch of 50, whatever it is asked for."""

    def __init__(self, seed):
        self.made = 0

    def propose(self, n, history, pending):
        self.made += 50
        return [Proposal({**GOOD, "time_s": 10 + (self.made + i) % 500}) for i in range(50)]


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_more_proposals_than_asked_for_run_the_first_and_the_rest_are_said_once_to_be_dropped(tmp_path, runtime,
                                                                                             caplog):
    """The extras were dropped without a word: a planner answering a whole batch thought the rest were queued."""
    import logging

    lab = parse(qd_lab(**{"campaign.planner": "tests.twin.test_bad_planners:WholeBatch", "campaign.budget": 8,
                          "campaign.max_in_flight": 3, "campaign.stop_on_target": False}))
    with caplog.at_level(logging.WARNING):
        summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == summary.proposed == 8
    said = [r.getMessage() for r in caplog.records if "were asked for" in r.getMessage()]
    assert said == ["planner 'tests.twin.test_bad_planners:WholeBatch' proposed 50 experiments where 3 were asked "
                    "for: the first 3 run, the rest are dropped (it is asked again as experiments finish; said once)"]


class BoxAsMapping:
    """Reads its box as the scenario writes it, `{low: 1, high: 50, unit: mM}`: it raised "'Parameter' object is not
    subscriptable" at its first proposal, and the campaign ran nothing."""

    def __init__(self, parameters, seed):
        import random

        self.rng, self.box = random.Random(seed), parameters

    def propose(self, n, history, pending):
        return [Proposal({k: self.rng.uniform(v["low"], v["high"]) for k, v in self.box.items()}) for _ in range(n)]


def test_a_planner_may_read_each_parameter_as_a_mapping_or_by_its_attributes(tmp_path):
    lab = parse(qd_lab(**{"campaign.planner": "tests.twin.test_bad_planners:BoxAsMapping", "campaign.budget": 4}))
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.done == summary.proposed == 4 and not summary.stopped
    box = lab.chemistry.parameters["time_s"]
    assert (box["low"], box["high"], box["unit"]) == (box.low, box.high, box.unit) == (10, 600, "")
    with pytest.raises(KeyError, match="a parameter has low, high and unit"):
        box["lo"]
