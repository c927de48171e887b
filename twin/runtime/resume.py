"""``twin resume RUN.db``: continue a campaign that was killed, from its journal.

A virtual-time campaign is deterministic, so it is re-executed from the
start on the scenario and seed the journal recorded, and every event is
checked against the journal's prefix as it is written: the first that
differs stops the resume with an error naming it (the code, a driver or a
plugin changed since the run), and the killed journal is left as it was.
The resumed journal replaces the killed one only when the campaign ends,
and equals the journal of the same campaign never killed.
"""

from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path
from typing import Any

from twin.core.errors import TwinError
from twin.campaign.journal import Journal, read_run
from twin.scenario import Scenario


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
    """The scenario and the events a killed run's journal holds."""
    path = Path(path)
    if not path.exists():
        raise ResumeError(f"{path}: no such journal; runs are written to runs/ by default")
    try:
        data = read_run(path)
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            prefix = db.execute("SELECT * FROM events ORDER BY seq").fetchall()
    except sqlite3.DatabaseError as exc:
        raise ResumeError(f"{path}: not a labtwin journal ({exc})") from None
    if "summary" in data:
        raise ResumeError(f"{path}: the campaign finished; nothing to resume (twin report {path} shows it)")
    if "scenario" not in data:
        raise ResumeError(f"{path}: the journal holds no scenario; it was killed before it began")
    return Scenario.model_validate(data["scenario"]), prefix


def interrupted(path: str | Path) -> dict[str, Any]:
    """How far a killed run got, from what its journal committed."""
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
        events, t_lab = db.execute("SELECT COUNT(*), MAX(t_lab) FROM events").fetchone()
        statuses = dict(db.execute("SELECT status, COUNT(*) FROM experiments GROUP BY status").fetchall())
        scenario = db.execute("SELECT value FROM run WHERE key='scenario'").fetchone()
    name = json.loads(scenario[0])["name"] if scenario else "?"
    return {"scenario": name, "events": events, "lab_hours": (t_lab or 0.0) / 3600, "experiments": statuses}


def replace(resumed: Path, killed: Path) -> None:
    for suffix in ("-wal", "-shm"):
        Path(f"{killed}{suffix}").unlink(missing_ok=True)
    os.replace(resumed, killed)
