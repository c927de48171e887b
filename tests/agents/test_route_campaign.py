"""Routes run in the lab twin: the route planner's reactions as react -> purify -> LC-MS experiments, with faults,
an alternative route when a reaction keeps failing, and the chemistry of each step (RDKit masses)."""

from __future__ import annotations

import json
import logging
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from devices.models import synthesis
from twin import ScenarioError, load_scenario, prepare, run
from twin.runtime.checks import check

ROOT = Path(__file__).resolve().parents[2]
ASPIRIN = ROOT / "scenarios" / "aspirin.yaml"
ASPIRIN_SMILES = "CC(=O)Oc1ccccc1C(=O)O"


def campaign(tmp_path: Path, **overrides):
    journal = tmp_path / "journal.db"
    s = prepare(ASPIRIN, clock="virtual", bus="memory", overrides=overrides)
    summary = run(s, journal=journal)
    db = sqlite3.connect(journal)
    rows = [(json.loads(p), status, json.loads(o) if o else None)
            for p, status, o in db.execute("SELECT params, status, outputs FROM experiments ORDER BY id")]
    db.close()
    return summary, rows


def test_aspirin_is_made_in_one_step_from_salicylic_acid_with_faults_injected(tmp_path):
    # at this seed the fault draws fail the first attempt of every step (twin.device.driver.simulated_faults)
    summary, rows = campaign(tmp_path, **{"campaign.seed": 2, "devices.synthesiser.faults.fail_p": 0.5,
                                         "devices.purifier.faults.fail_p": 0.5})
    assert summary.targets_met_h.get("aspirin") is not None
    assert summary.failed_attempts > 0  # the faults happened, and the orchestrator retried through them
    assert summary.done + summary.abandoned + summary.pending == summary.proposed
    first = rows[0][0]
    assert first["reaction"] == f"CC(=O)OC(C)=O.O=C(O)c1ccccc1O>>{first['product']}"
    assert first["plan"] == [first["reaction"]] and first["steps"] == 1 and first["final"]
    met = [o for _, status, o in rows if o and o.get("target_mg", 0) >= 500 and o.get("target_purity_pct", 0) >= 98]
    assert met and abs(met[0]["mz_found"] - 181.0495) < 0.01  # [M+H]+ of C9H8O4


def test_a_reaction_class_that_always_fails_is_routed_around(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="agents.routes.campaign")
    summary, rows = campaign(tmp_path, **{"chemistry.options": {"failing": ["acylation"]},
                                         "devices.synthesiser.faults.fail_p": 0.0})
    assert summary.targets_met_h.get("aspirin") is not None
    acylations = [(p, o) for p, _, o in rows if p["class"] == "acylation"]
    assert len(acylations) == 2 and all(o["yield_pct"] < 10 for _, o in acylations)  # next to nothing, twice
    routes = sorted({p["route"] for p, _, _ in rows})
    assert routes[0] == 1 and routes[-1] >= 2
    final = [p for p, _, o in rows if p["final"] and o and o.get("target_mg", 0) >= 500]
    assert final and final[0]["class"] != "acylation" and final[0]["route"] >= 2
    assert "failed (2 of 2)" in caplog.text


def test_intermediates_are_made_first_and_handed_on_as_lots(tmp_path):
    # lidocaine needs two or more reactions: each later one takes the lot an earlier one made
    summary, rows = campaign(tmp_path, **{"campaign.planner_options": {"molecule": "CCN(CC)CC(=O)Nc1c(C)cccc1C",
                                                                       "method": "breadth-first"},
                                         "chemistry.targets": [{"name": "lidocaine",
                                                                "outputs": {"target_mg": {"min": 200}}}]})
    assert summary.targets_met_h.get("lidocaine") is not None
    made = {}
    for p, status, o in rows:
        for lot in p["lots"]:
            assert lot["smiles"] in made and lot["made_at_s"] == made[lot["smiles"]]["made_at_s"]
        if o:
            made[p["product"]] = o
    assert rows[0][0]["steps"] >= 2 and any(p["lots"] for p, _, _ in rows)


def test_no_route_ends_the_campaign_with_the_reason(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="agents.routes.campaign")
    summary, rows = campaign(tmp_path, **{"campaign.planner_options": {"molecule": "C1CC2CCC1C2[Si](C)(C)C",
                                                                       "method": "breadth-first", "seconds": 2}})
    assert summary.proposed == 0 and not summary.targets_met_h
    assert "no route to" in caplog.text


def test_a_molecule_rdkit_cannot_read_is_refused_naming_the_field():
    s = load_scenario(ASPIRIN).model_copy(deep=True)
    s.campaign.planner_options["molecule"] = "C1CC(("
    with pytest.raises(ScenarioError) as err:
        check(s)
    assert "campaign.planner_options.molecule" in str(err.value) and "SMILES" in str(err.value)
    s.campaign.planner_options.update(molecule="CCO", stock="no/such/stock.csv")
    with pytest.raises(ScenarioError, match=r"campaign.planner_options.stock: no/such/stock.csv: cannot read"):
        check(s)


def test_lcms_reports_the_exact_mass_and_purification_trades_mass_for_purity():
    rng = np.random.default_rng(0)
    params = {"reaction": f"CC(=O)OC(C)=O.O=C(O)c1ccccc1O>>{ASPIRIN_SMILES}", "scale_mmol": 5.0,
              "yield_pct": [80, 90], "final": True}
    crude = synthesis.react(params, 0.0, 0.0, [], rng)
    pure = synthesis.purify(crude, rng)
    before = synthesis.lcms(crude, params, 0.0, 0.0, 0.0, rng)
    after = synthesis.lcms(pure, params, 0.0, 0.0, 0.0, rng)
    assert before["mz_expected"] == pytest.approx(181.0495, abs=1e-3)
    assert after["purity_pct"] > before["purity_pct"] and after["product_mg"] < before["product_mg"]
    assert 80 * 0.75 <= after["yield_pct"] <= 90
    assert after["target_mg"] == after["product_mg"]
    # a week on the shelf at a stability of one day: most of it has turned into something else
    old = synthesis.lcms(pure, params, 7 * 86400.0, 86400.0, 0.0, rng)
    assert old["purity_pct"] < 5 and old["age_s"] == 7 * 86400.0
    # a failing class gives no product, and an aged intermediate gives less
    assert synthesis.react(params | {"class": "acylation"}, 0.0, 0.0, ["acylation"], rng)["product_mg"] < 0.03 * 5 * 181
    lot = {"smiles": ASPIRIN_SMILES, "purity": 1.0, "made_at_s": 0.0}
    assert synthesis.aged(lot, 86400.0, 86400.0) == pytest.approx(np.exp(-1))


def test_a_reaction_the_planner_did_not_write_is_refused_by_the_synthesiser():
    from devices.synthesiser import Synthesiser
    from twin import DriverError, driver_setup, run_step

    s = load_scenario(ASPIRIN)
    setup = driver_setup(chemistry=s.chemistry)
    with pytest.raises(DriverError, match="reaction"):
        run_step(Synthesiser(setup), "react", {"scale_mmol": 1.0})
    with pytest.raises(DriverError, match="RDKit"):
        run_step(Synthesiser(setup), "react", {"reaction": "C1((>>C", "scale_mmol": 1.0})


def test_the_recording_shows_the_route_drawn_and_each_step_state(tmp_path):
    from tests.rrd import read_rrd
    from twin import RecordOptions

    rrd = tmp_path / "route.rrd"
    s = prepare(ASPIRIN, clock="virtual", bus="memory", overrides={"chemistry.options": {"failing": ["acylation"]}})
    run(s, journal=tmp_path / "journal.db", record=RecordOptions(save=rrd))
    data = read_rrd(rrd)
    images = [r for r in data["route/plan"] if "EncodedImage:blob" in r]
    assert len(images) >= 2  # the first route, then the alternative
    assert bytes(images[0]["EncodedImage:blob"][0][:8]) == b"\x89PNG\r\n\x1a\n"
    tables = [r["TextDocument:text"][0] for r in data["route/steps"]]
    assert any("running on synthesiser" in t for t in tables)
    last = tables[-1]
    assert "O-acetylation" in last and "done:" in last and last.count("| 1 |") >= 2


def test_the_reagents_bought_are_part_of_the_campaigns_cost(tmp_path):
    free = {f"devices.{d}.cost": 0 for d in ("synthesiser", "purifier", "spectrometer")}
    summary, rows = campaign(tmp_path, **free, **{"chemistry.targets": [
        {"name": "aspirin", "outputs": {"target_mg": {"min": 50000}}}], "campaign.budget": 3})
    spent = sum(p["reagents_eur"] for p, _, _ in rows)
    assert spent > 0 and summary.cost == pytest.approx(spent)


def test_a_proposals_cost_survives_the_journal_a_resumed_core_is_rebuilt_from():
    from twin import Proposal
    from twin.campaign.events import Proposed
    from twin.campaign.replay import decode_input, encode
    from twin.core.messages import to_wire

    written = to_wire({"events": [encode(Proposed([Proposal({"x": 1.0}, None, 2.5), Proposal({"x": 2.0})]))]})
    back = decode_input(json.loads(written)["events"][0])
    assert [p.cost for p in back.proposals] == [2.5, 0.0] and back.proposals[0].params == {"x": 1.0}


def test_a_campaign_whose_planner_had_no_route_says_so_in_its_summary(tmp_path):
    """The campaign ended at once, and its summary (and `twin report`, later) said nothing of why: 0 experiments
    of 0 proposed. It now says the planner proposed no more, and the planner's reason; a campaign that met its
    targets says nothing."""
    from twin.campaign.journal_read import read_run

    (tmp_path / "none").mkdir()
    (tmp_path / "made").mkdir()
    none, _ = campaign(tmp_path / "none", **{"campaign.planner_options": {"molecule": "C1CC2CCC1C2[Si](C)(C)C",
                                                                           "method": "breadth-first", "seconds": 2}})
    assert none.ended.startswith("the planner proposed no more experiments after 0 of the budget's 20: no route to ")
    assert none.ended.endswith(": no route within 6 steps from this stock and these templates") and not none.stopped
    assert read_run(tmp_path / "none" / "journal.db")["summary"]["ended"] == none.ended
    made, _ = campaign(tmp_path / "made")
    assert made.targets_met_h and made.ended == ""
