"""Recovery the operator chooses: a step whose automatic retries are spent (or that failed with a fault the
scenario names) is not abandoned at once when an ``orchestrator.recovery`` rule covers it; the operator is
asked, with the options the rule gives, and the rule's default applies when nobody answers in time.

A question is a note (``question.asked``: its id, the experiment, step, device, fault, options, default and
timeout) and a timer; the answer is an ``Operator`` act (``answer``, ``twin ctl answer ID OPTION``) or, in
virtual time, the scenario's simulated operator. Either way the outcome is a ``question.answered`` note
naming who chose (or that the default applied). While a question is open its experiment stays in the lab's
books as running: nothing is lost, and the campaign does not end under it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from twin.campaign.events import Operator, Status, TimerKey, TimerKind
from twin.campaign.ledger import Task

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


@dataclass(slots=True)
class Question:
    id: str
    task: Task
    device: str
    fault: str
    why: str
    options: tuple[str, ...]
    default: str
    deadline: float  # lab time at which the default applies
    simulated: str = ""  # virtual time: what the scenario's simulated operator answers


def rule_for(core: CampaignCore, task: Task, device_type: str, code: str, retries_left: bool) -> Any:
    """The recovery rule that asks about this failure now, or None: a rule covers the step and device type, and
    either the step's retries are spent or the fault is one the rule asks about at once."""
    for rule in core.s.orchestrator.recovery:
        if rule.step not in (None, task.step.step) or rule.device not in (None, device_type):
            continue
        if not retries_left or code in rule.faults:
            return rule
    return None


def ask(core: CampaignCore, task: Task, device: str, code: str, why: str, rule: Any) -> None:
    core._question_seq += 1
    others = [d for d in core.devices.values() if d.type == task.step.device and d.name not in task.failed_on]
    options = tuple(o for o in rule.options if o != "another_device" or others) or ("abandon",)  # what makes sense
    default = rule.default if rule.default in options else "abandon" if "abandon" in options else options[0]
    answer_ = rule.simulate.answer if rule.simulate is not None else ""
    q = Question(f"q{core._question_seq}", task, device, code, why, options, default, core.now + rule.timeout_s,
                 answer_ if answer_ in options else default)
    core.questions[q.id] = q
    e = task.experiment
    core._note("question.asked", e.id, task.id, task.attempts, device,
               detail={"id": q.id, "step": task.step.step, "fault": code, "reason": why, "options": list(q.options),
                       "default": q.default, "timeout_s": rule.timeout_s})
    core._timer(TimerKey(TimerKind.QUESTION, q.id), rule.timeout_s)
    sim = rule.simulate
    if sim is not None and core.s.clock.mode == "virtual" and sim.after_s < rule.timeout_s:
        core._timer(TimerKey(TimerKind.ANSWER, q.id), sim.after_s)


def answer(core: CampaignCore, op: Operator) -> str:
    """An operator's answer (``op.question``, ``op.option``); '' when it applied, else why not."""
    q = core.questions.get(op.question)
    if q is None:
        open_ = ", ".join(core.questions) or "none"
        return f"there is no open question {op.question!r} (open: {open_}; `twin ctl pending` lists them)"
    if op.option not in q.options:
        return f"{op.option!r} is not an option of {q.id}: choose one of {', '.join(q.options)}"
    settle(core, q, op.option, op.who)
    return ""


def on_timer(core: CampaignCore, kind: TimerKind, qid: str) -> None:
    """The question's timeout (its default applies) or the simulated operator's answer."""
    q = core.questions.get(qid)
    if q is None:
        return
    if kind == TimerKind.QUESTION:
        settle(core, q, q.default, "", timed_out=True)
    else:
        settle(core, q, q.simulated, "simulated operator")


def _close(core: CampaignCore, q: Question) -> None:
    del core.questions[q.id]
    core.cancel_timer(TimerKey(TimerKind.QUESTION, q.id))
    core.cancel_timer(TimerKey(TimerKind.ANSWER, q.id))


def withdraw(core: CampaignCore, why: str, experiment: Any = None) -> None:
    """Close the open questions (about ``experiment``, or all) unanswered: their experiment was aborted, or the
    campaign ends (it then stays pending in the journal)."""
    for q in [q for q in core.questions.values() if experiment is None or q.task.experiment is experiment]:
        _close(core, q)
        core._note("question.withdrawn", q.task.experiment.id, q.task.id, q.task.attempts, q.device,
                   detail={"id": q.id, "why": why})


def settle(core: CampaignCore, q: Question, option: str, who: str, timed_out: bool = False) -> None:
    _close(core, q)
    task, e = q.task, q.task.experiment
    detail: dict[str, Any] = {"id": q.id, "option": option, "who": who or "nobody"}
    if timed_out:
        detail["default"] = True  # nobody answered in time
    core._note("question.answered", e.id, task.id, task.attempts, q.device, detail=detail)
    if e.status not in (Status.RUNNING, Status.PENDING) or e.id not in core.active:
        return  # aborted meanwhile
    chooser = who or "the default"
    if option in ("retry", "another_device"):
        task.excused = task.attempts  # fresh retries: the spent ones were the question's reason
        if option == "another_device":
            task.barred = frozenset(task.failed_on)
        core._make_ready(e, task)
    elif option == "skip":
        core._note("task.skipped", e.id, task.id, task.attempts, q.device, detail={"by": chooser})
        core._advance_experiment(task, {})
    elif option == "alternative":  # the planner proposes one in its place (it sees this one fail), beyond the budget
        core.replaced += 1
        core._filled = False  # ask the planner in this decision pass, even if it had its say before the answer
        core._finish(e, Status.ABANDONED, f"{q.why}; {chooser} asked the planner for an alternative")
    else:
        core._finish(e, Status.ABANDONED, f"{q.why}; {chooser} chose to abandon it")
    core._wake = True
