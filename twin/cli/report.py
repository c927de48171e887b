"""``twin report``: a run's summary again, from its journal alone (a killed run: how far it got; a run still
going: that it is)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from twin.campaign.journal import no_such_journal, read_events, read_run
from twin.campaign.journal_lock import writer
from twin.campaign.summary import Summary
from twin.cli.common import _fail, app, console
from twin.core.errors import TwinError
from twin.view.report import render_summary


@app.command()
def report(journal: Annotated[Path, typer.Argument(help="a run's journal, runs/<run>.db (or a lab's directory of "
                                                     "journals: each campaign's)")]) -> None:
    """Print a run's summary again from its journal (a killed run: how far it got, and how to resume it)."""
    if not journal.exists():
        _fail(no_such_journal(journal))
    if journal.is_dir():  # a lab of several campaigns: each campaign's journal, and how to resume the lab
        dbs = sorted(journal.glob("*.db"))
        if not dbs:
            _fail(TwinError(f"{journal}: no journals (<campaign>.db) here"))
        for db in dbs:
            console.print(f"[bold]{escape(db.stem)}[/] ({escape(str(db))})", highlight=False, markup=True)
            _report(db, resume_with=journal)
        return
    _report(journal)


def _report(journal: Path, resume_with: Path | None = None) -> None:
    from twin.runtime.resume import interrupted

    try:
        data = read_run(journal)
        got = interrupted(journal) if "summary" not in data else {}
        never = [] if "summary" in data else read_events(journal, "campaign.not_started")
    except TwinError as exc:
        _fail(exc)
    if never:  # a campaign of a lab that stopped, or failed to start, before it began
        try:
            why = json.loads(never[-1]["detail"])
        except (TypeError, ValueError):
            why = never[-1]["detail"]
        console.print(f"{journal}: never started — {why}", highlight=False, soft_wrap=True)
        return
    if "summary" not in data:
        shown = {"pending": "not finished", "running": "not finished"}
        counts: dict[str, int] = {}
        for status, n in got["experiments"].items():
            counts[shown.get(status, status)] = counts.get(shown.get(status, status), 0) + n
        states = ", ".join(f"{n} {status}" for status, n in sorted(counts.items())) or "none proposed yet"
        so_far = f"{got['lab_hours']:.2f} lab-h with {got['events']} events on disk; experiments: {states}"
        holder = writer(journal)
        if holder is not None:
            console.print(f"{journal}: running — {f'process {holder}' if holder else 'another process'} is writing "
                          f"it now. The run of {got['scenario']} has got to {so_far}. Report it again when it ends",
                          highlight=False, soft_wrap=True)
            return
        console.print(f"{journal}: interrupted — the run of {got['scenario']} was killed before it finished. It got "
                      f"to {so_far}. Continue it with: twin resume {resume_with or journal}",
                      highlight=False, soft_wrap=True)
        return
    summary = Summary.from_dict(data["summary"])
    summary.journal = str(journal)  # the file read: a journal copied or moved names where it was written
    render_summary(summary, console, resume_with or (journal.parent if "lab" in data else None))
