"""A scheduler and a planner written from docs/plugins.md alone — its Python blocks, run as they stand — run a
campaign each and take part in the benches, as a stranger's would."""

import json
import re
from pathlib import Path

import pytest

from tests.conftest import twin_cli
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def documented(tmp_path, monkeypatch):
    """docs/plugins.md's Python blocks written as the files their first lines name, importable here and in the
    benches' worker processes."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "plugins.md").read_text(), re.S)
    names = [b.split("\n", 1)[0].removeprefix("# ") for b in blocks]
    assert names == ["my_rules.py", "my_planner.py"]
    for name, block in zip(names, blocks):
        (tmp_path / name).write_text(block)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    return tmp_path


def test_the_documented_scheduler_runs_a_lab_and_is_benched_beside_the_rules(documented):
    summary = run(ROOT / "scenarios" / "flaky_lab.yaml", journal=documented / "j.db", bus="memory",
                  overrides={"campaign.scheduler": "my_rules:LongestFirst", "campaign.budget": 12})
    assert summary.done + summary.abandoned == 12 and summary.decisions > 0 and summary.scheduler_fallbacks == 0
    res = twin_cli("bench", "schedulers", str(ROOT / "scenarios" / "flaky_lab.yaml"), "--budget", "8",
                   "--seeds", "2", "--schedulers", "mwkr,my_rules:LongestFirst", "--json", columns=80)
    assert res.exit_code == 0, res.output
    runs = [r for r in json.loads(res.stdout)["runs"] if r["scheduler"] == "my_rules:LongestFirst"]
    assert len(runs) == 2 and all(r["makespan_s"] > 0 for r in runs)


def test_the_documented_planner_takes_its_option_and_closes_in_on_the_best(documented):
    def spread(radius: float) -> float:
        """How far the last experiments' temperatures lie from one another (°C)."""
        db = documented / f"r{radius}.db"
        run(ROOT / "scenarios" / "quantum_dots.yaml", journal=db, bus="memory",
            overrides={"campaign.planner": "my_planner:NearBest", "campaign.budget": 16,
                       "campaign.stop_on_target": False, "campaign.planner_options": {"radius": radius}})
        temps = [json.loads(e["detail"])["temperature_c"] for e in read_events(db, "experiment.proposed")]
        assert len(temps) == 16
        return max(temps[-6:]) - min(temps[-6:])

    assert spread(0.001) < 1.0 < spread(0.5)  # the option reached it: a small radius stays close to the best
    res = twin_cli("bench", "planners", str(ROOT / "scenarios" / "quantum_dots.yaml"), "--seeds",
                   "2", "--budget", "12", "--planners", "random,my_planner:NearBest", "--json", columns=80)
    assert res.exit_code == 0, res.output
    assert {r["planner"] for r in json.loads(res.stdout)["rows"]} == {"random", "my_planner:NearBest"}
    # its option benched beside the others, which take none of it: it was refused as a misspelling of gp-bo's
    res = twin_cli("bench", "planners", str(ROOT / "scenarios" / "quantum_dots.yaml"), "--seeds", "1", "--budget",
                   "6", "--planners", "random,my_planner:NearBest", "--set", "campaign.planner_options.radius=0.1",
                   "--json", columns=80)
    assert res.exit_code == 0, res.output
    res = twin_cli("bench", "planners", str(ROOT / "scenarios" / "quantum_dots.yaml"), "--seeds", "1", "--budget",
                   "6", "--planners", "random,my_planner:NearBest", "--set", "campaign.planner_options.radus=0.1")
    assert res.exit_code == 2 and "'my_planner:NearBest' takes radius" in " ".join(res.stderr.split())


class WantsALab:
    def __init__(self, lab):
        pass

    def decide(self, view):
        return []


def test_a_constructor_that_wants_what_is_not_given_is_told_what_is():
    from tests.conftest import qd_lab
    from twin.core.errors import ScenarioError
    from twin.runtime.checks import checked
    from twin.scenario import parse

    lab = parse(qd_lab(**{"campaign.scheduler": "tests.twin.test_plugin_docs:WantsALab"}))
    with pytest.raises(ScenarioError, match=r"missing 1 required positional argument: 'lab' \(its constructor is "
                                            r"given, by keyword, those of scenario and seed it names"):
        checked(lab, "lab.yaml")


class Boom:
    def propose(self, n, history, pending):
        raise RuntimeError("out of ideas")


def test_a_bench_says_which_rows_ended_early_and_why(tmp_path):
    """A planner that failed gave a row of noughts ('≥0 [0–0]') and nothing else; and 'Boom:' in its name came out
    as an emoji."""
    res = twin_cli("bench", "planners", str(ROOT / "scenarios" / "quantum_dots.yaml"), "--seeds", "2",
                   "--budget", "6", "--planners", "random,tests.twin.test_plugin_docs:Boom")
    assert res.exit_code == 0, res.output
    said = " ".join(res.output.split())
    assert ("tests.twin.test_plugin_docs:Boom: 2 of 2 runs ended early — the planner failed (planner "
            "'tests.twin.test_plugin_docs:Boom' raised RuntimeError('out of ideas'))") in said
    assert "random:" not in said  # its runs ended as they should
    res = twin_cli("bench", "planners", str(ROOT / "scenarios" / "quantum_dots.yaml"), "--seeds", "2",
                   "--budget", "6", "--planners", "tests.twin.test_plugin_docs:Boom", "--json", columns=80)
    assert all("raised RuntimeError" in r["stopped"] for r in json.loads(res.stdout)["runs"])
