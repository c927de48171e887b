"""``twin resume JOURNALS/``: continue a lab of several campaigns that was killed, from its campaigns' journals.

In virtual time the lab is deterministic, as one campaign is (``twin.runtime.resume``): it is re-executed from
the start on the lab file and seed its journals recorded, every campaign's events checked against its journal's
prefix as they are written; the first that differs stops the resume with an error naming the campaign and the
event, and the killed journals are left as they were. The resumed journals replace them only when the lab ends.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import sqlite3
from pathlib import Path

from twin.campaign.journal import Journal, read_run
from twin.campaign.summary import LabSummary
from twin.runtime.resume import CheckedJournal, ResumeError, replace
from twin.scenario import Scenario
from twin.scenario.sharing import campaign_scenarios
from twin.view.lab_observer import SharedLabObserver

log = logging.getLogger(__name__)


def recorded_lab(path: str | Path) -> tuple[Scenario, dict[str, list[tuple]]]:
    """The lab file a killed lab ran, and each campaign's journalled events."""
    where = Path(path)
    dbs = sorted(where.glob("*.db"))
    if not dbs:
        raise ResumeError(f"{where}: no campaign journals (<campaign>.db) here; a lab's journals are written to "
                          "runs/<lab>-seed<N>-<time>/ by default")
    lab, prefixes, ended, scenarios = None, {}, [], {}
    for db in dbs:
        try:
            data = read_run(db)
            with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
                prefixes[db.stem] = con.execute("SELECT * FROM events ORDER BY seq").fetchall()
        except sqlite3.DatabaseError as exc:
            raise ResumeError(f"{db}: not a labtwin journal ({exc})") from None
        if "lab" not in data:
            raise ResumeError(f"{db}: the journal does not say which lab file it ran in (a campaign run on its own: "
                              f"twin resume {db}; or a lab run before labs journalled it: run it again)")
        lab = lab or data["lab"]
        scenarios[db.stem] = data.get("scenario")
        if "summary" in data:
            ended.append(db.stem)
    if len(ended) == len(dbs):
        raise ResumeError(f"{where}: every campaign of the lab finished; nothing to resume (twin report "
                          f"{dbs[0]} shows one)")
    s = Scenario.model_validate(lab)
    for name, cs in campaign_scenarios(s, s.name).items():
        if name in scenarios and Scenario.model_validate(scenarios[name]).model_dump() != cs.model_dump():
            raise ResumeError(f"{where / (name + '.db')}: the campaign's scenario differs from what its lab file "
                              "makes of it now (the code changed since the run); run the lab again instead (twin run)")
    return s, prefixes


def resume_lab(path: str | Path, handle_signals: bool = True, observer: SharedLabObserver | None = None) -> LabSummary:
    """Continue a killed virtual-time lab from its journals (``twin resume JOURNALS/``); see the module."""
    from twin.runtime.shared_run import run_shared

    where = Path(path)
    s, prefixes = recorded_lab(where)
    if s.clock.mode != "virtual":
        raise ResumeError(f"{where}: a lab on a {s.clock.mode} clock cannot be resumed yet (its journals hold each "
                          "campaign's events, not the lab's turns); each campaign's journal is intact: twin report "
                          f"{where}/<campaign>.db")
    resuming = where.with_name(where.name + ".resuming")
    shutil.rmtree(resuming, ignore_errors=True)
    checked: dict[str, CheckedJournal] = {}

    def make(p: Path) -> Journal:
        checked[p.stem] = CheckedJournal(p, prefixes.get(p.stem, []), where / p.name)
        return checked[p.stem]

    try:
        summary = run_shared(s, resuming, handle_signals=handle_signals, observer=observer, make_journal=make)
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
