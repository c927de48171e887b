"""Reading a run's journal (``twin.campaign.journal`` writes it): read-only, and a file that is not one, or a row
labtwin never writes, raises ``NotAJournal`` naming the file and what is wrong, rather than failing whatever reads
the rows after."""

from __future__ import annotations

import contextlib
import json
import sqlite3
import urllib.parse
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from twin.campaign.events import Status
from twin.core.errors import TwinError
from twin.core.numbers import finite


class NotAJournal(TwinError):
    """A file that is not a labtwin journal (not SQLite, or not ours, or damaged)."""


def no_such_journal(path: str | Path) -> NotAJournal:
    return NotAJournal(f"{path}: no such journal; runs are written to runs/ by default")


@contextmanager
def reading(path: str | Path) -> Iterator[sqlite3.Connection]:
    """A journal opened read-only; a file that is not one raises ``NotAJournal`` naming it and why."""
    if not Path(path).exists():
        raise no_such_journal(path)
    if not Path(path).stat().st_size:
        raise NotAJournal(f"{path}: empty — the name a run claimed for its journal, and the run was stopped before it "
                          "wrote anything (or the file is not a journal); nothing to report, resume or export")
    # read-write opened, and read-only asked: a connection opened read-only cannot remove the -wal and -shm files it
    # makes beside a finished run's journal, and left them there; the name quoted, or '#' or '%20' in it misread
    uri = f"file:{urllib.parse.quote(str(path))}?mode=rw"
    try:
        with contextlib.closing(sqlite3.connect(uri, uri=True)) as db:
            db.execute("PRAGMA query_only = 1")
            db.execute("PRAGMA trusted_schema = 0")
            _only_tables(path, db)
            yield db
    except sqlite3.DatabaseError as exc:  # not SQLite, or not ours
        raise _not_ours(path, exc) from None


def _only_tables(path: str | Path, db: sqlite3.Connection) -> None:
    """A journal holds tables of plain columns, as labtwin writes them: a view, a virtual table or a computed column
    runs a query of someone else's on every read (a view of an endless recursive query held `twin report` for good,
    its memory growing), and a trigger on every write."""
    schema = db.execute("SELECT type, name, sql FROM sqlite_master WHERE type IN ('table', 'view', 'trigger')")
    for kind, name, sql in schema.fetchall():
        if kind == "table" and str(sql or "").upper().startswith("CREATE VIRTUAL"):
            kind = "virtual table"
        elif kind == "table":
            computed = [c[1] for c in db.execute(f"PRAGMA table_xinfo({_quoted(name)})") if c[6]]
            if not computed:
                continue
            kind, name = "computed column", f"{name}.{computed[0]}"
        raise NotAJournal(f"{path}: holds a {kind} ({str(name)[:60]!r}), which labtwin never writes: the journal was "
                          "altered, or is another program's database; nothing was read from it")


def _quoted(name: str) -> str:
    return '"' + str(name).replace('"', '""') + '"'


def _not_ours(path: str | Path, exc: Exception) -> NotAJournal:
    if "malformed" in str(exc):  # SQLite, cut short or overwritten in part
        return NotAJournal(f"{path}: a damaged database ({type(exc).__name__}: {exc}): cut short or overwritten in "
                           "part, so not a labtwin journal that can be read; if it was copied while its run wrote "
                           "it, copy it again (with its -wal file) once the run has ended")
    if "no such table" in str(exc):  # SQLite, without a journal's tables
        return NotAJournal(f"{path}: holds none of a labtwin journal's tables ({exc}): a run that has only just "
                           "started writing it (try again in a moment), or another program's database; twin run "
                           "writes journals to runs/")
    return NotAJournal(f"{path}: not a labtwin journal ({type(exc).__name__}: {exc}); twin run writes them to runs/")


# what labtwin writes under these keys of a journal's run table (the others are read where they are used)
_RUN_SHAPES: dict[str, type] = {"scenario": dict, "lab": dict, "summary": dict, "provenance": dict}


def read_run(path: str | Path, needs: tuple[str, ...] = ()) -> dict[str, Any]:
    """The journal's run table as a dict; one of ``needs`` missing, or a value of another shape than labtwin
    writes, raises ``NotAJournal`` naming the key."""
    with reading(path) as db:
        rows = db.execute("SELECT key, value FROM run").fetchall()
    run: dict[str, Any] = {}
    for key, value in rows:
        try:
            run[key] = json.loads(value)
        except (ValueError, TypeError, RecursionError):
            raise NotAJournal(f"{path}: its run table's {str(key)[:40]!r} is not JSON: {str(value)[:40]!r}; labtwin "
                              "never writes that, so the journal was altered or corrupted: run the campaign again "
                              "(twin run)") from None
    for key, shape in _RUN_SHAPES.items():
        if key in run and not isinstance(run[key], shape):
            raise NotAJournal(f"{path}: its run table's {key!r} is {str(run[key])[:40]!r}, not a mapping; labtwin "
                              "never writes that, so the journal was altered or corrupted")
    missing = [key for key in needs if key not in run]
    if missing:
        raise NotAJournal(f"{path}: its run table has no {' or '.join(map(repr, missing))}: the run was stopped "
                          "before it began, or the journal was altered")
    return run


_EXPERIMENT_JSON = ("params", "route", "outputs", "scores")
_EXPERIMENT_SHAPES = {"params": lambda v: isinstance(v, dict), "outputs": lambda v: v is None or isinstance(v, dict),
                      "scores": lambda v: v is None or isinstance(v, dict),
                      "route": lambda v: isinstance(v, list) and all(
                          isinstance(s, list) and len(s) in (2, 3) and isinstance(s[0], str) and isinstance(s[1], str)
                          and (len(s) == 2 or s[2] is None or isinstance(s[2], dict)) for s in v)}
_EXPERIMENT_WORDS = {"params": "a mapping", "outputs": "a mapping", "scores": "a mapping",
                     "route": "a list of [step, device type, params]"}
_WHAT_NOW = "run the campaign again (twin run); a finished run's summary is still shown by twin report"
_ALTERED = f"labtwin never writes such a row, so the journal was altered or corrupted: {_WHAT_NOW}"


_EXPERIMENT_COLUMNS = ("id", "params", "route", "status", "reason", "outputs", "scores", "attempts", "retries",
                       "degraded", "t_proposed", "t_done")
_STATUSES = tuple(status.value for status in Status)
_EVENT_COLUMNS = ("seq", "t_lab", "kind", "experiment", "task", "attempt", "device", "detail")
#: Past any campaign's lab time (``campaign.max_lab_hours`` is at most a million hours), and within what a recording's
#: timeline holds (nanoseconds in 64 bits: 9.2e9 s).
LATEST_LAB_S = 4.0e9


def _columns(path: str | Path, table: str, rows: list[dict[str, Any]], columns: tuple[str, ...]) -> None:
    missing = [c for c in columns if rows and c not in rows[0]]
    if missing:
        raise NotAJournal(f"{path}: its {table} table has no {', '.join(missing)} column; labtwin never writes such a "
                          f"table, so the journal was altered or corrupted: {_WHAT_NOW}")


def read_experiments(path: str | Path) -> list[dict[str, Any]]:
    """The journal's experiments in order; a row no labtwin wrote (an id that is not a whole number, a column
    that should be JSON and is not, a status or count of another kind) raises ``NotAJournal`` naming it."""
    with reading(path) as db:
        db.row_factory = sqlite3.Row
        rows = [dict(r) for r in db.execute("SELECT * FROM experiments ORDER BY id")]
    _columns(path, "experiments", rows, _EXPERIMENT_COLUMNS)
    for row in rows:
        damage = "its id is not a whole number" if type(row.get("id")) is not int else _experiment_damage(row)
        for column in _EXPERIMENT_JSON:
            text = row.get(column)
            if damage or text is None:
                continue
            try:
                value = json.loads(text)
            except (TypeError, ValueError, RecursionError):
                damage = f"its {column} is not JSON: {str(text)[:40]!r}"
                continue
            if not _EXPERIMENT_SHAPES[column](value):
                damage = f"its {column} is {str(text)[:40]!r}, not {_EXPERIMENT_WORDS[column]}"
        if damage:
            raise NotAJournal(f"{path}: experiment {str(row.get('id'))[:20]} is damaged ({damage}); {_ALTERED}")
    return rows


def _experiment_damage(row: dict[str, Any]) -> str:
    """What is wrong with an experiment row's plain columns, or ''."""
    if row["status"] not in _STATUSES:
        return f"its status is {str(row['status'])[:20]!r}, not one of {', '.join(_STATUSES)}"
    if type(row["reason"]) is not str:
        return "its reason is not text"
    for column in ("attempts", "retries", "degraded"):
        if type(row[column]) is not int or row[column] < 0:
            return f"its {column} is {str(row[column])[:20]!r}, not a whole number of them"
    for column in ("t_proposed", "t_done"):
        if (row[column] is not None or column == "t_proposed") and not _lab_time(row[column]):
            return f"its {column} is {str(row[column])[:20]!r}, not a lab time"
    return ""


def _lab_time(t: Any) -> bool:
    return finite(t) and -1.0 <= t <= LATEST_LAB_S


def read_events(path: str | Path, kind_like: str = "%") -> list[dict[str, Any]]:
    """The journal's events in order; a row no labtwin wrote (a time that is not a number, a detail that is not
    JSON, ...) raises ``NotAJournal`` naming it, rather than failing whatever reads the rows after."""
    with reading(path) as db:
        db.row_factory = sqlite3.Row
        rows = [dict(r) for r in db.execute("SELECT * FROM events WHERE kind LIKE ? ORDER BY seq", (kind_like,))]
    _columns(path, "events", rows, _EVENT_COLUMNS)
    for row in rows:
        damage = _damage(row)
        if damage:
            raise NotAJournal(f"{path}: event {row.get('seq')} is damaged ({damage}); {_ALTERED}")
    if kind_like == "%":
        for expected, row in enumerate(rows, 1):
            if row.get("seq") != expected:
                raise NotAJournal(f"{path}: event {expected} is missing (the next is {str(row.get('seq'))[:20]}); "
                                  "labtwin numbers a journal's events 1, 2, 3, ... and never deletes one, so the "
                                  f"journal was altered or corrupted: {_WHAT_NOW}")
    return rows


def _damage(row: dict[str, Any]) -> str:
    """What is wrong with an event row, or ''."""
    t = row.get("t_lab")
    if not finite(t):
        return f"its lab time is {str(t)[:20]!r}, not a number"
    if not _lab_time(t):
        return f"its lab time is {t:g} s, beyond any campaign's"
    if type(row.get("kind")) is not str or not row["kind"]:
        return "it has no kind"
    for field in ("experiment", "attempt"):
        if row.get(field) is not None and type(row[field]) is not int:
            return f"its {field} is {str(row[field])[:20]!r}, not a whole number"
    for field in ("task", "device"):
        if row.get(field) is not None and type(row[field]) is not str:
            return f"its {field} is not text"
    detail = row.get("detail")
    if detail is not None:
        try:
            json.loads(detail)
        except (TypeError, ValueError, RecursionError):
            return f"its detail is not JSON: {str(detail)[:40]!r}"
    return ""


def decision_id(seq: int) -> str:
    """The id of the decision message published with journal event ``seq``."""
    return f"orchestrator:j{seq}"


def decision_payload(row: dict[str, Any]) -> str:
    """The decision message a state-change row was published as, rebuilt from the row."""
    detail = {"experiment": row["experiment"], "task": row["task"], "attempt": row["attempt"],
              "device": row["device"], "info": json.loads(row["detail"]) if row["detail"] else None}
    return json.dumps({"v": 1, "kind": "decision", "id": decision_id(row["seq"]), "campaign": "",
                       "task": row["task"] or "", "attempt": row["attempt"] or 0, "sender": "orchestrator",
                       "t_lab": row["t_lab"], "body": {"what": row["kind"], "detail": detail}})


def as_messages(rows: list[dict[str, Any]]) -> list[str]:
    """The bus messages a run's events stand for, in journal order: what an observer saw."""
    return [r["detail"] if r["kind"].startswith("msg.") else decision_payload(r) for r in rows]


def read_inputs(path: str | Path) -> list[tuple[float, Any]]:
    """A live run's core inputs, batch by batch: (lab time, batch)."""
    with reading(path) as db:
        try:
            return [(t, json.loads(b)) for t, b in db.execute("SELECT t_lab, batch FROM inputs ORDER BY seq")]
        except sqlite3.OperationalError:
            return []  # a journal from before inputs were journalled
