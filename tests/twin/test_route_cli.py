"""`twin route` as a user meets it: a route from the shipped stock, JSON for machines, and exit codes 0 / 1 / 2
for a route, no route, and bad input."""

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import twin_cli

ROOT = Path(__file__).resolve().parents[2]
UNMADE = "CC(=O)Nc1ccc(O)cc1C(=O)OCCN"  # no route in the shipped stock: the search goes on to its --seconds


def twin_route(*args):
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "twin", "route", *args], capture_output=True, text=True, cwd=ROOT,
                          env=env, timeout=120)


def test_aspirin_is_one_acetylation_of_salicylic_acid():
    res = twin_cli("route", "CC(=O)OC1=CC=CC=C1C(=O)O")
    assert res.exit_code == 0, res.stderr
    assert "O-acetylation with acetic anhydride" in res.stdout
    assert "acetic anhydride + salicylic acid" in res.stdout and "buys:" in res.stdout


def test_json_gives_the_steps_in_the_order_the_lab_runs_them():
    res = twin_cli("route", "CCN(CC)CC(=O)Nc1c(C)cccc1C", "--method", "breadth-first", "--json")
    assert res.exit_code == 0, res.stderr
    data = json.loads(res.stdout)
    assert data["solved"] and [s["step"] for s in data["steps"]] == [1, 2]
    made = {b["smiles"] for b in data["bought"]}
    for step in data["steps"]:
        assert set(step["reactants"]) <= made
        made.add(step["product"])
    assert data["steps"][-1]["product"] == data["target"] and 0 < data["overall_yield_pct"] < 100


def in_process(*args):
    """`twin route` run by typer's test runner: the same command, without a Python start-up per case."""
    res = twin_cli("route", *args)
    return res.exit_code, " ".join(res.output.split())


def test_a_bad_smiles_exits_2_from_a_real_process():
    res = twin_route("C1CC")
    assert res.returncode == 2 and "not a valid SMILES: 'C1CC'" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.process
@pytest.mark.parametrize("sig, code, said", [(signal.SIGINT, 130, "interrupted"),
                                             (signal.SIGTERM, 143, "terminated (SIGTERM)")])
def test_ctrl_c_or_sigterm_stops_a_search_and_says_so(tmp_path, sig, code, said):
    """Ctrl-C of a 10-s search exited 130 without a word (and SIGTERM killed it at once); a search says it has
    started, and stopped, it says what became of it."""
    drawn = tmp_path / "route.svg"
    proc = subprocess.Popen([sys.executable, "-m", "twin", "route", UNMADE, "--seconds", "60", "--save", str(drawn)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            env={**os.environ, "COLUMNS": "200"})
    assert proc.stderr is not None
    first = proc.stderr.readline()
    assert first.startswith(f"searching for a route to {UNMADE} (mcts, up to 60 s; Ctrl-C stops it)"), first
    proc.send_signal(sig)
    out, rest = proc.communicate(timeout=60)
    assert proc.returncode == code, rest
    assert re.search(rf"^{re.escape(said)} after \d+\.\d s of the search, before it found a route: nothing shown or "
                     r"drawn; --seconds sets how long it searches", rest, re.M), rest
    assert "Traceback" not in rest and not out and not drawn.exists()


@pytest.mark.parametrize("args,code,says", [
    (["C1CC"], 2, "not a valid SMILES: 'C1CC'"),
    ([""], 2, "not a valid SMILES: ''"),  # RDKit reads it as a molecule of no atoms: the search said "no route to "
    (["CCO", "--method", "nope"], 2, "unknown route planner 'nope'. Installed: breadth-first, mcts, random"),
    (["CCO", "--stock", "missing.csv"], 2, "missing.csv: cannot read the stock file"),
    (["CCO", "--prior", "missing"], 2, "python -m agents.routes.train --out missing"),
    (["C1CC2CCC1C2", "--seconds", "5"], 1, "no route to C1CC2CCC1C2"),
    (["C1CC2CCC1C2", "--seconds", "5"], 1, "no template makes this molecule: give --templates a file"),
    (["CCN(CC)CC(=O)Nc1c(C)cccc1C", "--seconds", "1e-9"], 1, "stopped after 1e-09 s; give it longer (--seconds 2)"),
    (["OC(=O)c1ccccc1O"], 0, "the target is in stock; nothing to make"),
    (["CCO", "--seconds", "-1"], 2, "--seconds -1: give the search a budget above 0"),  # was "no route", exit 1
    (["CCO", "--seconds", "nan"], 2, "--seconds nan: give the search a budget above 0"),
])
def test_exit_codes_and_what_they_say(args, code, says):
    exit_code, out = in_process(*args)
    assert exit_code == code and says in out and "Traceback" not in out, out


@pytest.mark.parametrize("damage,says", [
    ("stock not text", "stock.csv: not a text file (byte 17 is not UTF-8)"),
    ("templates not text", "templates.yaml: not UTF-8 text (byte 0)"),
    ("templates a field over csv's limit", "templates.csv: the table cannot be read past row 1 (field larger than"),
    ("templates a SMARTS too long", "templates.csv: row 2: a retro_template of 6,772 characters"),
    ("templates an alias bomb", "templates.yaml: its aliases expand to more than 100,000 values"),  # 47 s before
    ("templates nested too deep", "templates.yaml: line 1: nested more than 32 levels deep; a template file in YAML"),
    ("description not JSON", "prior.json: not a route prior's description"),
    ("description a list", "prior.json: not a route prior's description"),
    ("description nested too deep", "prior.json: not a route prior's description (maximum recursion depth"),
    ("weights not torch's", "prior.pt: not this prior's weights"),
])
def test_damaged_files_are_one_line_errors_naming_them(tmp_path, damage, says):
    prior, stock = ROOT / "agents" / "policies" / "route_prior", tmp_path / "stock.csv"
    for suffix in (".json", ".pt"):
        (tmp_path / f"prior{suffix}").write_bytes(prior.with_suffix(suffix).read_bytes())
    args = ["CCO", "--prior", str(tmp_path / "prior")]
    if damage == "stock not text":
        stock.write_bytes(b"smiles,name\nCCO,e\xff\xfe\n")
        args += ["--stock", str(stock)]
    elif damage == "templates nested too deep":
        (tmp_path / "templates.yaml").write_text("a: " + "[" * 40 + "]" * 40 + "\n")
        args += ["--templates", str(tmp_path / "templates.yaml")]
    elif damage == "templates an alias bomb":
        levels = [f"l0: &l0 [{', '.join(['x'] * 10)}]"] + [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]"
                                                            for i in range(1, 8)]
        (tmp_path / "templates.yaml").write_text("\n".join(levels) + "\nsources: {s: ref}\ntemplates:\n"
                                                 "  - {name: x, class: c, source: *l7, smarts: x}\n")
        args += ["--templates", str(tmp_path / "templates.yaml")]
    elif damage.startswith("templates a"):
        mapped = "[C:1]" + "".join(f"[C:{i}]" for i in range(2, 30_000 if "limit" in damage else 500))
        (tmp_path / "templates.csv").write_text(f'retro_template,classification\n"{mapped}>>{mapped}",x\n')
        args += ["--templates", str(tmp_path / "templates.csv")]
    elif damage == "templates not text":
        (tmp_path / "templates.yaml").write_bytes(b"\xff\xfetemplates: []\n")
        args += ["--templates", str(tmp_path / "templates.yaml")]
    elif damage == "description not JSON":
        (tmp_path / "prior.json").write_text('{"kind": ')
    elif damage == "description a list":
        (tmp_path / "prior.json").write_text("[1]")
    elif damage == "description nested too deep":  # json.loads raises RecursionError, not ValueError
        (tmp_path / "prior.json").write_text("[" * 100_000)
    else:
        (tmp_path / "prior.pt").write_bytes(b"not weights")
    exit_code, out = in_process(*args)
    assert exit_code == 2 and says in out and "Traceback" not in out, out


def test_save_draws_the_route_as_svg(tmp_path):
    out = tmp_path / "lidocaine.svg"
    res = twin_cli("route", "CCN(CC)CC(=O)Nc1c(C)cccc1C", "--method", "breadth-first", "--save", out)
    assert res.exit_code == 0 and f"drawn: {out}" in " ".join(res.stdout.split()), res.stderr
    svg = out.read_text()
    desc = svg[svg.index("<desc>"):svg.index("</desc>")]
    assert "<svg" in svg and svg.count("<path") > 50  # molecules drawn
    assert "step 1: " in desc and "2,6-dimethylaniline" in desc and "step 2: " in desc and "from step 1" in desc
    code, said = in_process("CCO", "--save", str(tmp_path / "x.gif"))
    assert code == 2 and "give a file name ending in .svg or .png" in said and not (tmp_path / "x.gif").exists()
    code, said = in_process("CC(=O)Nc1ccc(O)cc1", "--method", "breadth-first", "--policy", "none",
                            "--save", str(tmp_path / "p.png"))
    assert code == 0 and (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def bench_in_process(*args):
    res = twin_cli("bench", "routes", *args, columns=80)
    return res.exit_code, res.stdout if "--json" in args else res.output  # progress lines go to stderr


def test_bench_routes_compares_methods_on_targets_of_known_length():
    code, out = bench_in_process("--set", "drugs", "--targets", "3", "--seconds", "5", "--workers", "1",
                                 "--methods", "breadth-first,mcts:none", "--json")
    assert code == 0, out
    results = json.loads(out)["runs"]
    assert {r["method"] for r in results} == {"breadth-first", "mcts:none"} and len(results) == 6
    assert all(r["solved"] and r["steps"] == r["known"] == 1 and r["expansions"] >= 1 for r in results)
    code, out = bench_in_process("--set", "drugs", "--targets", "2", "--seconds", "5", "--workers", "2",
                                 "--methods", "breadth-first")
    lines = out.splitlines()
    assert code == 0 and max(len(line) for line in lines) <= 80
    assert any(line.split()[:3] == ["breadth-first", "100", "100"] for line in lines), out


@pytest.mark.parametrize("args,says", [
    (["--methods", "nope"], "unknown route planner 'nope'"),
    (["--set", "nope"], "unknown route target set 'nope'. Installed: drugs, held-out"),
    (["--targets", "0"], "give at least 1 target"),
])
def test_bench_routes_refuses_what_it_cannot_run(args, says):
    code, out = bench_in_process(*args)
    assert code == 2 and says in " ".join(out.split()) and "Traceback" not in out, out


# its own process: RDKit's parser took the process down with it (SIGSEGV) before the bound
@pytest.mark.parametrize("where", ["target", "stock"])
def test_a_smiles_too_long_for_rdkit_is_refused_not_a_crash(tmp_path, where):
    chain = "C" * 20_000
    args = [chain] if where == "target" else ["CC(=O)Oc1ccccc1C(=O)O", "--stock", str(tmp_path / "stock.csv")]
    (tmp_path / "stock.csv").write_text(f"smiles,name\nCCO,ethanol\n{chain},wax\n")
    res = subprocess.run([sys.executable, "-m", "twin", "route", *args], capture_output=True, text=True, cwd=ROOT,
                         timeout=120)
    said = " ".join(res.stderr.split())
    assert res.returncode == 2 and "a SMILES of 20,000 characters" in said and "reads at most 2,000" in said, said
    assert where == "target" or f"{tmp_path / 'stock.csv'}:3:" in said


def test_a_compressed_table_is_read_only_up_to_its_bound_and_a_stock_too(tmp_path, monkeypatch):
    """`gzip.decompress` of the whole file: a table of a few hundred KB that unpacks to gigabytes took the memory."""
    import gzip

    from agents.routes import stock, templates

    bound = templates.MAX_TABLE_BYTES
    monkeypatch.setattr(templates, "MAX_TABLE_BYTES", 4096)
    with gzip.open(tmp_path / "t.csv.gz", "wb") as f:
        f.write(b"retro_template\n" + b"x" * 100_000)
    exit_code, out = in_process("CCO", "--templates", str(tmp_path / "t.csv.gz"))
    assert exit_code == 2 and "t.csv.gz: more than 0 MiB of templates (uncompressed)" in out, out
    monkeypatch.setattr(templates, "MAX_TABLE_BYTES", bound)  # the shipped templates, read for the stock's search
    monkeypatch.setattr(stock, "MAX_STOCK_BYTES", 4096)
    (tmp_path / "s.csv").write_text("smiles,name\n" + "CCO,ethanol\n" * 1000)
    exit_code, out = in_process("CCO", "--stock", str(tmp_path / "s.csv"))
    assert exit_code == 2 and "s.csv: more than 0 MiB" in out, out


def test_no_route_says_what_to_change_by_what_stopped_the_search():
    from twin.cli.routes import _what_next

    assert "--seconds 20" in _what_next({"why": "stopped after 10 s", "seconds": 10.0, "expansions": 40})
    spent = _what_next({"why": "stopped after 2000 expansions", "seconds": 4.0, "expansions": 2000})
    assert "--seconds" not in spent and "another --method" in spent  # more time would not have helped
    assert "--stock the building blocks" in _what_next({"why": "no route within 6 steps", "seconds": 0.1,
                                                        "expansions": 42})


def test_a_ctrl_c_that_python_dropped_is_raised_again_until_the_search_has_stopped():
    """A Ctrl-C that landed in a weakref callback while a module was being imported was dropped by Python
    ("Exception ignored in …"), and the search ran its whole budget (a CI run: exit 1 after 60 s, not 130). Inside
    `sigterm_unwinds(redeliver=True)` it is raised again until it leaves the block; outside, Ctrl-C is Python's."""
    import time

    from twin.cli.stopping import REDELIVER_S, sigterm_unwinds

    dropped, started = 0, time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        with sigterm_unwinds(redeliver=True):
            while time.monotonic() - started < 10:
                try:
                    if not dropped:
                        os.kill(os.getpid(), signal.SIGINT)
                    time.sleep(0.01)
                except KeyboardInterrupt:
                    if dropped:
                        raise
                    dropped += 1  # as Python drops one raised in a callback
    assert dropped == 1 and time.monotonic() - started < 4 * REDELIVER_S + 1
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
