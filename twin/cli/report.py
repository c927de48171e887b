"""``twin report``: a run's summary again, from its journal alone (a killed run: how far it got; a run still
going: that it is)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape

from twin.core.printable import shell_word
from twin.cli.common import _fail, app, console
from twin.core.errors import TwinError


@app.command()
def report(journal: Annotated[Path, typer.Argument(help="a run's journal, runs/<run>.db (or a lab's directory of "
                                                     "journals: each campaign's)")],
           as_json: Annotated[bool, typer.Option("--json", help="print it as JSON: state (finished, running, "
                                                                "interrupted, never_started) and the summary or how "
                                                                "far it got, for a script")] = False) -> None:
    """Print a run's summary again from its journal (a killed run: how far it got, and how to resume it)."""
    from twin.campaign.journal_read import no_such_journal  # the journal's readers, when the command runs

    if not journal.exists():
        _fail(no_such_journal(journal))
    if journal.is_dir():  # a lab of several campaigns: each campaign's journal, and how to resume the lab
        dbs = sorted(journal.glob("*.db"))
        if not dbs:
            _fail(TwinError(f"{journal}: no journals (<campaign>.db) here"))
        states = {db.stem: _state(db) for db in dbs}
        if as_json:
            console.print_json(json.dumps({"lab": str(journal), "campaigns": {name: _plain(state) for name, state
                                                                                in states.items()}}))
            return
        for db in dbs:
            console.print(f"[bold]{escape(db.stem)}[/] ({escape(str(db))})", highlight=False, markup=True)
            _render(states[db.stem])
        return
    state = _state(journal)
    if as_json:
        console.print_json(json.dumps(_plain(state)))
    else:
        _render(state)


def _plain(state: dict[str, Any]) -> dict[str, Any]:
    """A state as JSON holds it: the summary as ``twin run --json`` prints it."""
    return {**state, "summary": state["summary"].to_dict()} if "summary" in state else state


def _state(journal: Path) -> dict[str, Any]:
    """What a journal says of its run: ``state`` finished (with its ``summary``), running or interrupted (with
    ``so_far``), or never_started (with ``why``); ``resume_with``: what `twin resume` takes to go on with it — the
    journal, or for a campaign of a lab of several, the lab's directory (a directory of other journals is not
    one)."""
    from twin.campaign.journal_lock import writer
    from twin.campaign.journal_read import read_events, read_run
    from twin.campaign.summary import Summary
    from twin.runtime.resume import interrupted

    try:
        data = read_run(journal)
        got = interrupted(journal) if "summary" not in data else {}
        never = [] if "summary" in data else read_events(journal, "campaign.not_started")
    except TwinError as exc:
        _fail(exc)
    out: dict[str, Any] = {"journal": str(journal)}
    home = journal.parent if "lab" in data else None  # a lab's campaign: the lab resumes as one
    if never:  # a campaign of a lab that stopped, or failed to start, before it began
        try:
            why = json.loads(never[-1]["detail"])
        except (TypeError, ValueError):
            why = never[-1]["detail"]
        return {**out, "state": "never_started", "why": why}
    if "summary" not in data:
        holder = writer(journal)
        running = holder is not None
        return {**out, "state": "running" if running else "interrupted", "so_far": got,
                "writer": holder or None, "resume_with": None if running else str(home or journal)}
    summary = Summary.from_dict(data["summary"])
    summary.journal = str(journal)  # the file read: a journal copied or moved names where it was written
    return {**out, "state": "finished", "summary": summary, "resume_with":
            str(home or journal) if summary.resumable else None}


def _render(state: dict[str, Any]) -> None:
    journal = state["journal"]
    if state["state"] == "never_started":
        console.print(f"{journal}: never started — {state['why']}", highlight=False, soft_wrap=True)
        return
    if state["state"] in ("running", "interrupted"):
        got = state["so_far"]
        shown = {"pending": "not finished", "running": "not finished"}
        counts: dict[str, int] = {}
        for status, n in got["experiments"].items():
            counts[shown.get(status, status)] = counts.get(shown.get(status, status), 0) + n
        states = ", ".join(f"{n} {status}" for status, n in sorted(counts.items())) or "none proposed yet"
        so_far = f"{got['lab_hours']:.2f} lab-h with {got['events']} events on disk; experiments: {states}"
        if state["state"] == "running":
            holder = state["writer"]
            console.print(f"{journal}: running — {f'process {holder}' if holder else 'another process'} is writing "
                          f"it now. The run of {got['scenario']} has got to {so_far}. Report it again when it ends",
                          highlight=False, soft_wrap=True)
            return
        console.print(f"{journal}: interrupted — the run of {got['scenario']} was killed before it finished. It got "
                      f"to {so_far}. Continue it with: twin resume {shell_word(state['resume_with'])}",
                      highlight=False, soft_wrap=True)
        return
    from twin.view.report import render_summary

    render_summary(state["summary"], console, state["resume_with"])
