"""``twin resume RUN.db``: continue a campaign that was killed, or stopped from outside (Ctrl-C, SIGTERM,
``twin ctl stop``), from its journal.

A virtual-time campaign is deterministic, so it is re-executed from
the start on the scenario and seed the journal recorded, and every event is
checked against the journal's prefix as it is written (a stopped one's up to its
stop): the first that differs stops the resume with an error naming it (the code, a driver or a
plugin changed since the run), and the journal is left as it was.
The resumed journal replaces it only when the campaign ends,
and equals the journal of the same campaign never killed or stopped.

A scaled or wall-clock campaign is rebuilt from the inputs it journalled
(``twin.campaign.replay``; a stopped one as it was just before its stop) and taken over by the asyncio runtime;
the journal goes on, its stop kept in the history.
A campaign that stopped itself (its lab hours spent, a stall) would only stop again, and is refused.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from twin.core.printable import shell_word
from twin.campaign import CampaignCore
from twin.campaign.journal import Journal
from twin.campaign.journal_read import read_events, read_inputs, read_run, reading
from twin.campaign.journal_lock import held
from twin.campaign.replay import rebuild
from twin.campaign.summary import Summary
from twin.core import keys
from twin.core.bus.presence import present
from twin.core.clock import LabClock
from twin.core.errors import TwinError
from twin.core.numbers import finite
from twin.runtime.checked_planner import caught_up
from twin.runtime.lab import make_bus, make_planner, run, run_async
from twin.view.observer import LabObserver
from twin.view.watch import RecordOptions
from twin.scenario import Scenario, parse


log = logging.getLogger(__name__)


class ResumeError(TwinError):
    """A journal cannot be resumed, or the re-executed campaign left its recorded path."""


class CheckedJournal(Journal):
    """A journal that checks each event it writes against a recorded prefix."""

    def __init__(self, path: str | Path, prefix: list[tuple], source: Path) -> None:
        super().__init__(path)
        self._prefix, self._source = prefix, source
        self.label = str(source)

    def _append(self, *row: Any) -> None:
        n = self._seq
        if n < len(self._prefix) and tuple(self._prefix[n][1:]) != row:
            recorded = self._prefix[n]
            raise ResumeError(
                f"{self._source}: event {n + 1} differs from the journal: it recorded "
                f"{recorded[2]!r} at {recorded[1]:.3f} lab-s ({_short(recorded[7])}), the re-run made {row[1]!r} at "
                f"{row[0]:.3f} lab-s ({_short(row[6])}). The code, a driver or a plugin changed since the run; "
                "run the campaign again instead (twin run).")
        super()._append(*row)

    @property
    def checked(self) -> int:
        return min(self._seq, len(self._prefix))


def _short(detail: Any, n: int = 80) -> str:
    text = "" if detail is None else str(detail)
    return text if len(text) <= n else text[:n] + "…"


def recorded(path: str | Path) -> tuple[Scenario, list[tuple]]:
    """The scenario and the events a killed run's journal holds; a stopped run's, up to its stop."""
    path = Path(path)
    data = read_run(path)
    if "lab" in data:
        raise ResumeError(f"{path}: a campaign of a lab of several, which resumes as one: twin resume "
                          f"{shell_word(path.parent)}")
    summary = data.get("summary")
    if summary is not None:
        stopped = summary.get("stopped") if isinstance(summary, dict) else None
        if stopped and "resumable" not in summary:
            raise ResumeError(f"{path}: the campaign was stopped ({stopped}) by a labtwin older than the resume of a "
                              "stopped campaign, and its summary does not say whether the stop came from outside: "
                              f"run it again (twin run); twin report {shell_word(path)} shows how far it got")
        if stopped and not summary.get("resumable"):
            raise ResumeError(f"{path}: the campaign ended ({stopped}), not stopped from outside (Ctrl-C, SIGTERM, "
                              f"twin ctl stop): resumed, it would end the same way; run it again (twin run) with what "
                              f"it lacked, and twin report {shell_word(path)} shows how far it got")
        if not stopped:
            raise ResumeError(f"{path}: the campaign finished; nothing to resume (twin report {shell_word(path)} "
                              "shows it)")
    if "scenario" not in data:
        raise ResumeError(f"{path}: the journal holds no scenario; it was killed before it began")
    prefix = [tuple(row.values()) for row in read_events(path)]  # in the table's column order; damage is named
    if summary is not None:  # a re-run goes on where the stop came
        prefix = before_stop(prefix)
    return parse(data["scenario"], f"{path}: the journal's scenario"), prefix


def before_stop(prefix: list[tuple]) -> list[tuple]:
    """A stopped campaign's journalled events up to its stop: those a re-run must make again. A campaign of a lab
    stops there too, or where it was said never to have started, or at its summary (one that had finished is summed
    up when the lab ends, at the stop)."""
    ends = ("campaign.stopping", "campaign.not_started", "campaign.summary")
    return prefix[:next((i for i, row in enumerate(prefix) if row[2] in ends), len(prefix))]


def interrupted(path: str | Path) -> dict[str, Any]:
    """How far a killed run got, from what its journal committed."""
    with reading(path) as db:
        events, t_lab, last = db.execute("SELECT COUNT(*), MAX(t_lab), MAX(seq) FROM events").fetchone()
        statuses = dict(db.execute("SELECT status, COUNT(*) FROM experiments GROUP BY status").fetchall())
    if (t_lab is not None and not finite(t_lab)) or (last or 0) != events:
        read_events(path)  # names the damaged row, or the first missing one
    name = read_run(path, needs=("scenario",))["scenario"].get("name", "?")
    return {"scenario": str(name), "events": events, "lab_hours": (t_lab or 0.0) / 3600 if finite(t_lab) else 0.0,
            "experiments": statuses}


def replace(resumed: Path, killed: Path) -> None:
    for suffix in ("-wal", "-shm"):
        Path(f"{killed}{suffix}").unlink(missing_ok=True)
    os.replace(resumed, killed)


def resume(path: str | Path, *, on_progress: Callable[[CampaignCore], None] | None = None,
           record: RecordOptions | None = None, observer: LabObserver | None = None,
           runtime: str = "auto") -> Summary:
    """Continue a killed or stopped campaign from its journal (``twin resume``); see ``twin.runtime.resume``."""
    path = Path(path)
    s, prefix = recorded(path)
    if s.clock.mode != "virtual":
        return _resume_live(path, s, on_progress, observer)  # appends to the journal: its writer's lock, as a run's
    with held(path):  # a run still writing it is not resumed, nor does one start on it while this re-runs
        return _resume_virtual(path, s, prefix, on_progress, record, observer, runtime)


def _resume_virtual(path: Path, s: Scenario, prefix: list, on_progress: Callable[[CampaignCore], None] | None,
                    record: RecordOptions | None, observer: LabObserver | None, runtime: str) -> Summary:
    resuming = path.with_name(path.name + ".resuming")
    checked: list[CheckedJournal] = []

    def make(p: Path) -> Journal:
        checked.append(CheckedJournal(p, prefix, path))
        return checked[-1]

    try:
        summary = run(s, journal=resuming, on_progress=on_progress, record=record, observer=observer,
                      runtime=runtime, make_journal=make)
        if checked[-1].checked < len(prefix):
            raise ResumeError(f"{path}: the re-run ended after {checked[-1].checked} of the journal's "
                                f"{len(prefix)} events; run the campaign again instead (twin run)")
    except BaseException:
        for suffix in ("", "-wal", "-shm"):
            Path(f"{resuming}{suffix}").unlink(missing_ok=True)
        raise
    replace(resuming, path)
    log.info("resumed %s: %d recorded events checked, %d in all", path, len(prefix), summary.events)
    return summary


def _resume_live(path: Path, s: Scenario, on_progress: Callable[[CampaignCore], None] | None,
                 observer: LabObserver | None) -> Summary:
    """A scaled or wall-clock campaign: its core rebuilt from the inputs it journalled (a stopped one's up to its
    stop); lab time goes on from there; the steps it had in the lab are asked after (still running, finished, or
    lost and retried; cancelled by the stop: sent again)."""
    try:
        batches = read_inputs(path)
    except ValueError as exc:
        raise ResumeError(f"{path}: its journalled inputs are damaged ({exc}): run the campaign again (twin run)") from None
    if not batches:
        raise ResumeError(f"{path}: no inputs were journalled (the campaign was killed before it began, or ran "
                          "before live campaigns journalled them): run it again instead (twin run)")
    secret = read_run(path).get("attempt_secret")
    rebuilt = rebuild(s, batches, secret=bytes.fromhex(secret) if isinstance(secret, str) else None)
    if rebuilt.core.finished:
        raise ResumeError(f"{path}: the campaign had finished; nothing to resume")
    probe = LabClock("wall")
    running = probe.run(_still_running(s, probe))
    if running:
        raise ResumeError(f"{path}: the campaign is still running ({running}); a second orchestrator would "
                          "dispatch the same steps. Stop it first, or watch it (twin watch); if it was killed just "
                          f"now, its token lasts one link lease ({s.bus.lease_ms} ms): try again then")
    # before the lab's time runs
    planner = caught_up(make_planner(s), s.campaign.planner, rebuilt.planner_asks, rebuilt.core.history)
    clock = LabClock(s.clock.mode, s.clock.speed, start=rebuilt.now)
    external = set(read_run(path).get("external") or ())
    log.info("resuming %s at %.0f lab-s: %d input batches replayed", path, rebuilt.now, len(batches))
    return clock.run(run_async(s, clock, path, external, on_progress, observer,
                               make_journal=lambda p: Journal(p, append=True), rebuilt=rebuilt, planner=planner))


async def _still_running(s: Scenario, clock: LabClock, wait_s: float = 1.0) -> str:
    """Why the campaign of ``s`` looks alive on its bus ('' when it does not): its token, or its endpoint taken."""
    if s.bus.kind == "memory":
        return ""  # one process's bus: nothing else can be on it
    bus = make_bus(s, clock)
    try:
        await bus.start()
    except TwinError as exc:
        return f"its bus endpoint is in use: {exc}"
    try:
        seen = await present(bus, [keys.orchestrator(s.lab)], wait_s)
    finally:
        await bus.close()
    return f"its token {seen[0]} is on the bus" if seen else ""
