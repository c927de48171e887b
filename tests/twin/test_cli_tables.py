"""`twin devices` for people and machines: whole names when piped, JSON and CSV."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_twin_devices_piped_keeps_every_name_whole_and_speaks_json_and_csv(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    res = subprocess.run([sys.executable, "-m", "twin", "devices"], capture_output=True, text=True, cwd=ROOT,
                         env=env, timeout=60)
    assert res.returncode == 0, res.stderr
    lines = {line.split()[0]: line for line in res.stdout.splitlines()[2:] if line.strip()}
    assert "devices.spectrometer:Spectrometer" in lines["spectrometer"] and "…" not in res.stdout
    assert "lcms, measure" in lines["spectrometer"]
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
