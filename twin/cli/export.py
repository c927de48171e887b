"""``twin export``: a run's journal as CSV, Parquet or JSON-lines tables, with its provenance."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from twin.cli.common import _fail, app, say_if_still_written
from twin.core.errors import TwinError


#: twin.tools.export.WHAT, here as text: the export's module imports the journal's readers, when the command runs
ALL_TABLES = "experiments,attempts,devices,consumables,decisions,operator"


@app.command("export")
def export_run(
    journal: Annotated[Path, typer.Argument(help="the run's journal, e.g. runs/quantum_dots-seed0-….db (or a lab's "
                                                 "directory of journals: each campaign's, to OUT/<campaign>)")],
    fmt: Annotated[str, typer.Option("--format", help="csv | parquet | jsonl")] = "csv",
    what: Annotated[str, typer.Option(help="the tables, comma-separated: experiments, attempts, devices, "
                                           "consumables, decisions, operator")] = ALL_TABLES,
    out: Annotated[Optional[Path], typer.Option(help="the directory to write (default: beside the journal, "
                                                     "<journal>-export)")] = None,
) -> None:
    """Write a run's experiments, attempts, devices, consumables, decisions and operator acts as tables (one file
    each) and its provenance (scenario hash, seed, versions, files and their hashes, operator acts) as
    provenance.json."""
    from twin.tools.export import export

    tables = [w.strip() for w in what.split(",") if w.strip()]
    target = out or journal.with_name(f"{journal.stem if journal.is_file() else journal.name}-export")
    try:
        if journal.is_dir():  # a lab of several campaigns: each campaign's journal, to a directory of its own
            dbs = sorted(journal.glob("*.db"))
            if not dbs:
                raise TwinError(f"{journal}: no journals (<campaign>.db) here")
            written = [path for db in dbs for path in export(db, target / db.stem, fmt, tables)]
        else:
            written = export(journal, target, fmt, tables)
    except TwinError as exc:
        _fail(exc)
    for path in written:
        print(path)  # whole paths, for scripts: never wrapped to the terminal
    say_if_still_written(journal, "the export")
