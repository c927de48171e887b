"""The files a scenario gives its plugins are found beside it, as its job-shop file is, wherever the command runs."""

from pathlib import Path

import yaml

from tests.conftest import qd_lab, twin_cli
from twin.scenario import load, load_mapping

ROOT = Path(__file__).resolve().parents[2]


def test_a_plugins_files_beside_the_scenario_are_found_from_any_folder(tmp_path, monkeypatch):
    lab = tmp_path / "lab"
    (lab / "policies").mkdir(parents=True)
    for name in ("stock.csv", "policies/p.zip", "ca.pem"):
        (lab / name).write_text("x")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "mine.csv").write_text("x")  # a file only the working directory has: left to it
    raw = qd_lab(**{"campaign.planner_options": {"stock": "stock.csv", "solvent": "THF", "rounds": 3,
                                                 "more": ["mine.csv", "policies/p.zip"]},
                    "campaign.scheduler": "rl:policies/p.zip", "campaign.scheduler_options": {"model": "nope.pt"},
                    "devices.spectrometer.options": {"tls": {"ca": "ca.pem"}},
                    "chemistry.options": {"table": "stock.csv"}})
    (lab / "s.yaml").write_text(yaml.safe_dump(raw))
    monkeypatch.chdir(elsewhere)
    s = load(lab / "s.yaml")
    options = s.campaign.planner_options
    assert options["stock"] == str(lab / "stock.csv") and options["solvent"] == "THF" and options["rounds"] == 3
    assert options["more"] == ["mine.csv", str(lab / "policies" / "p.zip")]
    assert s.campaign.scheduler == f"rl:{lab / 'policies' / 'p.zip'}"
    assert s.campaign.scheduler_options == {"model": "nope.pt"}  # nowhere: the plugin says so, naming it
    assert s.devices["spectrometer"].options["tls"]["ca"] == str(lab / "ca.pem")
    assert s.chemistry.options["table"] == str(lab / "stock.csv")
    assert load_mapping(raw).campaign.planner_options["stock"] == "stock.csv"  # a mapping's: the working folder's


def test_a_route_planners_stock_and_templates_beside_the_scenario_run_from_another_folder(tmp_path, monkeypatch):
    """`twin run rt/amide.yaml` said `good.yaml: cannot read the template file` where `cd rt` ran it."""
    lab = tmp_path / "rt"
    lab.mkdir()
    shipped = ROOT / "agents" / "routes" / "data"
    (lab / "templates.yaml").write_text((shipped / "templates.yaml").read_text())
    (lab / "stock.csv").write_text((shipped / "stock.csv").read_text())
    raw = yaml.safe_load((ROOT / "scenarios" / "aspirin.yaml").read_text())
    raw["campaign"]["planner_options"].update(templates="templates.yaml", stock="stock.csv", seconds=5)
    raw["campaign"]["budget"] = 3
    (lab / "aspirin.yaml").write_text(yaml.safe_dump(raw))
    monkeypatch.chdir(tmp_path)
    res = twin_cli("run", "rt/aspirin.yaml", "--bus", "memory", "--journal", str(tmp_path / "j.db"))
    assert res.exit_code == 0, res.stderr
    assert "cannot read" not in res.stderr


def test_each_campaign_of_a_shared_lab_finds_its_files_beside_the_lab_file(tmp_path, monkeypatch):
    raw = yaml.safe_load((ROOT / "scenarios" / "shared_lab.yaml").read_text())
    raw["campaigns"][0]["campaign"] = {**raw["campaigns"][0].get("campaign", {}), "scheduler": "rl:p.zip"}
    raw["campaigns"][0]["chemistry"]["options"] = {"table": "data/t.csv"}
    (tmp_path / "data").mkdir()
    for name in ("p.zip", "data/t.csv"):
        (tmp_path / name).write_text("x")
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    monkeypatch.chdir(ROOT)
    first = load(tmp_path / "lab.yaml").campaigns[0]
    assert first.campaign.scheduler == f"rl:{tmp_path / 'p.zip'}"
    assert first.chemistry.options["table"] == str(tmp_path / "data" / "t.csv")


def test_a_file_found_nowhere_is_said_with_where_it_was_looked_for(tmp_path, monkeypatch):
    import pytest

    from twin.core.errors import ScenarioError
    from twin.runtime.checks import validate_file

    raw = yaml.safe_load((ROOT / "scenarios" / "aspirin.yaml").read_text())
    raw["campaign"]["planner_options"]["templates"] = "nothere.yaml"
    (tmp_path / "a.yaml").write_text(yaml.safe_dump(raw))
    monkeypatch.chdir(ROOT)
    with pytest.raises(ScenarioError, match=r"nothere\.yaml: cannot read the template file \(No such file or "
                                            r"directory\) \(a file a scenario gives its plugins is looked for beside "
                                            r"the scenario, then in the working directory\)"):
        validate_file(tmp_path / "a.yaml")
