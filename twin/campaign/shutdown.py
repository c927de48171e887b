"""The campaign's end: what is in the lab is cancelled, open questions are withdrawn, experiments still in the
lab are left pending with why, and the ledger is proved whole before ``Finished``."""

from __future__ import annotations

from typing import Any

from twin.campaign import questions
from twin.campaign.events import Finished, RecordExperiment, Status, TimerKey, TimerKind
from twin.campaign.ledger import check_accounting
from twin.core.messages import Kind

CampaignCore = Any  # the core calls in here with itself (an import of it would be a cycle)


def end(core: CampaignCore) -> None:
    for dev in core.devices.values():
        att = dev.attempt
        if att is not None and not att.resolved:
            att.resolved = True
            core.cancel_timer(TimerKey(TimerKind.DEADLINE, f"{att.task.id}#{att.n}"))
            dev.busy_s += core.now - att.t_sent
            dev.attempt = None
            if dev.name not in core.people:
                core._send(dev.name, Kind.CANCEL, att.task.id, att.n, {"reason": "campaign stopped"}, att.token)
            core._note("attempt.cancelled", att.task.experiment.id, att.task.id, att.n, dev.name,
                       detail=core.stopping)
    questions.withdraw(core, core.stopping or "the campaign ended")
    for e in core.active.values():
        if e.status == Status.RUNNING:
            e.status = Status.PENDING
            e.reason = f"in the lab at shutdown ({core.stopping})" if core.stopping else "in the lab at shutdown"
            core._out.append(RecordExperiment(e))
    check_accounting(core.experiments, len(core.experiments))
    core.finished = True
    core._out.append(Finished(core.stopping))
