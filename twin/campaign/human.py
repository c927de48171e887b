"""Human steps: a device type whose ``driver`` is ``operator`` is people ("load the reagent rack", "confirm the
seal"). Nothing is sent to it: a step dispatched to it is an ``operator.step`` note (what to do, and where the
scenario says how: ``options.instructions``), and it is done when an operator confirms it (``twin ctl confirm
TASK``), with a deadline like any device's. In virtual time the scenario's operator confirms after the step's
expected duration. An operator is always present: there is no presence token to lose.
"""

from __future__ import annotations

from typing import Any

from twin.campaign.events import Code, Note, Operator, TimerKey, TimerKind
from twin.campaign.ledger import Attempt

DRIVER = "operator"
OPTION_NAMES = frozenset({"instructions"})  # what its options may hold (checked like a driver's option_names)
CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


def people(s: Any) -> set[str]:
    """The device instances of scenario ``s`` that are people."""
    return {name for dtype, spec in s.devices.items() if spec.driver == DRIVER for name in s.instance_names(dtype)}


def dispatched(core: CampaignCore, att: Attempt, body: dict[str, Any]) -> None:
    """A step given to people: say what to do; in virtual time, the simulated operator confirms it in time."""
    core._out.append(_announced(core, att, core.now, deadline_s=body["deadline_s"]))
    if core.s.clock.mode == "virtual":
        core._timer(TimerKey(TimerKind.CONFIRM, f"{att.task.id}#{att.n}"), att.task.expected_s)


def said_again(core: CampaignCore, att: Attempt, t_lab: float, why: str) -> Note:
    """A human step still waiting for its person, announced again (a resumed campaign's: whoever pages people
    from the ``operator.step`` notes hears of it afresh); ``why`` says why it is said again."""
    return _announced(core, att, t_lab, again=why)


def _announced(core: CampaignCore, att: Attempt, t_lab: float, **extra: Any) -> Note:
    """The ``operator.step`` note of a human step: what to do, with what, and where the scenario says how."""
    task = att.task
    instructions = str(core.s.devices[core.devices[att.device].type].options.get("instructions", ""))[:500]
    return Note(t_lab, "operator.step", task.experiment.id, task.id, att.n, att.device,
                {"step": task.step.step, "params": {**task.experiment.params, **task.step.params}, **extra,
                 "instructions": instructions})


def confirm(core: CampaignCore, op: Operator) -> str:
    """An operator's confirmation of a human step in the lab; '' when it counted, else why not."""
    att = next((d.attempt for d in core.devices.values() if d.name in core.people and d.attempt is not None
                and d.attempt.task.id == op.task), None)
    if att is None:
        waiting = [d.attempt.task.id for d in core.devices.values() if d.name in core.people and d.attempt]
        return (f"{op.task!r} is not a human step waiting for confirmation (waiting: "
                f"{', '.join(waiting) or 'none'}; `twin ctl pending` lists them)")
    done(core, att, op.who)
    return ""


def on_timer(core: CampaignCore, ref: str) -> None:
    """Virtual time: the simulated operator confirms the step."""
    task, _, n = ref.rpartition("#")
    att = core.attempts.get((task, int(n)))
    if att is not None and not att.resolved:
        done(core, att, "simulated operator")


def done(core: CampaignCore, att: Attempt, who: str) -> None:
    core._note("attempt.confirmed", att.task.experiment.id, att.task.id, att.n, att.device, detail={"who": who})
    core._resolve(att, Code.OK, {"outputs": {}})
