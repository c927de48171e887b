"""Default journal names: campaigns of one scenario and seed started in the same second (a sweep run in parallel)
each get their own journal; one that fails before it writes anything leaves no file behind."""

import os
from pathlib import Path

import pytest

from tests.conftest import twin_cli
from twin.campaign.journal_read import read_events
from twin.runtime import lab
from twin.runtime.lab import run
from twin.runtime.shared_run import run_shared

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def same_second(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(lab, "_default_stem",
                        lambda s: Path("runs") / f"{s.name}-seed{s.campaign.seed}-20261129-050000")
    return tmp_path / "runs"


def test_campaigns_started_in_the_same_second_each_get_their_own_journal(same_second):
    """Two of three parallel runs of a sweep died with 'sqlite3.OperationalError: disk I/O error': each replaced
    the journal the others were writing."""
    summaries = [run(ROOT / "scenarios" / "flaky_lab.yaml", overrides={"devices.reactor.instances": n,
                                                                         "campaign.budget": 6}) for n in (1, 2, 3)]
    names = [Path(s.journal).name for s in summaries]
    assert names == ["flaky_lab-seed0-20261129-050000.db", "flaky_lab-seed0-20261129-050000-2.db",
                     "flaky_lab-seed0-20261129-050000-3.db"]
    assert sorted(p.name for p in same_second.iterdir()) == sorted(names)
    for s in summaries:  # each journal holds its own campaign, whole
        assert sum(1 for e in read_events(Path(s.journal), "experiment.done")) == s.done


def test_a_lab_of_several_campaigns_gets_its_own_directory_too(same_second):
    first, again = (run_shared(lab.prepare(ROOT / "scenarios" / "shared_lab.yaml"), handle_signals=False)
                    for _ in range(2))
    assert Path(first.journals).name == "shared_lab-seed0-20261129-050000"
    assert Path(again.journals).name == "shared_lab-seed0-20261129-050000-2"


class Broken:
    labtwin_api = 1

    def __init__(self, setup):
        raise RuntimeError("no such instrument on this bench")

    async def run(self, step, params, sample, ctx):
        raise AssertionError("never made")

    async def safe_state(self):
        pass


def test_a_campaign_that_fails_before_it_writes_leaves_no_journal_behind(same_second):
    with pytest.raises(Exception, match="no such instrument"):
        run(ROOT / "scenarios" / "quantum_dots.yaml", bus="memory",
            overrides={"devices.synthesiser.driver": "tests.twin.test_journal_names:Broken"})
    assert not list(same_second.iterdir())


def test_a_journal_that_cannot_be_written_is_a_clear_error_before_anything_runs(tmp_path, monkeypatch):
    """It was a traceback ending in FileExistsError or FileNotFoundError."""
    from twin import TwinError

    (tmp_path / "a_file").write_text("not a directory")
    with pytest.raises(TwinError, match=r"cannot write the journal .*a_file/j\.db: .*give --journal a file in a "
                                        r"directory you can write \(nothing has run yet\)"):
        run(ROOT / "scenarios" / "quantum_dots.yaml", journal=tmp_path / "a_file" / "j.db", bus="memory")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs").write_text("a file where the runs directory goes")
    with pytest.raises(TwinError, match=r"cannot write a journal in runs/: runs is a file, not a directory; move it "
                                        r"away, or give --journal FILE"):
        run(ROOT / "scenarios" / "quantum_dots.yaml", bus="memory")


@pytest.mark.parametrize("command", [["report"], ["resume"], ["export"], ["replay", "--save", "r.rrd"]])
def test_an_empty_journal_a_killed_run_claimed_says_so(tmp_path, command, monkeypatch):
    monkeypatch.chdir(tmp_path)
    empty = tmp_path / "runs" / "qd-seed0-20261129-050000.db"
    empty.parent.mkdir()
    empty.touch()
    res = twin_cli(command[0], str(empty), *command[1:])
    assert res.exit_code == 2 and f"{empty}: empty — the name a run claimed for its journal" in \
        " ".join(res.output.split()), res.output


def test_a_journal_being_written_is_not_replaced_by_a_second_run_given_its_name(tmp_path):
    """`--journal x.db` given to two runs at once: the second replaced the file under the first, which died of a
    disk I/O error with its campaign lost. Now the second is refused, naming the first's process."""

    from twin.campaign.journal import Journal
    from twin.core.errors import TwinError

    path = tmp_path / "x.db"
    first = Journal(path)
    first.event(1.0, "campaign.started")
    first.flush()
    with pytest.raises(TwinError, match=rf"x.db is being written by another run \(process {os.getpid()}\): wait "
                                        r"for that run to end, or give --journal another file"):
        run(ROOT / "scenarios" / "flaky_lab.yaml", journal=path, overrides={"campaign.budget": 2})
    assert [e["kind"] for e in read_events(path)] == ["campaign.started"]  # the first's journal, untouched
    first.close()
    assert not Path(f"{path}-lock").exists()
    assert run(ROOT / "scenarios" / "flaky_lab.yaml", journal=path, overrides={"campaign.budget": 2}).done == 2
    assert not Path(f"{path}-lock").exists()


def test_a_journal_being_written_is_not_resumed_under_its_run(tmp_path):
    """`twin resume` of a run still going re-ran it and then replaced the journal the run was writing."""
    import sqlite3

    from twin.campaign.journal import Journal
    from twin.core.errors import TwinError
    from twin.runtime.resume import resume

    path = tmp_path / "j.db"
    run(ROOT / "scenarios" / "flaky_lab.yaml", journal=path, overrides={"campaign.budget": 4}, bus="memory")
    with sqlite3.connect(path) as c:  # as a run still going has it: no summary yet
        c.execute("DELETE FROM run WHERE key='summary'")
    writer = Journal(path, append=True)  # and its writer
    try:
        with pytest.raises(TwinError, match="j.db is being written by another run"):
            resume(path)
        assert not (tmp_path / "j.db.resuming").exists()
        # `twin report` called it killed and told the user to resume it
        told = " ".join(twin_cli("report", path).output.split())
        assert f"j.db: running — process {os.getpid()} is writing it now" in told and "resume" not in told, told
    finally:
        writer.close()
    Path(f"{path}-lock").write_text("4194304")  # a killed run's lock file: nothing holds it
    told = " ".join(twin_cli("report", path).output.split())
    assert "interrupted" in told and f"Continue it with: twin resume {path}" in told, told
    assert resume(path).done == 4  # once it has ended (killed), it resumes
