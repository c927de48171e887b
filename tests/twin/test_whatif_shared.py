"""`twin whatif` of a lab of several campaigns: each campaign's hours, a stalled campaign at its limit, and the lab
asked in virtual time whatever its file's clock."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from tests.twin.test_whatif import whatif

ROOT = Path(__file__).resolve().parents[2]


def test_a_lab_of_several_campaigns_shows_each_campaigns_hours_one_after_the_other_adding_up(tmp_path):
    """Catalysis after quantum dots: in every run the lab's hours are the two campaigns' own, end to end; both at
    once, neither campaign's own hours exceed the lab's. The table and the CSV give each campaign's median."""
    import yaml

    raw = yaml.safe_load((ROOT / "scenarios" / "shared_lab.yaml").read_text())
    for c, budget in zip(raw["campaigns"], (6, 4)):
        c["campaign"].update(budget=budget, planner="random")
    lab = tmp_path / "lab.yaml"
    lab.write_text(yaml.safe_dump(raw))
    code, out = whatif(str(lab), "--vary", "campaigns.1.after=,dots", "--seeds", "3", "--json")
    assert code == 0, out
    data = json.loads(out[out.index("{"):])
    for run in data["runs"]:
        dots, catalyst = run["per_campaign"]["dots"], run["per_campaign"]["catalyst"]
        if run["variant"] == "as written":
            assert max(dots, catalyst) <= run["campaign_hours"] + 1e-9
        else:
            assert dots + catalyst == pytest.approx(run["campaign_hours"], abs=1e-6)
    code, out = whatif(str(lab), "--vary", "campaigns.1.after=,dots", "--seeds", "3", "--csv", str(tmp_path / "w.csv"))
    assert code == 0 and "each campaign: median lab-h from its start to its end" in out
    rows = list(csv.DictReader((tmp_path / "w.csv").open()))
    for row, variant in zip(rows, data["variants"]):
        assert float(row["campaign_h_dots"]) == pytest.approx(variant["per_campaign"]["dots"], abs=1e-4)
    assert all(len(line) <= 80 for line in out.splitlines())


def test_a_lab_of_several_campaigns_on_a_scaled_clock_is_asked_in_virtual_time_with_its_twins(tmp_path):
    """A lab of one campaign is asked on a virtual clock whatever its file says; a lab of several ran on its file's
    own: a scaled clock waited out its lab time in wall time, with its real drivers (one not installed here, behind
    a twin, stopped it), and gave other numbers than the same lab's file on a virtual clock."""
    import yaml

    raw = yaml.safe_load((ROOT / "scenarios" / "shared_lab.yaml").read_text())
    for c in raw["campaigns"]:
        c["campaign"]["budget"] = 4
    (tmp_path / "virtual.yaml").write_text(yaml.safe_dump(raw))
    raw["clock"] = {"mode": "scaled", "speed": 3600}
    raw["devices"]["spectrometer"].update(driver="labtwin_acme_absent:Reader", twin={"driver": "spectrometer"})
    (tmp_path / "scaled.yaml").write_text(yaml.safe_dump(raw))
    hours = []
    for lab in ("virtual.yaml", "scaled.yaml"):
        code, out = whatif(str(tmp_path / lab), "--vary", "devices.reactor.instances=1,2", "--seeds", "2", "--json")
        assert code == 0, out
        hours.append([v["lab_hours"] for v in json.loads(out[out.index("{"):])["variants"]])
    assert hours[0] == hours[1]


def test_a_lab_whose_scheduler_stalls_counts_at_the_campaigns_limit_not_as_the_shortest(tmp_path):
    """A shared lab's stall ends it at once in virtual time: `twin whatif` showed such a variant at 0.0 lab-h, the
    best of the table. As a bench does for a campaign on its own, each stalled campaign counts at its limit."""
    import yaml

    raw = yaml.safe_load((ROOT / "scenarios" / "shared_lab.yaml").read_text())
    for c, budget in zip(raw["campaigns"], (6, 4)):
        c["campaign"].update(budget=budget, planner="random", max_lab_hours=50)
    lab = tmp_path / "lab.yaml"
    lab.write_text(yaml.safe_dump(raw))
    code, out = whatif(str(lab), "--vary", "orchestrator.lab_scheduler=,tests.twin.test_bad_schedulers:Patient",
                       "--seeds", "2", "--json")
    assert code == 0, out
    data = json.loads(out[out.index("{"):])
    stalled = [r for r in data["runs"] if r["variant"] != "as written"]
    assert stalled and all("answered wait with no device busy" in r["stopped"] for r in stalled)
    assert all(r["lab_hours"] >= 50 and r["per_campaign"]["dots"] == 50 for r in stalled), stalled
    written = [r for r in data["runs"] if r["variant"] == "as written"]
    assert all(r["lab_hours"] < 50 for r in written)
