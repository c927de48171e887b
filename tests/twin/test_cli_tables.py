"""`twin devices` for people and machines: whole names when piped, JSON and CSV."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import twin_cli

ROOT = Path(__file__).resolve().parents[2]


def test_twin_devices_piped_keeps_every_name_whole_and_speaks_json_and_csv(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    res = subprocess.run([sys.executable, "-m", "twin", "devices"], capture_output=True, text=True, cwd=ROOT,
                         env=env, timeout=60)
    assert res.returncode == 0, res.stderr
    lines = {line.split()[0]: line for line in res.stdout.splitlines()[2:] if line.strip()}
    assert "devices.spectrometer:Spectrometer" in lines["spectrometer"] and "…" not in res.stdout
    assert "lcms, measure" in lines["spectrometer"]
    assert "its device type's steps" in lines["machine"] and "its device type's steps" in lines["mqtt"]
    res = subprocess.run([sys.executable, "-m", "twin", "devices", "--json", "--csv", str(tmp_path / "d.csv")],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=60)
    rows = {r["driver"]: r for r in json.loads(res.stdout)["rows"]}
    assert rows["purifier"]["class"] == "devices.purifier:Purifier" and rows["purifier"]["runs"] == "purify"
    with open(tmp_path / "d.csv") as f:
        assert {r["driver"] for r in csv.DictReader(f)} == set(rows)


def test_every_bench_script_speaks_json_and_csv(tmp_path):
    code = ("import sys; sys.path.insert(0, '.'); from bench.tables import table; "
            "table('speed', ['run', 'ratio'], [['baseline', 1.0], ['new', 0.5]]); table('size', ['mb'], [[2]])")
    res = subprocess.run([sys.executable, "-c", code, "--json", "--csv", str(tmp_path / "t.csv")],
                         capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert res.returncode == 0, res.stderr
    tables = json.loads(res.stdout)["tables"]
    assert [t["title"] for t in tables] == ["speed", "size"] and tables[0]["rows"][1] == {"run": "new", "ratio": 0.5}
    with open(tmp_path / "t.csv") as f:
        assert list(csv.reader(f)) == [["run", "ratio"], ["baseline", "1.0"], ["new", "0.5"]]
    assert (tmp_path / "t-2.csv").read_text().splitlines() == ["mb", "2"]


def test_a_health_answer_of_any_shape_is_shown_not_fatal(capsys):
    """A device of someone else's (docs/wire.md) may answer a health query with anything."""
    from twin.cli.distributed import render_health
    from twin.runtime.serve import health_report

    answers = [b'{"running": ["e1s2", 1], "dropped": 3, "driver": {"ok": true}}', b"[1, 2]", b"\xff not json",
               b'{"running": 5, "driver": "[bold]fine[/bold]"}', b'"ok"']
    reports = [health_report(a) for a in answers]
    assert reports[1] == {"driver": [1, 2]} and reports[4] == {"driver": "ok"}
    assert reports[2]["driver"]["ok"] is False and "not JSON" in reports[2]["driver"]["error"]
    render_health([{"device": f"dev[{i}]", "report": r} for i, r in enumerate(reports)]
                  + [{"device": "gone", "report": None},
                     {"device": "edited", "report": reports[0], "differs": ["devices.x.setup_s: 9 there, 0 here"]}])
    out = capsys.readouterr().out
    assert "e1s2#1" in out and "[bold]fine[/bold]" in out and "dev[4]" in out and "not JSON" in out
    assert "edited runs by a scenario that differs from this file: devices.x.setup_s: 9 there, 0 here" in \
        " ".join(out.split())  # wrapped at the terminal's width


def test_a_narrow_table_keeps_numbers_whole_and_fits_80_columns(monkeypatch):
    """rich folds any word to fit: '0.01/0.33' came out as '0.01/0.3' over '3', and widening a column after it
    had narrowed the others left the caption one column too wide (its last letter cut)."""
    import io

    from rich.console import Console

    from twin.cli import common
    from twin.tools.scheduler_bench import HEADER, caption

    out = io.StringIO()
    monkeypatch.setattr(common, "console", Console(file=out, width=80))
    header = [h for h in HEADER if h != "vs bound"]  # a lab with no CP-SAT bound, as `twin bench schedulers` shows it
    table = common.narrow_table(header, "five_stage — 4 runs per scheduler", caption("lab-h", bound=False))
    numbers = [["least-loaded", "39.89", "39.89", "+1.2%", "28%", "48.5", "0.0", "0.0", "0.01/0.33"],
               ["rl:flaky_scheduler", "139.18", "39.18", "-10.6%", "29%", "18.0", "0.1", "0.0", "10.30/14.51"]]
    for row in numbers:
        table.add_row(*row)
    common.print_table(table)
    text = out.getvalue()
    assert max(len(line) for line in text.splitlines()) <= 80
    words = text.split()
    for row in numbers:
        assert all(cell in words for cell in row[1:]), row
    assert " ".join(words).endswith(caption("lab-h", bound=False))  # the caption whole, wrapped only at spaces
    # columns of numbers no wider than they need: the names have the room, broken (if at all) only after a
    # hyphen or underscore, never inside a word
    names = [line.split()[0] for line in text.splitlines()[5:9]]
    assert names in (["least-loaded", "rl:flaky_scheduler"], ["least-", "loaded", "rl:flaky_", "scheduler"]), text


def test_a_job_shop_bench_at_80_columns_keeps_the_policy_name_whole_and_leaves_out_counts_that_are_nought():
    """A job shop degrades no sample, abandons nothing and needs no fallback: those columns took the room that
    folded 'rl:jobshop_scheduler' over three lines; the caption says what they would have shown."""
    res = twin_cli("bench", "schedulers", "scenarios/jobshop.yaml", "--workers", "1",
                   "--schedulers", "fifo,mwkr,rl:agents/policies/jobshop_scheduler.zip", columns=80)
    assert res.exit_code == 0, res.stderr
    lines = res.stdout.splitlines()
    assert max(map(len, lines)) <= 80
    header = " ".join(line for line in lines if "scheduler" in line.split()[:1] or "vs" in line.split()[:1])
    assert "degr." not in header and "lost" not in header and "fallb." not in header and "busy" in header
    rl = [line.split() for line in lines if line.strip().startswith("rl:")]
    assert rl and rl[0][0] == "rl:jobshop_scheduler" and float(rl[0][1]) >= 55  # whole, then its makespan (ft06)
    caption = " ".join(" ".join(lines).split())
    assert "no run degraded a sample, abandoned an experiment or needed the fallback rule (not shown)" in caption


def test_a_shop_whose_optimum_is_0_s_has_no_bound_column_and_its_caption_says_none(tmp_path):
    """The gap to a 0-s optimum is no number: the column was left out, and the caption still explained it."""
    shop = tmp_path / "instant.txt"
    shop.write_text("2 2\n0 0 1 0\n1 0 0 0\n")  # every operation takes no time
    res = twin_cli("bench", "schedulers", "scenarios/jobshop.yaml", "--jobshop", shop, "--schedulers", "fifo,mwkr",
                   columns=120)
    assert res.exit_code == 0, res.stderr
    assert "CP-SAT optimum 0 lab-s" in res.stdout and "vs bound" not in " ".join(res.stdout.split())


def test_a_narrow_table_with_more_header_words_than_80_columns_hold_breaks_them_at_hyphens_and_fits(monkeypatch):
    import io

    from rich.console import Console

    from twin.cli import common

    out = io.StringIO()
    monkeypatch.setattr(common, "console", Console(file=out, width=80))
    names = ["fifo", "mwkr", "spt", "oldest-sample", "least-loaded"]
    table = common.narrow_table(["shape", "best rule", "its mean h", *names, "rl:\nflaky_scheduler"])
    for shape in ("as written", "synthesiser ×2 instances", "synthesiser bottleneck (×2 duration)"):
        table.add_row(shape, "mwkr", "44.94", *["+0.17 ± 3.58\nsame"] * len(names), "+1.28 ± 5.51\nsame")
    common.print_table(table)
    assert max(map(len, out.getvalue().splitlines())) <= 80
    words = out.getvalue().split()
    assert all(n in words for n in ("+0.17", "3.58", "+1.28", "5.51"))  # numbers whole
    # and words: the shapes' whole, the headers' broken only after a hyphen or underscore ("synthes" over "iser",
    # "least-l" over "oaded" before)
    assert {"synthesiser", "bottleneck", "instances", "duration)"} <= set(words)
    assert {"least-", "loaded", "oldest-", "sample", "flaky_", "scheduler"} <= set(words)


@pytest.mark.parametrize("schedulers,lines_per_comparison", [
    ("fifo,rl:agents/policies/flaky_scheduler.zip", 1),
    ("fifo,spt,mwkr,least-loaded,oldest-sample,rl:agents/policies/flaky_scheduler.zip", 3)])
def test_the_shapes_bench_at_80_columns_never_breaks_a_comparison_inside_a_line(schedulers, lines_per_comparison):
    """Six schedulers at 80 columns folded each "+2.84 ± 2.77 worse" into "+2.84 ±" over "2.77" over "worse": the
    comparisons now go on one line, on two, or with the difference, its interval and the verdict on a line each.
    And a policy's column was headed 'rl:flaky_schedu' over 'ler' with room to spare: the name now breaks after
    'rl:', and a header's words are kept whole when the table still fits."""
    args = ["bench", "schedulers", "scenarios/flaky_lab.yaml", "--shapes", "--seeds", "2", "--workers", "1",
            "--schedulers", schedulers, "--set", "campaign.budget=4"]
    shown = twin_cli(*args, columns=80)
    data = json.loads(twin_cli(*args, "--json").stdout)
    assert shown.exit_code == 0, shown.stderr
    lines = shown.stdout.splitlines()
    assert max(map(len, lines)) <= 80 and not any(line.rstrip().endswith("±") for line in lines)
    words = shown.stdout.split()
    assert {"synthesiser", "spectrometer", "bottleneck"} <= set(words)  # the shapes' words whole
    if lines_per_comparison == 1:  # room to spare: the policy's name whole, under "rl:"
        assert "flaky_scheduler" in words and "rl:" in words, shown.stdout
    for c in data["comparisons"]:
        if c["scheduler"] == c["best_rule"]:
            continue
        diff, ci, said = f"{c['diff_h']:+.2f}", f"{c['ci95_h']:.2f}", c["verdict"]
        if lines_per_comparison == 1:
            assert f"{diff} ± {ci} {said}" in shown.stdout, (c, shown.stdout)
        else:
            assert f"± {ci}" in shown.stdout and diff in words and said in words, c


def test_a_narrow_tables_title_and_caption_wrap_at_the_terminals_width_not_the_tables(monkeypatch):
    """A shapes bench stopped after one shape titled its narrow table "… the table is of 1" over "of 11 shapes":
    rich wraps a title at the table's width."""
    import io

    from rich.console import Console

    from twin.cli import common

    out = io.StringIO()
    monkeypatch.setattr(common, "console", Console(file=out, width=80))
    title = "flaky_lab: each scheduler minus the shape's best rule, 1 of 11 shapes"
    caption = "campaigns end when every target is met, and chance weighs on every row"
    table = common.narrow_table(["shape", "best", "h"], title=title, caption=caption)
    table.add_row("as written", "mwkr", "4.2")
    common.print_table(table)
    lines = out.getvalue().splitlines()
    assert lines[0] == title and lines[-1] == caption, lines
    assert max(len(line) for line in lines[1:-1]) < 30  # the table itself as narrow as before
