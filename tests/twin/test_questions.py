"""Recovery the operator chooses: a failed step covered by an ``orchestrator.recovery`` rule is asked about, the
answer (or the default at the timeout, or a simulated operator in virtual time) decides, and it is journalled."""

import json
import logging
from pathlib import Path

import pytest

from twin.campaign import Decided, Operator, TimerFired
from twin.campaign.decisions import Assignment
from twin.campaign.events import TimerKey, TimerKind
from twin.campaign.journal_read import read_events
from twin.core.errors import ScenarioError
from twin.core.messages import Kind
from twin.runtime import asked_of_people
from twin.runtime.lab import prepare, run
from twin.scenario import parse

from tests.conftest import qd_lab
from tests.twin.test_core import msg, notes
from tests.twin.test_operator import running

ROOT = Path(__file__).resolve().parents[2]
ASK = {"orchestrator.retry.max_attempts": 1,
       "orchestrator.recovery": [{"device": "synthesiser", "options": ["retry", "skip", "abandon"],
                                  "default": "abandon", "timeout_s": 600}]}


def failed(core, attempt=1, t=10.0, code="failed"):
    core.feed(msg(Kind.FAULT, "synthesiser", "e0s0", attempt, code=code, reason="clogged"))
    return core.advance(t)


def answer(core, qid, option, t, who="alice"):
    core.feed(Operator("answer", who, f"r{t}", question=qid, option=option))
    return core.advance(t)


def test_spent_retries_ask_the_operator_instead_of_abandoning(scenario_of):
    core = running(scenario_of, **ASK)
    out = failed(core)
    (asked,) = notes(out, "question.asked")
    assert not notes(out, "experiment.abandoned") and 0 in core.active
    assert asked.detail == {"id": "q1", "step": "synthesise", "fault": "failed", "reason":
                            "step 'synthesise' failed 1 time(s); last: failed on synthesiser: clogged",
                            "options": ["retry", "skip", "abandon"], "default": "abandon", "timeout_s": 600}
    assert TimerKey(TimerKind.QUESTION, "q1") in [a.key for a in out if hasattr(a, "delay")]
    out = answer(core, "q1", "retry", 20.0)
    (answered,) = notes(out, "question.answered")
    assert answered.detail == {"id": "q1", "option": "retry", "who": "alice"} and "e0s0" in core.ready
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    core.advance(20.0)
    assert core.attempts[("e0s0", 2)].device == "synthesiser"  # numbering goes on: a late first answer matches nothing
    out = failed(core, attempt=2, t=30.0)
    assert notes(out, "question.asked")[0].detail["id"] == "q2", "a retried step that fails again asks again"
    out = answer(core, "q2", "abandon", 40.0, who="bob")
    (gone,) = notes(out, "experiment.abandoned")
    assert gone.detail["reason"].endswith("; bob chose to abandon it") and not core.questions


def test_a_question_no_twin_ctl_can_reach_says_so_with_what_applies_when(scenario_of, caplog):
    """A live lab on a memory bus asks; the log says what and that nobody can answer (with Zenoh: the command,
    tests/twin/test_ctl.py)."""
    (asked,) = notes(failed(running(scenario_of, **ASK)), "question.asked")
    with caplog.at_level("WARNING", logger="twin.alerts"):
        asked_of_people.tell(asked, None, speed=20.0)
    assert caplog.messages == ["question.asked q1: synthesise of experiment 0 failed on synthesiser (failed; step "
                               "'synthesise' failed 1 time(s); last: failed on synthesiser: clogged): what now? "
                               "Options retry, skip, abandon. Nobody can answer: twin ctl reaches a campaign "
                               "over Zenoh, and this lab's bus is memory; unanswered within 600 lab-s (30 s of wall "
                               "time) abandon applies"]


def test_skip_moves_the_experiment_on_without_the_steps_outputs(scenario_of):
    core = running(scenario_of, **ASK)
    failed(core)
    out = answer(core, "q1", "skip", 15.0)
    assert notes(out, "task.skipped")[0].detail == {"by": "alice"} and "e0s1" in core.ready


def test_nobody_answers_and_the_default_applies_at_the_timeout(scenario_of):
    core = running(scenario_of, **ASK)
    failed(core)
    core.feed(TimerFired(TimerKey(TimerKind.QUESTION, "q1")))
    out = core.advance(610.0)
    assert notes(out, "question.answered")[0].detail == {"id": "q1", "option": "abandon", "who": "nobody",
                                                         "default": True}
    assert notes(out, "experiment.abandoned")[0].detail["reason"].endswith("the default chose to abandon it")
    out = answer(core, "q1", "retry", 620.0)
    why = notes(out, "operator.refused")[0].detail["why"]
    assert "there is no open question 'q1' (open: none" in why


def test_a_listed_fault_asks_at_once_and_a_wrong_option_is_refused(scenario_of):
    rules = [{"step": "synthesise", "faults": ["timed_out"], "options": ["retry", "abandon"], "default": "retry"}]
    core = running(scenario_of, **{"orchestrator.recovery": rules})  # three attempts, but a timeout asks at once
    core.feed(TimerFired(TimerKey(TimerKind.DEADLINE, "e0s0#1")))
    out = core.advance(500.0)
    assert notes(out, "question.asked")[0].detail["fault"] == "timed_out" and not notes(out, "task.retry")
    out = answer(core, "q1", "skip", 510.0)
    assert "'skip' is not an option of q1: choose one of retry, abandon" in notes(out, "operator.refused")[0].detail["why"]
    core.feed(msg(Kind.FAULT, "synthesiser", "e0s0", 1, code="failed", reason="plain failure"))  # late: no question
    assert not notes(core.advance(520.0), "question.asked")


def test_an_abort_withdraws_the_open_question(scenario_of):
    core = running(scenario_of, **ASK)
    failed(core)
    core.feed(Operator("abort", "alice", "r1", 0))
    out = core.advance(20.0)
    assert notes(out, "question.withdrawn")[0].detail["id"] == "q1" and not core.questions
    assert notes(out, "experiment.abandoned")


def test_a_simulated_operator_answers_in_virtual_time_and_nothing_is_lost(tmp_path):
    rules = [{"device": "reactor", "options": ["retry", "abandon"], "default": "abandon", "timeout_s": 7200,
              "simulate": {"after_s": 900, "answer": "retry"}}]
    db = tmp_path / "j.db"
    summary = run(prepare(ROOT / "scenarios" / "flaky_lab.yaml", seed=3, bus="memory",
                          overrides={"campaign.budget": 40, "orchestrator.retry.max_attempts": 1,
                                     "orchestrator.recovery": rules}), journal=db)
    events = read_events(db)
    asked = [e for e in events if e["kind"] == "question.asked"]
    answered = [json.loads(e["detail"]) for e in events if e["kind"] == "question.answered"]
    assert asked and all(a["who"] == "simulated operator" and a["option"] == "retry" for a in answered)
    assert len(answered) + sum(e["kind"] == "question.withdrawn" for e in events) == len(asked)
    gaps = [b["t_lab"] - a["t_lab"] for a, b in zip(asked, [e for e in events if e["kind"] == "question.answered"])]
    assert all(abs(g - 900) < 1e-6 for g in gaps)
    assert summary.done + summary.abandoned + summary.pending == 40
    reactor_abandoned = [r for r in summary.abandoned_reasons if "'react'" in r]
    assert reactor_abandoned == [], "a reactor failure is retried on the simulated answer, never abandoned"


@pytest.mark.parametrize("rule, words", [
    ({"options": ["retry"], "default": "abandon"}, "default 'abandon' is not one of the options ['retry']"),
    ({"device": "oven"}, "orchestrator.recovery.0.device: 'oven' is not a device type"),
    ({"step": "bake"}, "orchestrator.recovery.0.step: 'bake' is no device's step"),
    ({"simulate": {"after_s": 5, "answer": "skip"}, "options": ["retry", "abandon"]}, "simulate.answer 'skip'"),
    ({"options": ["retry", "retry", "abandon"]}, "each at most once"),
])
def test_a_recovery_rule_that_cannot_work_is_refused_with_its_field(rule, words):
    with pytest.raises(ScenarioError, match=words.replace("[", r"\[").replace("]", r"\]")):
        parse(qd_lab(**{"orchestrator.recovery": [rule]}), "lab.yaml")


def test_another_device_bars_the_one_that_failed_and_is_offered_only_where_there_is_another(scenario_of):
    rules = [{"device": "synthesiser", "options": ["another_device", "abandon"], "default": "abandon"}]
    core = running(scenario_of, **{"orchestrator.retry.max_attempts": 1, "orchestrator.recovery": rules})
    out = failed(core)
    assert notes(out, "question.asked")[0].detail["options"] == ["abandon"]  # the only synthesiser failed it
    two = running(scenario_of, device="synthesiser-1", **{"orchestrator.retry.max_attempts": 1,
                                                          "orchestrator.recovery": rules,
                                                          "devices.synthesiser.instances": 2})
    two.feed(msg(Kind.FAULT, "synthesiser-1", "e0s0", 1, code="failed", reason="clogged"))
    out = two.advance(10.0)
    assert notes(out, "question.asked")[0].detail["options"] == ["another_device", "abandon"]
    answer(two, "q1", "another_device", 20.0)
    from twin.campaign import dispatch

    view = dispatch.view(20.0, two.ready.values(), two.devices, 0, 2, 2)
    assert "synthesiser-1" in next(r for r in view.ready if r.task == "e0s0").avoid
    two.feed(Decided([Assignment("e0s0", "synthesiser-1")]))
    out = two.advance(20.0)
    assert "an operator chose another device" in notes(out, "scheduler.invalid")[0].detail


def test_an_alternative_abandons_the_experiment_and_the_planner_proposes_one_in_its_place(scenario_of):
    """`alternative`: the experiment is abandoned, the planner is asked at once — its history has the failure —
    and the new experiment does not count against the budget."""
    rules = [{"device": "synthesiser", "options": ["retry", "alternative", "abandon"], "default": "abandon"}]
    core = running(scenario_of, **{"orchestrator.retry.max_attempts": 1, "orchestrator.recovery": rules})
    assert len(core.experiments) == core.s.campaign.budget == 2  # the budget is spent
    failed(core)
    core.feed(Decided([Assignment("e1s0", "synthesiser")]))  # the other experiment's step takes the synthesiser
    core.advance(10.0)
    out = answer(core, "q1", "alternative", 20.0)
    (gone,) = notes(out, "experiment.abandoned")
    assert gone.experiment == 0 and gone.detail["reason"].endswith("; alice asked the planner for an alternative")
    (ask,) = [a for a in out if getattr(a, "what", "") == "plan"]
    assert ask.n == 1 and any(h.reason.endswith("an alternative") for h in ask.history)
    from twin.campaign import Proposed
    from twin.campaign.decisions import Proposal

    core.feed(Proposed([Proposal({"concentration_mm": 9, "temperature_c": 260, "time_s": 30})]))
    out = core.advance(20.0)
    assert len(core.experiments) == 3 and notes(out, "experiment.proposed")[0].experiment == 2
    assert not [a for a in core.advance(20.0) if getattr(a, "what", "") == "plan"]  # one in its place, no more


def test_a_simulated_operator_asking_for_alternatives_gets_the_budget_done(tmp_path):
    """Virtual time: every failed synthesis is replaced; the campaign still finishes its budget's worth of
    experiments, and the books balance."""
    lab = qd_lab(**{"campaign.budget": 8, "campaign.stop_on_target": False, "orchestrator.retry.max_attempts": 1,
                    "devices.synthesiser.faults": {"fail_p": 0.3},
                    "orchestrator.recovery": [{"device": "synthesiser", "options": ["alternative", "abandon"],
                                               "default": "abandon",
                                               "simulate": {"after_s": 60, "answer": "alternative"}}]})
    summary = run(parse(lab, "lab.yaml"), journal=tmp_path / "j.db")
    replaced = [e for e in read_events(tmp_path / "j.db", "experiment.abandoned")
                if json.loads(e["detail"])["reason"].endswith("asked the planner for an alternative")]
    assert replaced and summary.abandoned == len(replaced)
    assert summary.done == 8 and summary.proposed == 8 + len(replaced)
    assert summary.done + summary.abandoned + summary.pending == summary.proposed


def test_a_simulated_operator_slower_than_the_timeout_is_warned_of(tmp_path, caplog):
    """simulate.after_s past timeout_s: the simulated operator never answered, the default applied to every
    question, and nothing said so. A what-if of a slow operator may mean it: warned of, not refused."""
    from twin.runtime.checks import check

    for after_s, warned in ((900, False), (7200, True), (9000, True)):
        rules = [{"device": "reactor", "options": ["retry", "abandon"], "default": "abandon", "timeout_s": 7200,
                  "simulate": {"after_s": after_s, "answer": "retry"}}]
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            check(prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides={"orchestrator.recovery": rules}))
        said = [r.getMessage() for r in caplog.records if "simulate.after_s" in r.getMessage()]
        assert bool(said) == warned, (after_s, said)
        if warned:
            assert said == [f"orchestrator.recovery.0.simulate.after_s: {after_s} lab-s is not below its timeout_s, "
                            "7200, so the simulated operator never answers and the default (abandon) applies to "
                            "every question; give an after_s below 7200 for it to answer retry"]
