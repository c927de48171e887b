"""A journal that is missing, not one, cut short or altered by hand: `twin report`, `resume`, `replay` and `export`
name what is wrong (the file, the row, the run-table entry) and exit 2, never a traceback."""

import json
import sqlite3
from pathlib import Path

import pytest

from tests.conftest import twin_cli

ROOT = Path(__file__).resolve().parents[2]


def test_report_of_a_missing_journal_is_a_clear_error(tmp_path):
    res = twin_cli("report", tmp_path / "nope.db")
    assert res.exit_code == 2 and "no such journal" in res.stderr


@pytest.mark.parametrize("command", [["report"], ["resume"], ["replay", "--save", "r.rrd"], ["export"]])
@pytest.mark.parametrize("content", ["text", "another SQLite database"])
def test_a_file_that_is_not_a_journal_is_a_clear_error(tmp_path, command, content, monkeypatch):
    bad = tmp_path / "notes.db"
    if content == "text":
        bad.write_text("this is not SQLite")
    else:
        with sqlite3.connect(bad) as db:
            db.execute("CREATE TABLE notes (line TEXT)")
    monkeypatch.chdir(tmp_path)
    res = twin_cli(command[0], bad, *command[1:])
    assert res.exit_code == 2, res.stderr
    said = " ".join(res.stderr.split())
    if content == "text":
        assert f"{bad}: not a labtwin journal" in said
    else:  # or one a run has only just begun: its tables come a moment after the file
        assert f"{bad}: holds none of a labtwin journal's tables" in said and "another program's database" in said


@pytest.mark.parametrize("command", [["report"], ["resume"], ["replay", "--save", "r.rrd"], ["export"]])
def test_a_journal_cut_short_is_called_damaged_not_foreign(tmp_path, command, monkeypatch):
    from twin.runtime.lab import run

    whole = tmp_path / "whole.db"
    run(ROOT / "scenarios" / "quantum_dots.yaml", journal=whole, overrides={"campaign.budget": 6})
    cut = tmp_path / "cut.db"
    cut.write_bytes(whole.read_bytes()[:whole.stat().st_size // 2])  # copied while the run still wrote it, say
    monkeypatch.chdir(tmp_path)
    res = twin_cli(command[0], cut, *command[1:])
    said = " ".join(res.stderr.split())
    assert res.exit_code == 2 and f"{cut}: a damaged database" in said and "copy it again" in said, said


@pytest.mark.parametrize("damage,says", [
    ("UPDATE events SET detail = 'not json {' WHERE seq = 3", "event 3 is damaged (its detail is not JSON"),
    ("UPDATE events SET experiment = 'zz' WHERE seq = 4", "event 4 is damaged (its experiment is 'zz'"),
    ("UPDATE events SET t_lab = 'noon' WHERE seq = 5", "event 5 is damaged (its lab time is 'noon'"),
    ("UPDATE events SET t_lab = 1e308 WHERE seq = 5", "event 5 is damaged (its lab time is 1e+308 s, beyond any"),
    ("DELETE FROM events WHERE seq IN (6, 7)", "event 6 is missing (the next is 8)"),  # replayed without them
    ("DELETE FROM events WHERE seq = 1", "event 1 is missing (the next is 2)"),
])
def test_a_journal_altered_row_by_row_is_refused_naming_the_row(tmp_path, damage, says):
    """SQLite keeps whatever a row is given: replay and export check each row instead of failing on it later."""
    from twin.runtime.lab import run

    db = tmp_path / "qd.db"
    run(ROOT / "scenarios" / "quantum_dots.yaml", journal=db, bus="memory", overrides={"campaign.budget": 3})
    with sqlite3.connect(db) as conn:
        conn.execute(damage)
    for command in (["replay", str(db), "--save", str(tmp_path / "r.rrd")],
                    ["export", str(db), "--format", "csv", "--out", str(tmp_path / "out")]):
        res = twin_cli(*command)
        out = " ".join(res.output.split())
        assert res.exit_code == 2 and says in out and "altered or corrupted" in out, (command, out)
    assert twin_cli("report", str(db)).exit_code == 0


_KILLED = "DELETE FROM run WHERE key = 'summary'; "  # as a run killed before its end leaves it


@pytest.mark.parametrize("damage,commands,says", [
    ("UPDATE experiments SET params = '[1,' WHERE id = 0", ["export"],
     "experiment 0 is damaged (its params is not JSON"),
    ("UPDATE run SET value = '\"hello\"' WHERE key = 'scenario'", ["replay", "export"],
     "its run table's 'scenario' is 'hello', not a mapping"),
    ("DELETE FROM run WHERE key = 'scenario'", ["export"], "its run table has no 'scenario'"),
    ("UPDATE experiments SET params = '[1, 2]' WHERE id = 0", ["export"],
     "experiment 0 is damaged (its params is '[1, 2]', not a mapping)"),
    ("UPDATE experiments SET status = 'exploded' WHERE id = 1", ["export"],
     "experiment 1 is damaged (its status is 'exploded', not one of pending, running, done, abandoned)"),
    ("UPDATE experiments SET attempts = 'many' WHERE id = 1", ["export"],
     "experiment 1 is damaged (its attempts is 'many', not a whole number of them)"),
    ("UPDATE experiments SET t_done = -1e300 WHERE id = 1", ["export"],
     "experiment 1 is damaged (its t_done is '-1e+300', not a lab time)"),
    ("ALTER TABLE experiments RENAME TO old; CREATE TABLE experiments AS SELECT id, params FROM old", ["export"],
     "its experiments table has no route, status, reason"),
    ("UPDATE experiments SET route = '[[1, 2]]' WHERE id = 1", ["export"],
     "experiment 1 is damaged (its route is '[[1, 2]]', not a list of [step, device type, params])"),
    ("UPDATE run SET value = '{' WHERE key = 'summary'", ["report", "replay", "export", "resume"],
     "its run table's 'summary' is not JSON: '{'"),
    (_KILLED + "DELETE FROM run WHERE key = 'scenario'", ["report", "resume"], "before it began"),
    (_KILLED + "UPDATE events SET t_lab = 'noon' WHERE seq = 5", ["resume", "report"],
     "event 5 is damaged (its lab time is 'noon'"),
    (_KILLED + "DELETE FROM events WHERE seq = 9", ["resume", "report"], "event 9 is missing (the next is 10)"),
    (_KILLED + "UPDATE run SET value = '{\"name\": 5}' WHERE key = 'scenario'", ["resume"],
     "the journal's scenario: 1 problem - name: Input should be a valid string"),
])
def test_a_journal_altered_in_its_run_or_experiments_is_refused_naming_what(tmp_path, damage, commands, says):
    """Not a traceback from whichever reader met the damage first: export, replay, resume and report name it."""
    from twin.runtime.lab import run

    db = tmp_path / "qd.db"
    run(ROOT / "scenarios" / "quantum_dots.yaml", journal=db, bus="memory", overrides={"campaign.budget": 3})
    with sqlite3.connect(db) as conn:
        conn.executescript(damage)
    args = {"replay": ["--save", str(tmp_path / "r.rrd")], "export": ["--out", str(tmp_path / "out")]}
    for command in commands:
        res = twin_cli(command, str(db), *args.get(command, []))
        out = " ".join(res.output.split())
        assert res.exit_code == 2 and says in out, (command, out)  # a traceback exits 1


_ENDLESS = "WITH RECURSIVE n(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM n LIMIT 3)"  # without LIMIT: for good


@pytest.mark.parametrize("change,says", [
    (f"ALTER TABLE run RENAME TO kept; CREATE VIEW run AS {_ENDLESS} SELECT 'k' || x AS key, '1' AS value FROM n",
     "holds a view ('run')"),
    (f"CREATE TRIGGER more AFTER INSERT ON events BEGIN INSERT INTO run {_ENDLESS} SELECT x, x FROM n; END",
     "holds a trigger ('more')"),
    ("ALTER TABLE run RENAME TO kept; CREATE VIRTUAL TABLE run USING fts5(key, value); "
     "INSERT INTO run SELECT * FROM kept", "holds a virtual table ('run')"),
    ("ALTER TABLE experiments ADD COLUMN big TEXT GENERATED ALWAYS AS (printf('%.*c', 100000000, 'x')) VIRTUAL",
     "holds a computed column ('experiments.big')"),
])
def test_a_journal_that_would_run_a_query_of_its_own_is_refused_before_any_read(tmp_path, change, says):
    """A journal someone sends is read as data: a view, a virtual table or a computed column runs the sender's
    query at every read (a view of an endless recursive query held `twin report` for good, its memory growing)."""
    from twin.runtime.lab import run

    db = tmp_path / "qd.db"
    run(ROOT / "scenarios" / "quantum_dots.yaml", journal=db, bus="memory", overrides={"campaign.budget": 3})
    with sqlite3.connect(db) as conn:
        conn.executescript(_KILLED + change)  # resumable, as far as the run table says
    args = {"replay": ["--save", str(tmp_path / "r.rrd")], "export": ["--out", str(tmp_path / "out")]}
    for command in ("report", "replay", "export", "resume"):
        res = twin_cli(command, str(db), *args.get(command, []))
        out = " ".join(res.output.split())
        assert res.exit_code == 2 and says in out and "labtwin never writes" in out, (command, out)
        assert "nothing was read from it" in out


@pytest.mark.parametrize("name", ["run.db", "run #1.db", "run%20a.db", "what?.db"])
def test_reading_a_journal_leaves_nothing_beside_it_whatever_its_name(tmp_path, name):
    """Read-only connections cannot remove the -wal and -shm files they make: `twin report` left both beside every
    journal it read. And the name went into an SQLite URI unquoted: 'run #1.db' opened (and made) an empty 'run ',
    'run%20a.db' was 'unable to open'."""
    from twin.runtime.lab import run

    journal = tmp_path / name
    run(ROOT / "scenarios" / "quantum_dots.yaml", journal=journal, overrides={"campaign.budget": 3})
    assert [p.name for p in tmp_path.iterdir()] == [name]
    res = twin_cli("report", journal, "--json")
    assert res.exit_code == 0 and json.loads(res.stdout)["summary"]["done"] == 3, res.stderr
    assert [p.name for p in tmp_path.iterdir()] == [name]


def test_the_commands_a_run_names_for_its_files_run_as_pasted(tmp_path):
    """`journal: runs/j #1.db  (twin report runs/j #1.db)`: pasted into a shell, '#' began a comment."""
    import re
    import shlex

    journal, saved = tmp_path / "j #1.db", tmp_path / "r #1.rrd"
    res = twin_cli("run", ROOT / "scenarios" / "quantum_dots.yaml", "--budget", "2", "--journal", journal, "--save",
                   saved, columns=400)
    assert res.exit_code == 0, res.stderr
    report = re.search(r"\((twin report [^)]+)\)", res.stdout)
    viewer = re.search(r"open it with: (rerun .+)\)$", res.stderr, re.M)
    assert report and viewer, (res.stdout[-300:], res.stderr[-300:])
    assert shlex.split(viewer[1]) == ["rerun", str(saved)]
    words = shlex.split(report[1])
    assert words == ["twin", "report", str(journal)]
    assert twin_cli(*words[1:]).exit_code == 0
