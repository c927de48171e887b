"""The run's journal: SQLite in WAL mode, one file per run.

``events`` is append-only: every message received and every state change, in
lab time. ``experiments`` holds one row per proposed experiment, rewritten as
it moves. ``run`` holds the scenario, the seed and the final summary. Writes
are buffered and committed in batches; ``close`` flushes everything.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import msgspec

from twin.campaign.events import Status
from twin.campaign.journal_lock import claim, release
from twin.core.environment import number_setting
from twin.core.errors import TwinError
from twin.core.numbers import finite
from twin.core.messages import plain_value
from twin.core.messages import to_wire

SCHEMA = """
CREATE TABLE IF NOT EXISTS run (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY, t_lab REAL NOT NULL, kind TEXT NOT NULL,
    experiment INTEGER, task TEXT, attempt INTEGER, device TEXT, detail TEXT);
CREATE TABLE IF NOT EXISTS experiments (
    id INTEGER PRIMARY KEY, params TEXT NOT NULL, route TEXT NOT NULL, status TEXT NOT NULL,
    reason TEXT NOT NULL, outputs TEXT, scores TEXT, attempts INTEGER NOT NULL,
    retries INTEGER NOT NULL, degraded INTEGER NOT NULL, t_proposed REAL NOT NULL, t_done REAL);
CREATE TABLE IF NOT EXISTS inputs (seq INTEGER PRIMARY KEY, t_lab REAL NOT NULL, batch TEXT NOT NULL);
"""
# rows buffered before a commit; LABTWIN_FLUSH_EVERY sets it (a test that kills runs wants small batches)
FLUSH_EVERY = 2000


def flush_every() -> int:
    """The rows a journal buffers before a commit: ``LABTWIN_FLUSH_EVERY`` if set, else 2,000."""
    return number_setting("LABTWIN_FLUSH_EVERY", FLUSH_EVERY, int, lambda rows: rows >= 1,
                          "the rows a journal buffers before a commit as a whole number of 1 or more", f"{FLUSH_EVERY:,}")


_encode_sorted = msgspec.json.Encoder(enc_hook=plain_value, order="sorted").encode


def _sorted(value: Any) -> str:
    """JSON with sorted keys (msgspec; numpy numbers become plain ones, NaN and infinity null)."""
    return _encode_sorted(value).decode()


class Journal:
    FLUSH_EVERY: int | None = None  # None: flush_every()

    def __init__(self, path: str | Path, append: bool = False) -> None:
        """A new journal at ``path`` (one already there is replaced; an empty file there is a name claimed for it),
        or with ``append`` the one there, continued."""
        self._flush_every = self.FLUSH_EVERY or flush_every()
        self.path = Path(path)
        self.label = str(path)  # how summaries name it
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._lock = claim(self.path)
            if self.path.exists() and not append and self.path.stat().st_size:
                for old in (self.path, Path(f"{self.path}-wal"), Path(f"{self.path}-shm")):
                    old.unlink(missing_ok=True)
            self._db = sqlite3.connect(self.path)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(SCHEMA)
        except (OSError, sqlite3.Error) as exc:
            raise TwinError(f"cannot write the journal {path}: {exc}; give --journal a file in a directory you can "
                            "write (nothing has run yet)") from None
        self._events: list[tuple] = []
        self._experiments: dict[int, tuple] = {}
        self._seq = self._db.execute("SELECT COALESCE(MAX(seq), 0) FROM events").fetchone()[0]
        self._inputs: list[tuple] = []
        self.closed = False
        self.failed = ""  # why a write failed (a full disk): later writes are dropped, the first error stands

    def event(self, t_lab: float, kind: str, experiment: int | None = None, task: str | None = None,
              attempt: int | None = None, device: str | None = None, detail: Any = None) -> int:
        """A state change; ``detail`` is stored as JSON. Returns the event's sequence number."""
        # every row goes through _append: a resume checks rows there
        self._append(t_lab, kind, experiment, task, attempt, device, None if detail is None else to_wire(detail).decode())
        return self._seq

    def message(self, t_lab: float, kind: str, experiment: int | None, task: str | None, attempt: int | None,
                device: str | None, payload: bytes | dict) -> None:
        """A message received, stored as the JSON it came as (an in-process envelope is encoded here)."""
        text = payload.decode() if isinstance(payload, bytes) else to_wire(payload).decode()
        self._append(t_lab, kind, experiment, task, attempt, device, text)

    def _append(self, *row: Any) -> None:
        self._seq += 1
        self._events.append((self._seq, *row))
        if len(self._events) >= self._flush_every:
            self.flush()

    def note(self, n: Any) -> int:
        """A ``campaign.Note`` (a state change the core made); returns its sequence number."""
        return self.event(n.t_lab, n.kind, n.experiment, n.task, n.attempt, n.device, n.detail)

    def received(self, m: Any) -> None:
        """A ``campaign.RecordMessage`` (a message the core was given)."""
        self.message(m.t_lab, m.kind, m.experiment, m.task, m.attempt, m.device, m.payload)

    def inputs(self, t_lab: float, batch: Any) -> None:
        """What a live campaign's core was given at one step: what ``twin resume`` replays to rebuild it."""
        self._inputs.append((t_lab, to_wire(batch).decode()))

    def experiment(self, e: Any) -> None:
        self._experiments[e.id] = (
            e.id, _sorted(e.params), _sorted([[s.step, s.device, s.params] for s in e.route]),
            e.status, e.reason, _sorted(e.outputs) if e.outputs else None,
            _sorted(e.scores) if e.scores else None,
            e.attempts, e.retries, int(e.degraded), e.t_proposed, e.t_done,
        )

    def set(self, key: str, value: Any) -> None:
        """A fact of the run (scenario, seed, summary), on disk at once: a run killed later can be resumed."""
        if self.failed:
            return
        try:
            self._db.execute("INSERT OR REPLACE INTO run VALUES (?, ?)", (key, json.dumps(value, default=str)))
            self._db.commit()
        except sqlite3.Error as exc:
            raise self._failing(exc) from None

    def unset(self, key: str) -> None:
        """A fact of the run no longer true (a stopped campaign's summary, when ``twin resume`` continues it)."""
        if self.failed:
            return
        try:
            self._db.execute("DELETE FROM run WHERE key = ?", (key,))
            self._db.commit()
        except sqlite3.Error as exc:
            raise self._failing(exc) from None

    def get(self, key: str) -> Any:
        """A fact of the run set before (None if it was not)."""
        row = self._db.execute("SELECT value FROM run WHERE key = ?", (key,)).fetchone()
        return json.loads(row[0]) if row else None

    def flush(self) -> None:
        if self.closed and not (self._events or self._inputs or self._experiments):
            return  # its close wrote it all (an operator's answer flushed after the act ended the campaign)
        if self.failed:  # what follows a failed write (the stop's own rows, the summary) is dropped, not raised again
            self._events.clear()
            self._inputs.clear()
            self._experiments.clear()
            return
        try:
            self._flush()
        except sqlite3.Error as exc:
            raise self._failing(exc) from None

    def _flush(self) -> None:
        if self._inputs:
            self._db.executemany("INSERT INTO inputs (t_lab, batch) VALUES (?,?)", self._inputs)
            self._inputs.clear()
        if self._events:
            self._db.executemany("INSERT INTO events VALUES (?,?,?,?,?,?,?,?)", self._events)
            self._events.clear()
        if self._experiments:
            self._db.executemany(
                "INSERT OR REPLACE INTO experiments VALUES (?,?,?,?,?,?,?,?,?,?,?,?)", self._experiments.values()
            )
            self._experiments.clear()
        self._db.commit()

    def rows(self, after: int = 0, limit: int | None = None) -> list[dict[str, Any]]:
        """The events written so far (flush first), as ``read_events`` returns them; with ``after`` and ``limit``,
        at most ``limit`` of them past the first ``after`` (a page, read without reading the rest)."""
        cur = self._db.execute("SELECT * FROM events ORDER BY seq LIMIT ? OFFSET ?",
                               (-1 if limit is None else limit, after))
        names = [c[0] for c in cur.description]
        return [dict(zip(names, r)) for r in cur]

    def close(self) -> None:
        if self.closed:
            return
        try:
            self.flush()
        finally:
            self._db.close()
            self.closed = True
            release(self._lock)

    def _failing(self, exc: sqlite3.Error) -> JournalError:
        """A write that failed (its disk full, say): the campaign stops with what to do, said once."""
        with contextlib.suppress(sqlite3.Error):
            self._db.rollback()
        self.failed = str(exc)
        free = shutil.disk_usage(self.path.parent).free
        return JournalError(f"cannot write the journal {self.path}: {exc} ({free:,} bytes free on its disk): it "
                            "lacks what came after, and a campaign still running stopped there; free some space, or "
                            "give --journal a file on another disk, and run it again")


class NullJournal(Journal):
    """Keeps nothing: the journal of a campaign nobody will read (a training episode)."""

    def __init__(self, path: str | Path = ":memory:") -> None:  # noqa: D107 - no file, no database
        self.path, self.label = Path(path), str(path)
        self._events, self._experiments, self._inputs = [], {}, []
        self._seq, self.closed = 0, False

    def event(self, t_lab: float, kind: str, experiment: int | None = None, task: str | None = None,
              attempt: int | None = None, device: str | None = None, detail: Any = None) -> int:
        self._seq += 1
        return self._seq

    def message(self, *args: Any) -> None:
        self._seq += 1

    def inputs(self, t_lab: float, batch: Any) -> None:
        pass

    def experiment(self, e: Any) -> None:
        pass

    def set(self, key: str, value: Any) -> None:
        pass

    def unset(self, key: str) -> None:
        pass

    def get(self, key: str) -> Any:
        return None

    def flush(self) -> None:
        pass

    def rows(self, after: int = 0, limit: int | None = None) -> list[dict[str, Any]]:
        return []

    def close(self) -> None:
        self.closed = True


class JournalError(TwinError):
    """A journal that could not be written (its disk full): the campaign stops."""


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
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            yield db
    except sqlite3.DatabaseError as exc:  # not SQLite, or not ours
        raise _not_ours(path, exc) from None


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
