"""The band-gap problem: cost accounting adds up, and DFT-first search is cheaper than blind experiments."""

import json
import statistics
from pathlib import Path

from twin.campaign.journal_read import read_events
from twin.runtime.lab import prepare, run
from twin.tools.planner_bench import trial

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "scenarios" / "bandgap.yaml"


def test_cost_is_500_per_synthesis_attempt_and_nothing_for_dft(tmp_path):
    db = tmp_path / "j.db"
    s = run(SCENARIO, journal=db, bus="memory", overrides={"devices.synthesiser.faults.fail_p": 0.3})
    dispatched = read_events(db, "attempt.dispatched")
    synth = [e for e in dispatched if e["device"].startswith("synthesiser")]
    dft = [e for e in dispatched if e["device"].startswith("dft")]
    assert dft and synth
    assert s.cost == 500 * len(synth)
    assert s.failed_attempts > 0, "failed syntheses are paid for too"
    assert all(v <= s.cost for v in s.targets_met_cost.values())


def test_spending_stops_at_the_cost_budget(tmp_path):
    s = run(SCENARIO, journal=tmp_path / "j.db", bus="memory", overrides={
        "campaign.max_cost": 2000, "campaign.planner": "random", "campaign.stop_on_target": False})
    assert 2000 <= s.cost <= 2000 + 500 * s.proposed
    assert s.proposed < 10


def test_the_calculator_is_used_first_and_experiments_follow_its_map(tmp_path):
    db = tmp_path / "j.db"
    run(SCENARIO, journal=db, bus="memory", seed=2)
    dispatched = read_events(db, "attempt.dispatched")
    first_synth = min(e["t_lab"] for e in dispatched if e["device"].startswith("synthesiser"))
    dft_results = [e for e in read_events(db, "msg.result") if e["device"].startswith("dft")]
    assert len([e for e in dft_results if e["t_lab"] <= first_synth]) >= 12
    assert all("band_gap_dft_ev" in json.loads(e["detail"])["body"]["outputs"] for e in dft_results)


def test_multi_fidelity_reaches_the_gap_for_less_money_than_random():
    s = prepare(SCENARIO)
    mf = [trial(s, "mf-gp-bo", seed) for seed in range(8)]
    rnd = [trial(s, "random", seed) for seed in range(8)]
    assert all(t.reached for t in mf)
    assert statistics.median(t.cost for t in mf) < statistics.median(t.cost for t in rnd)
    assert statistics.mean(t.cost for t in mf) * 1.5 <= statistics.mean(t.cost for t in rnd)
