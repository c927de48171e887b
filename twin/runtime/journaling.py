"""The core's record actions written to the journal; the same in every runtime."""

from __future__ import annotations

from twin.campaign import Note, RecordExperiment, RecordMessage
from twin.campaign.journal import Journal


def note(journal: Journal, n: Note) -> int:
    """Journal a state change; returns its sequence number."""
    return journal.event(n.t_lab, n.kind, n.experiment, n.task, n.attempt, n.device, n.detail)


def message(journal: Journal, m: RecordMessage) -> None:
    journal.message(m.t_lab, m.kind, m.experiment, m.task, m.attempt, m.device, m.payload)


def experiment(journal: Journal, r: RecordExperiment) -> None:
    journal.experiment(r.experiment)
