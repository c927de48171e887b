"""The command line on the machine around it: a full disk, a port another program holds, a path or a SMILES with
brackets, a mistyped environment variable. Each is said with what to do, never a traceback or a hang."""

import os
from pathlib import Path

import pytest

from tests.conftest import twin_cli

ROOT = Path(__file__).resolve().parents[2]


def test_paths_and_smiles_print_as_they_are_never_as_rich_markup(tmp_path):
    """A file under "runs[/old]" or a SMILES with "[nH]" is text: rich read it as tags, dropping "[nH]" from the
    target's name and failing with a MarkupError traceback on "[/old]"."""
    odd = tmp_path / "runs[/old]" / "[lab]qd.yaml"
    odd.parent.mkdir(parents=True)
    odd.write_text((ROOT / "scenarios" / "quantum_dots.yaml").read_text().replace("budget:", "budget: x #"))
    for command in ("validate", "run"):
        res = twin_cli(command, odd)
        assert res.exit_code == 2 and f"{odd}: 1 problem" in res.output, res.output
    res = twin_cli("route", "c1ccc2[nH]ccc2c1")
    assert res.exit_code == 0 and "c1ccc2[nH]ccc2c1:" in res.output, res.output


def test_a_terminal_that_cannot_show_every_character_shows_the_rest(tmp_path):
    """Under PYTHONIOENCODING=ascii (or a Latin-1 console) the summary's dash ended `twin run` and `twin report`
    in a UnicodeEncodeError, after the campaign had run."""
    from typer.testing import CliRunner

    from twin.cli import app

    db = tmp_path / "j.db"
    for args in (["run", ROOT / "scenarios" / "quantum_dots.yaml", "--budget", "4", "--journal", db], ["report", db]):
        res = CliRunner(charset="ascii").invoke(app, [str(a) for a in args], env={"COLUMNS": "100"})
        assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
        assert res.exit_code == 0 and "quantum_dots ? seed 0" in res.stdout, res.output  # the dash as '?'


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_journal_whose_disk_fills_stops_the_run_with_what_to_do(tmp_path, monkeypatch, runtime):
    """SQLite's "database or disk is full" was a traceback out of the runtime's loop (on a live clock, logged with
    "the campaign stopped on an error" first). The disk is filled here as SQLite sees it: a page limit."""
    from twin.campaign import journal

    opened = journal.Journal.__init__

    def small(self, *args, **kwargs):
        opened(self, *args, **kwargs)
        self._db.execute("PRAGMA max_page_count = 40")

    monkeypatch.setattr(journal.Journal, "__init__", small)
    db = tmp_path / "j.db"
    res = twin_cli("run", ROOT / "scenarios" / "flaky_lab.yaml", "--journal", db, "--bus", "memory", "--runtime",
                   runtime)
    out = " ".join(res.output.split())
    assert res.exit_code == 2 and f"cannot write the journal {db}: database or disk is full" in out, out
    assert "give --journal a file on another disk" in out and "Traceback" not in out


def test_a_full_disk_is_said_for_the_recording_and_the_tables_not_a_traceback_or_a_hang(tmp_path, monkeypatch):
    """A full disk: Rerun's file sink hung when opened on one, and only logged a write that failed at the
    recording's end ("recording saved" after it); export died with OSError. (Free space is what the OS reports;
    here it is reported as the OS would on a full disk.)"""
    import errno

    from twin.cli import common
    from twin.tools import export
    from twin.view import recorder

    lab = ROOT / "scenarios" / "quantum_dots.yaml"
    monkeypatch.setattr(common, "free_bytes", lambda path: 0)
    res = twin_cli("run", lab, "--save", tmp_path / "r.rrd", "--set", "campaign.budget=3")
    assert res.exit_code == 2 and f"--save {tmp_path / 'r.rrd'}: its disk is full (0 bytes free)" in res.output
    assert not (tmp_path / "r.rrd").exists() and "runs/" not in res.output  # nothing ran
    monkeypatch.setattr(common, "free_bytes", lambda path: 10 << 30)
    monkeypatch.setattr(recorder, "free_bytes", lambda path: 0)  # full once the recording is written
    res = twin_cli("run", lab, "--save", tmp_path / "r.rrd", "--set", "campaign.budget=3", "--journal",
                   tmp_path / "j.db")
    out = " ".join(res.output.split())
    assert res.exit_code == 2 and "so its end may be cut short" in out and "recording saved" not in out, out
    assert f"twin replay {tmp_path / 'j.db'} --save FILE" in out

    def no_space(*_):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(export, "_write_table", no_space)
    res = twin_cli("export", tmp_path / "j.db", "--out", tmp_path / "x")
    assert res.exit_code == 2 and f"cannot write {tmp_path / 'x' / 'experiments.csv'}: No space left on device" in \
        " ".join(res.output.split())
    assert not list((tmp_path / "x").iterdir())  # no partial file left


@pytest.mark.parametrize("command", [
    ["router", "--listen", "{at}"],
    ["run", "scenarios/quantum_dots.yaml", "--clock", "scaled", "--speed", "3600", "--listen", "{at}"],
])
def test_a_port_another_program_listens_on_is_named_as_taken(command):
    """A second lab or router on a port printed Zenoh's "Can not create a new TCP listener … at
    /root/.cargo/git/checkouts/…"."""
    import socket

    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        at = f"tcp/127.0.0.1:{other.getsockname()[1]}"
        res = twin_cli(*[a.format(at=at) for a in command], columns=300)
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and f"{at} is taken: another lab, router or program listens there" in said, said
    assert "cargo" not in said


@pytest.mark.parametrize("variable, says", [
    ("LABTWIN_PROGRESS_S", "give the seconds between progress lines off a terminal as a positive number"),
    ("LABTWIN_FLUSH_EVERY", "give the rows a journal buffers before a commit as a whole number of 1 or more")])
def test_a_mistyped_labtwin_variable_is_refused_before_anything_runs(monkeypatch, tmp_path, variable, says):
    """LABTWIN_FLUSH_EVERY=abc was a ValueError traceback from importing twin; both are said, naming the value."""
    from twin import TwinError, prepare, run

    for bad in ("soon", "0", "-1", "nan", "inf"):
        if bad in ("nan", "inf") and variable == "LABTWIN_FLUSH_EVERY":
            continue  # not whole numbers: "soon" covers them
        monkeypatch.setenv(variable, bad)
        res = twin_cli("run", ROOT / "scenarios" / "quantum_dots.yaml", "--journal", tmp_path / "j.db")
        assert res.exit_code == 2, res.output
        assert f"{variable}='{bad}': {says}" in " ".join(res.stderr.split())
        assert not (tmp_path / "j.db").exists()  # refused before anything ran
    import subprocess
    import sys

    helped = subprocess.run([sys.executable, "-m", "twin", "run", "--help"], capture_output=True, text=True,
                            cwd=ROOT, env={**os.environ, variable: "soon"}, timeout=60)
    assert helped.returncode == 0 and "Usage: twin run" in helped.stdout, helped.stderr  # help whatever the settings
    if variable == "LABTWIN_FLUSH_EVERY":  # the Python API makes a journal without the command line
        with pytest.raises(TwinError, match=f"{variable}='-1': {says}"):
            run(prepare(ROOT / "scenarios" / "quantum_dots.yaml"), journal=tmp_path / "k.db")
