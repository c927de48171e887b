"""The dispatching rules and the random planner honour their contracts."""

from agents.planners import FixedPlanner, RandomPlanner
from agents.schedulers import FifoScheduler, OldestSampleScheduler
from twin.campaign.decisions import FreeDevice, LabView, ReadyStep
from twin.scenario import Parameter


def step(task, dtype, ready, made=None, avoid=()):
    return ReadyStep(task, 0, "s", dtype, ready, made, 10.0, 10.0, frozenset(avoid))


def test_fifo_serves_the_oldest_ready_step_first():
    view = LabView(100, (step("b", "spec", 50), step("a", "spec", 10)), (FreeDevice("spec-1", "spec"),))
    assert [a.task for a in FifoScheduler().decide(view)] == ["a"]


def test_oldest_sample_serves_the_oldest_sample_first_and_never_reuses_a_device():
    view = LabView(100, (step("a", "spec", 10, made=40), step("b", "spec", 50, made=5), step("c", "synth", 0)),
                   (FreeDevice("spec-1", "spec"), FreeDevice("synth-1", "synth")))
    out = OldestSampleScheduler().decide(view)
    assert [(a.task, a.device) for a in out] == [("b", "spec-1"), ("c", "synth-1")]


def test_a_step_is_not_sent_back_to_a_device_it_must_avoid():
    view = LabView(0, (step("a", "spec", 0, avoid={"spec-1"}),), (FreeDevice("spec-1", "spec"),))
    assert FifoScheduler().decide(view) == []


def test_random_planner_stays_in_the_box_and_is_seeded():
    box = {"x": Parameter(low=1, high=2), "y": Parameter(low=-5, high=5)}
    a = RandomPlanner(box, seed=1).propose(50, [], [])
    b = RandomPlanner(box, seed=1).propose(50, [], [])
    assert a == b
    assert all(1 <= p.params["x"] <= 2 and -5 <= p.params["y"] <= 5 for p in a)
    assert RandomPlanner(box, seed=2).propose(1, [], []) != a[:1]


def test_fixed_planner_runs_dry():
    p = FixedPlanner({}, 0, proposals=[{"params": {"job": 0}}, {"params": {"job": 1}}])
    assert [x.params["job"] for x in p.propose(5, [], [])] == [0, 1]
    assert p.propose(1, [], []) == []
