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
from pathlib import Path
from typing import Any

import msgspec

from twin.campaign.journal_lock import claim, release
from twin.core.environment import number_setting
from twin.core.errors import TwinError
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
