"""A live lab of several campaigns, rebuilt from the inputs it journalled.

A live ``LiveLab`` writes, before each ``SharedLab.advance`` and before any command that advance sends leaves,
what the lab was given since the last one (``<journals>/lab.inputs``): device messages and presence, the lab's
own timers and its one scheduler's answers (``orchestrator.lab_scheduler``), each campaign's timers, planner and scheduler answers and operator commands, campaigns submitted
(with their scenario and token secret), a stop, and the runtime's own remarks in a campaign's journal. The lab
is deterministic, so feeding the same batches to a new ``SharedLab`` rebuilds the same state — and the same
journal of every campaign, which is written again from the rebuild (a campaign journal may have lost its last
rows when the process was killed; the lab's inputs never lag what was sent).

Items of a batch: ``["dev", input]``, ``["lab", input]``, ``["seat", campaign, input]``, ``["add", entry,
scenario, secret]``, ``["stop", reason]``, ``["note", campaign, kind, detail, t_lab]`` (``input`` as
``twin.campaign.replay.encode`` writes it). The first batch is ``{"start": true, "secrets": {campaign: hex}}``;
a batch with ``"advance": false`` (a remark written ahead of the campaign's journal) is taken in without an
advance. A stop that ``twin resume`` undid is left out with what followed it, up to the ``{"resumed": why}``
batch the resumed lab wrote (``replay.unstopped``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from twin.campaign.events import (Ask, CancelTimer, Decided, Note, Proposed, RecordExperiment, RecordMessage,
                                  SetTimer, TimerFired, TimerKey)
from twin.campaign.journal import Journal
from twin.campaign.replay import PlannerAsk, ReplayError, decode_input, encode, replay_batches, unstopped
from twin.campaign.sharing import LAB, SharedLab
from twin.scenario.model import Scenario, SharedCampaign

__all__ = ["RebuiltLab", "encode", "rebuild_lab"]


@dataclass
class RebuiltLab:
    shared: SharedLab
    now: float
    scenarios: dict[str, Scenario]  # every campaign's, those submitted included
    timers: dict[tuple[str, TimerKey], float] = field(default_factory=dict)  # (campaign or LAB, key) -> due
    asked: dict[str, Ask] = field(default_factory=dict)  # a question a campaign still waits on
    stopped: str = ""  # the stop (a Ctrl-C's) the lab ended with, left out: its steps in the lab were cancelled
    planner_asks: dict[str, list[PlannerAsk]] = field(default_factory=dict)  # each campaign's planner's, answered
    plan_asked: dict[str, Ask] = field(default_factory=dict)  # a campaign's planner's question not answered yet


def rebuild_lab(lab: Scenario, scenarios: dict[str, Scenario], batches: list[tuple[float, Any]],
                journal_for: Callable[[str, Scenario], Journal], serving: bool = False) -> RebuiltLab:
    """Feed a live lab's journalled inputs to a new ``SharedLab``; each campaign's actions go to the journal
    ``journal_for(name, scenario)`` gives (the commands it sent are not sent again)."""
    if not batches or "start" not in batches[0][1]:
        raise ReplayError("the lab's inputs do not begin with its start: run the lab again (twin run)")
    secrets = {n: bytes.fromhex(h) for n, h in (batches[0][1].get("secrets") or {}).items()}
    out = RebuiltLab(SharedLab(lab, scenarios, secrets, serving), 0.0, dict(scenarios))
    batches, out.stopped, stopped_at = unstopped(batches, "items", _lab_stop)
    journals = {name: journal_for(name, s) for name, s in scenarios.items()}
    replay_batches(batches, lambda now, batch: _replay(out, journals, journal_for, now, batch), "lab input batch",
                   "the lab")
    out.now = max(out.now, stopped_at)  # lab time went on to the stop: the resumed clock starts there
    return out


def _lab_stop(item: Any) -> str:
    """Why a lab input stopped the lab (a Ctrl-C's, journalled by ``LiveLab.stop``), or ""."""
    ok = isinstance(item, list) and len(item) == 2 and item[0] == "stop" and isinstance(item[1], str)
    return item[1] if ok else ""


def _replay(out: RebuiltLab, journals: dict[str, Journal], journal_for: Callable[[str, Scenario], Journal],
            now: float, batch: dict[str, Any]) -> None:
    out.now = now
    shared = out.shared
    if "start" in batch:
        _track(out, journals, now, shared.start(now))
        return
    for item in batch["items"]:
        what = item[0]
        if what == "dev":
            shared.feed_device(decode_input(item[1]))
        elif what == "lab":  # its timer, or its one scheduler's answer
            event = decode_input(item[1])
            if type(event) is TimerFired:
                out.timers.pop((LAB, event.key), None)
            else:
                out.asked.pop(LAB, None)
            shared.feed(LAB, event)
        elif what == "seat":
            name, event = item[1], decode_input(item[2])
            if type(event) is TimerFired:
                out.timers.pop((name, event.key), None)
            if type(event) in (Proposed, Decided):
                out.asked.pop(name, None)
            if type(event) is Proposed and name in out.plan_asked:
                out.planner_asks.setdefault(name, []).append(PlannerAsk.of(out.plan_asked.pop(name)))
            shared.feed(name, event)
        elif what == "add":
            entry, scenario = SharedCampaign.model_validate(item[1]), Scenario.model_validate(item[2])
            shared.add(entry, scenario, bytes.fromhex(item[3]))
            out.scenarios[entry.name] = scenario
            journals[entry.name] = journal_for(entry.name, scenario)
        elif what == "stop":
            shared.stop(item[1], outside=True)  # only a Ctrl-C's is journalled (LiveLab.stop)
        elif what == "note":
            journals[item[1]].note(Note(item[4], item[2], detail=item[3]))
        else:
            raise ValueError(f"unknown lab input {what!r}")
    if batch.get("advance", True):
        _track(out, journals, now, shared.advance(now))


def _track(out: RebuiltLab, journals: dict[str, Journal], now: float, tagged: list[tuple[str, Any]]) -> None:
    """What a runtime would do with the actions, short of sending anything: journal them, keep the timers and
    questions pending."""
    for name, a in tagged:
        t = type(a)
        if t is SetTimer:
            out.timers[(name, a.key)] = now + a.delay
        elif t is CancelTimer:
            out.timers.pop((name, a.key), None)
        elif t is Ask:
            out.asked[name] = a
            if a.what == "plan":
                out.plan_asked[name] = a
        elif t is Note:
            journals[name].note(a)
        elif t is RecordMessage:
            journals[name].received(a)
        elif t is RecordExperiment:
            journals[name].experiment(a.experiment)
