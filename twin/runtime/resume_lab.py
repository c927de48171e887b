"""``twin resume JOURNALS/``: continue a lab of several campaigns that was killed, or stopped by Ctrl-C or SIGTERM,
from its campaigns' journals.

In virtual time the lab is deterministic, as one campaign is (``twin.runtime.resume``): it is re-executed from
the start on the lab file and seed its journals recorded, every campaign's events checked against its journal's
prefix as they are written (a stopped lab's up to its stop); the first that differs stops the resume with an error
naming the campaign and the event, and the journals are left as they were. The resumed journals replace them only
when the lab ends. On a live clock the lab is rebuilt from the inputs it journalled (``twin.campaign.lab_replay``;
a stopped lab's without its stop).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any
import shutil
import time
from pathlib import Path

from twin.core.printable import shell_word
from twin.campaign.journal import Journal
from twin.campaign.journal_read import read_events, read_inputs, read_run
from twin.campaign.lab_replay import rebuild_lab
from twin.campaign.summary import LabSummary
from twin.runtime.resume import CheckedJournal, ResumeError, before_stop, replace
from twin.scenario import Scenario, parse
from twin.scenario.sharing import campaign_scenarios
from twin.view.lab_observer import SharedLabObserver

log = logging.getLogger(__name__)


def recorded_lab(path: str | Path) -> tuple[Scenario, dict[str, list[tuple]]]:
    """The lab file a killed lab ran, and each campaign's journalled events."""
    from twin.runtime.shared_run import LAB_INPUTS

    where = Path(path)
    dbs = sorted(where.glob("*.db"))
    if not dbs and (where / LAB_INPUTS).exists():  # a served lab that had no campaign yet
        lab = read_run(where / LAB_INPUTS).get("lab")
        if lab is None:
            raise ResumeError(f"{where / LAB_INPUTS}: it does not say which lab file it ran; serve the lab again")
        return parse(lab, f"{where / LAB_INPUTS}: the journal's lab file", lab_only=True), {}
    if not dbs:
        raise ResumeError(f"{where}: no campaign journals (<campaign>.db) here; a lab's journals are written to "
                          "runs/<lab>-seed<N>-<time>/ by default")
    lab, prefixes, ended, scenarios, stopped, resumable = None, {}, [], {}, "", ""
    for db in dbs:
        data = read_run(db)
        prefixes[db.stem] = [tuple(row.values()) for row in read_events(db)]  # damage is named
        if "lab" not in data:
            raise ResumeError(f"{db}: the journal does not say which lab file it ran in (a campaign run on its own: "
                              f"twin resume {shell_word(db)}; or a lab run before labs journalled it: run it again)")
        lab = lab or data["lab"]
        scenarios[db.stem] = data.get("scenario")
        summary = data.get("summary")
        if summary is not None:
            ended.append(db.stem)
            why = str(summary.get("stopped") or "") if isinstance(summary, dict) else ""
            if why and "resumable" not in summary:
                raise ResumeError(f"{db}: the campaign was stopped ({why}) by a labtwin older than the resume of a "
                                  "stopped lab, and its summary does not say whether the stop came from outside: run "
                                  f"the lab again (twin run); twin report {shell_word(db)} shows how far it got")
            stopped = stopped or why
            resumable = resumable or (why if isinstance(summary, dict) and summary.get("resumable") else "")
    if len(ended) == len(dbs) and stopped and not resumable:
        raise ResumeError(f"{where}: the lab ended ({stopped}): its campaigns ended on their own or their operators "
                          "stopped them, not the lab as a whole by Ctrl-C or SIGTERM, and resumed it would end the "
                          f"same way; run it again (twin run), and twin report {shell_word(dbs[0])} shows how far one "
                          "got")
    if len(ended) == len(dbs) and not resumable:
        raise ResumeError(f"{where}: every campaign of the lab finished; nothing to resume (twin report "
                          f"{shell_word(dbs[0])} shows one)")
    s = parse(lab, f"{dbs[0]}: the journal's lab file", lab_only=True)  # a served lab's file may have no workflow
    for name, cs in campaign_scenarios(s, s.name).items():
        if name in scenarios and parse(scenarios[name], f"{where / (name + '.db')}: the journal's scenario"
                                       ).model_dump() != cs.model_dump():
            raise ResumeError(f"{where / (name + '.db')}: the campaign's scenario differs from what its lab file "
                              "makes of it now (the code changed since the run); run the lab again instead (twin run)")
    if resumable:  # a re-run goes on where the stop came
        prefixes = {name: before_stop(prefix) for name, prefix in prefixes.items()}
    return s, prefixes


def resume_lab(path: str | Path, handle_signals: bool = True, observer: SharedLabObserver | None = None,
               on_start: Callable[[Any], None] | None = None, runtime: str = "auto",
               reopen: Callable[[], SharedLabObserver] | None = None) -> LabSummary:
    """Continue a killed virtual-time lab from its journals (``twin resume JOURNALS/``); see the module.
    ``runtime`` and ``reopen``: as ``run_shared`` takes them, for the re-run of a virtual-time lab."""
    from twin.runtime.shared_run import run_shared

    where = Path(path)
    s, prefixes = recorded_lab(where)
    if s.clock.mode != "virtual":
        return _resume_live(where, s, prefixes, handle_signals, observer, on_start)
    resuming = where.with_name(where.name + ".resuming")
    shutil.rmtree(resuming, ignore_errors=True)
    checked: dict[str, CheckedJournal] = {}

    def make(p: Path) -> Journal:
        checked[p.stem] = CheckedJournal(p, prefixes.get(p.stem, []), where / p.name)
        return checked[p.stem]

    try:
        summary = run_shared(s, resuming, handle_signals=handle_signals, observer=observer, make_journal=make,
                             runtime=runtime, reopen=reopen)
        for name, prefix in prefixes.items():
            done = checked[name].checked if name in checked else 0
            if done < len(prefix):
                raise ResumeError(f"{where / (name + '.db')}: the re-run ended after {done} of the journal's "
                                  f"{len(prefix)} events; run the lab again instead (twin run)")
    except ResumeError as exc:
        shutil.rmtree(resuming, ignore_errors=True)
        first = exc  # the lab's end journals every campaign's summary, which then differs too: name the first
        while isinstance(first.__context__, ResumeError):
            first = first.__context__
        raise first from None
    except BaseException:
        shutil.rmtree(resuming, ignore_errors=True)
        raise
    for db in resuming.glob("*.db"):
        replace(db, where / db.name)
    shutil.rmtree(resuming, ignore_errors=True)
    log.info("resumed %s: %d recorded events checked", where, sum(len(p) for p in prefixes.values()))
    return dataclasses.replace(summary, journals=str(where))


def _resume_live(where: Path, s: Scenario, prefixes: dict[str, list[tuple]], handle_signals: bool,
                 observer: SharedLabObserver | None, on_start: Callable[[Any], None] | None) -> LabSummary:
    """A lab on a scaled or wall clock: rebuilt from the inputs it journalled (``twin.campaign.lab_replay``), every
    campaign's journal written again from the rebuild and checked against what it held; lab time goes on from
    there, and the steps it had in the lab are asked after."""
    from twin.core.clock import LabClock
    from twin.runtime.resume import _still_running
    from twin.runtime.shared_run import LAB_INPUTS, _live, _parts, shared_drivers
    from twin.runtime.standby import standby_drivers

    inputs = where / LAB_INPUTS
    if not inputs.exists():
        raise ResumeError(f"{where}: no {LAB_INPUTS} here: the lab ran before live labs journalled their inputs; "
                          "run it again (twin run)")
    run_data = read_run(inputs)
    try:
        batches = read_inputs(inputs)
    except ValueError as exc:
        raise ResumeError(f"{inputs}: damaged ({exc}): run the lab again (twin run)") from None
    serving, external = bool(run_data.get("serving")), set(run_data.get("external") or ())
    resuming = where.with_name(where.name + ".resuming")
    shutil.rmtree(resuming, ignore_errors=True)
    resuming.mkdir(parents=True)
    checked: dict[str, CheckedJournal] = {}

    def journal_for(name: str, cs: Scenario) -> Journal:
        def make(p: Path) -> Journal:
            checked[name] = CheckedJournal(p, prefixes.get(name, []), where / p.name)
            return checked[name]
        return _parts(cs, resuming / f"{name}.db", external, s, make)[0]

    try:
        rebuilt = rebuild_lab(s, campaign_scenarios(s, s.name), batches, journal_for, serving)
        for name, prefix in prefixes.items():
            done = checked[name].checked if name in checked else 0
            if done < len(prefix):
                raise ResumeError(f"{where / (name + '.db')}: the lab's inputs rebuild {done} of the journal's "
                                  f"{len(prefix)} events; run the lab again instead (twin run)")
        for journal in checked.values():
            journal.close()
    except BaseException:
        shutil.rmtree(resuming, ignore_errors=True)
        raise
    probe = LabClock("wall")
    running = probe.run(_still_running(s, probe))
    if running:
        shutil.rmtree(resuming, ignore_errors=True)
        raise ResumeError(f"{where}: the lab is still running ({running}); a second one would dispatch the same "
                          "steps. Stop it first, or watch it (twin watch)")
    for db in resuming.glob("*.db"):
        replace(db, where / db.name)
    shutil.rmtree(resuming, ignore_errors=True)
    log.info("resuming lab %s at %.0f lab-s: %d input batches replayed", where, rebuilt.now, len(batches))
    scenarios = rebuilt.scenarios
    drivers, per_device = shared_drivers(scenarios, skip=external) if scenarios else (
        standby_drivers(s, external), {})
    parts = {n: (Journal(where / f"{n}.db", append=True),
                 *_parts_of(cs, rebuilt.planner_asks.get(n, []), rebuilt.shared.cores[n].history))
             for n, cs in scenarios.items()}
    clock = LabClock(s.clock.mode, s.clock.speed, start=rebuilt.now)
    return clock.run(_live(s, clock, scenarios, drivers, per_device, parts, where, time.perf_counter(),
                           handle_signals, serving=external if serving else None, on_start=on_start,
                           trust_modules=bool(run_data.get("trust_modules")),
                           observer=observer, rebuilt=rebuilt, external=external))


def _parts_of(cs: Scenario, asks: list, history: list) -> tuple:
    """A campaign's planner, caught up with the questions it had answered (``caught_up``), and scheduler."""
    from twin.runtime.checked_planner import caught_up
    from twin.runtime.lab import make_planner, make_scheduler

    return caught_up(make_planner(cs), cs.campaign.planner, asks, history), make_scheduler(cs)
