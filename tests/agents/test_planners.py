"""Planners propose inside the box; GP-BO beats random by a margin that could fail; batches spread out."""

import statistics
from pathlib import Path

import numpy as np
import pytest

from agents.gp_bo import GpBoPlanner
from agents.planners import LhsPlanner, RandomPlanner
from tests.conftest import twin_cli
from twin.campaign.decisions import Outcome
from twin.tools.planner_bench import trial
from twin.runtime.lab import prepare
from twin.scenario import Parameter, Target

ROOT = Path(__file__).resolve().parents[2]
BOX = {"concentration_mm": Parameter(low=1, high=50), "temperature_c": Parameter(low=220, high=320),
       "time_s": Parameter(low=10, high=600)}
TARGETS = [Target.model_validate({"name": "G", "outputs": {"peak_nm": {"value": 520, "tol": 5}}})]


def history(n: int, seed: int = 0) -> list[Outcome]:
    from devices.models.quantum_dots import emission

    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        p = {k: float(rng.uniform(v.low, v.high)) for k, v in BOX.items()}
        peak = emission(p["concentration_mm"], p["temperature_c"] + 273.15, p["time_s"])["peak_nm"]
        out.append(Outcome(p, {"peak_nm": peak}, abs(peak - 520) / 5))
    return out


@pytest.mark.parametrize("planner", [RandomPlanner(BOX, seed=1), LhsPlanner(BOX, seed=1, budget=40),
                                     GpBoPlanner(BOX, seed=1, targets=TARGETS)])
def test_proposals_stay_inside_the_box(planner):
    for hist in ([], history(12)):
        for p in planner.propose(5, hist, []):
            assert set(p.params) == set(BOX)
            assert all(BOX[k].low <= v <= BOX[k].high for k, v in p.params.items())


def test_lhs_covers_every_stratum_of_every_parameter():
    design = LhsPlanner(BOX, seed=3, budget=20).propose(20, [], [])
    for name, box in BOX.items():
        strata = {int((p.params[name] - box.low) / (box.high - box.low) * 20) for p in design}
        assert strata == set(range(20))


def test_an_asynchronous_batch_never_repeats_a_pending_experiment():
    planner = GpBoPlanner(BOX, seed=2, targets=TARGETS)
    hist = history(15)
    pending = [p.params for p in planner.propose(3, hist, [])]
    batch = [p.params for p in planner.propose(4, hist, pending)]
    unit = lambda p: np.array([(p[k] - BOX[k].low) / (BOX[k].high - BOX[k].low) for k in BOX])  # noqa: E731
    points = [unit(p) for p in pending + batch]
    gaps = [np.linalg.norm(a - b) for i, a in enumerate(points) for b in points[i + 1:]]
    assert min(gaps) > 1e-3


def test_gp_bo_finds_the_targets_in_far_fewer_experiments_than_random():
    s = prepare(ROOT / "scenarios" / "quantum_dots.yaml", overrides={"campaign.budget": 150})
    gp = [trial(s, "gp-bo", seed) for seed in range(3)]
    rnd = [trial(s, "random", seed) for seed in range(3)]
    assert all(t.reached for t in gp)
    assert statistics.median(t.experiments for t in gp) * 3 <= statistics.median(t.experiments for t in rnd)


def test_gp_bo_does_not_propose_where_devices_refused():
    """A target the model places in the hot corner, where every try was refused: GP-BO stays where things ran."""
    rng = np.random.default_rng(4)
    hist = []
    for _ in range(40):
        p = {k: float(rng.uniform(v.low, v.high)) for k, v in BOX.items()}
        if p["temperature_c"] > 280:
            hist.append(Outcome(p, None, None, "infeasible: interlock", infeasible=True))
        else:  # the output rises with temperature: the model extrapolates the target past the interlock
            hist.append(Outcome(p, {"peak_nm": 400 + p["temperature_c"]}, None))
    hot = [Target.model_validate({"name": "R", "outputs": {"peak_nm": {"value": 710, "tol": 5}}})]
    planner = GpBoPlanner(BOX, seed=1, targets=hot)
    proposals = [p.params for p in planner.propose(8, hist, [])]
    assert all(p["temperature_c"] <= 290 for p in proposals), [round(p["temperature_c"]) for p in proposals]


def test_gp_bo_keeps_exploring_when_no_device_measures_what_the_targets_name():
    from agents.gp_bo import GpBoPlanner
    from tests.conftest import qd_lab
    from twin import Outcome
    from twin.scenario import parse

    s = parse(qd_lab())
    planner = GpBoPlanner(s.chemistry.parameters, 0, s.chemistry.targets)
    history = [Outcome(p.params, {"purity": 90.0}, None) for p in planner.propose(10, [], [])]
    proposals = planner.propose(3, history, [])  # a lab whose devices output "purity", targets "peak_nm"
    assert len(proposals) == 3 and all(set(p.params) == set(s.chemistry.parameters) for p in proposals)


def test_bench_planners_runs_a_row_with_another_scheduler_and_names_an_unknown_one(tmp_path):
    import csv
    import json

    from tests.conftest import twin_cli

    bench = ["bench", "planners", "scenarios/quantum_dots.yaml", "--seeds", "1", "--budget", "3", "--workers", "1"]
    res = twin_cli(*bench, "--planners", "lhs@fifo,lhs@spt~seq", "--json", "--csv", tmp_path / "runs.csv")
    assert res.exit_code == 0, res.stderr
    rows = {r["planner"]: r for r in json.loads(res.stdout)["rows"]}
    assert set(rows) == {"lhs@fifo", "lhs@spt~seq"}
    assert all(r["accel."] == "—" for r in rows.values())  # no random row to compare with
    with open(tmp_path / "runs.csv") as f:
        runs = list(csv.DictReader(f))
    assert sorted(r["planner"] for r in runs) == ["lhs@fifo", "lhs@spt~seq"] and all(int(r["experiments_run"]) == 3 for r in runs)
    bad = twin_cli(*bench, "--planners", "lhs@no-such-rule")
    assert bad.exit_code != 0 and "no-such-rule" in bad.stderr


def test_bench_planners_set_changes_the_lab_every_run_uses_and_names_a_field_that_does_not_exist():
    import json

    bench = ["bench", "planners", "scenarios/quantum_dots.yaml", "--seeds", "1", "--budget", "3", "--workers", "1",
             "--planners", "lhs", "--json"]
    hours = {}
    for in_lab in (1, 3):
        res = twin_cli(*bench, "--set", f"campaign.max_in_flight={in_lab}")
        assert res.exit_code == 0, res.output
        (run,) = json.loads(res.stdout)["runs"]
        assert run["experiments_run"] == 3
        hours[in_lab] = run["lab_hours"]
    assert hours[1] > 1.5 * hours[3]  # the same three experiments, one at a time on one synthesiser of two
    bad = twin_cli(*bench, "--set", "campaign.max_in_flihgt=2")
    assert bad.exit_code == 2 and "max_in_flihgt" in bad.output, bad.output


def test_bench_tables_read_at_80_columns():
    res = twin_cli("bench", "planners", "scenarios/quantum_dots.yaml", "--seeds", "1", "--budget", "3",
                   "--workers", "1", "--planners", "random,lhs", columns=80)
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert max(len(line) for line in lines) <= 80 and "…" not in res.output
    assert any(line.split()[:1] == ["random"] for line in lines) and "accel.: random's median" in " ".join(res.output.split())


def test_bench_planners_leaves_out_a_cost_column_of_noughts_and_keeps_it_where_experiments_cost():
    """Where nothing costs, the column of noughts folded 'rl:quantum_dots~seq' over two lines at 80 columns."""
    def head(*more):
        res = twin_cli("bench", "planners", *more, "--seeds", "1", "--budget", "3", "--workers", "1",
                       "--planners", "random,lhs", columns=80)
        assert res.exit_code == 0, res.output
        words = " ".join(res.output.split())
        return next(line.split() for line in res.output.splitlines() if line.split()[:1] == ["planner"]), words

    free, says = head("scenarios/quantum_dots.yaml")
    assert "cost" not in free and "no device costs anything (devices.*.cost, cost_per_hour), so no cost column" in says
    paid, says = head("scenarios/bandgap.yaml")
    assert "cost" in paid and "cost: at the last target (median)" in says


@pytest.mark.parametrize("proposals, says", [
    ([{"temperature_k": 400, "time_s": 900}], "proposals.0: each proposal is {params: {name: value, ...}}"),
    ([{"temperature_k": 400, "time_s": 900}], "(it has temperature_k, time_s: put the parameters under params)"),
    ([{"params": {"temperature_k": 400}}, {"params": {}, "route": [{"step": "react"}]}],
     "proposals.1.route: a list of {step, device}"),
    ([], "proposals: the fixed planner proposes a list given there, and it is empty"),
    # what the lab would abandon before sending anything: said by `twin validate`, naming the entry (was: at run time)
    ([{"params": {"temperature_k": 400, "time_s": 900}}, {"params": {"temperature_k": 900, "time_s": 900}}],
     "campaign.planner_options.proposals.1: temperature_k = 900 is outside chemistry.parameters.temperature_k"),
    ([{"params": {"time_s": 900}}], "campaign.planner_options.proposals.0: temperature_k is missing"),
    ([{"params": {"temperature_k": 400, "time_s": 900}, "route": [{"step": "react", "device": "furnace"}]}],
     "campaign.planner_options.proposals.0: route step 0: no device type 'furnace' in the lab"),
])
def test_fixed_proposals_in_another_form_are_refused_naming_the_entry_and_the_form(proposals, says):
    import re

    from twin import ScenarioError
    from twin.runtime.checks import check

    s = prepare(ROOT / "scenarios" / "flaky_lab.yaml",
                overrides={"campaign.planner": "fixed", "campaign.planner_options": {"proposals": proposals}})
    with pytest.raises(ScenarioError, match=re.escape(says)):
        check(s)


class CrashingPlanner:
    """Proposes the box's centre twice, then raises: the campaign ends early, short of every target."""

    def __init__(self, parameters, seed):
        self.box, self.asked = parameters, 0

    def propose(self, n, history, pending):
        from twin import Proposal

        self.asked += 1
        if self.asked > 2:
            raise RuntimeError("GP exploded")
        return [Proposal({k: (p.low + p.high) / 2 for k, p in self.box.items()}) for _ in range(n)]


def test_a_planner_that_fails_early_is_counted_at_the_budget_not_as_the_fastest():
    """A run its failed planner ended after 4 experiments read as '≥4 experiments, ≥1.3 lab-h' and an
    acceleration of '≥30×' over random: the best row of the bench. It now counts at the budget and
    campaign.max_lab_hours, as a stall does; and an acceleration over a censored row is an upper bound (≤),
    or nothing at all when random's is censored too."""
    from twin.tools.planner_bench import rows

    lab = prepare(ROOT / "scenarios" / "quantum_dots.yaml", overrides={"campaign.budget": 40,
                                                                        "campaign.max_lab_hours": 500})
    failed = trial(lab, "tests.agents.test_planners:CrashingPlanner", 0)
    assert "GP exploded" in failed.stopped and failed.experiments_run < 10
    assert not failed.reached and failed.experiments == 40 and failed.lab_hours == 500
    results = {"random": [trial(lab, "random", s) for s in (0, 1)], "gp-bo": [trial(lab, "gp-bo", s) for s in (0, 1)],
               "crash": [failed, trial(lab, "tests.agents.test_planners:CrashingPlanner", 1)]}
    table = {row[0]: row for row in rows(results)}
    random_censored = sum(t.reached for t in results["random"]) / 2 < 0.5
    assert table["crash"][1].startswith("≥40")
    assert (table["crash"][-1] == "—") if random_censored else table["crash"][-1].startswith("≤")
    assert all(t.reached for t in results["gp-bo"])  # not censored: its ratio a bound only by random's
    first = table["gp-bo"][-1][0]
    assert (first == "≥") if random_censored else first.isdigit()


def test_the_readmes_list_of_experiments_runs_as_given_and_a_lab_without_a_box_is_pointed_to_it(tmp_path):
    """The `fixed` planner was undocumented: a lab with no parameter box was told only to give one."""
    import json
    import re

    import yaml

    from twin import ScenarioError
    from twin.campaign.journal_read import read_events
    from twin.runtime.checks import check
    from twin.runtime.lab import run

    readme = (ROOT / "README.md").read_text()
    block = re.search(r"```yaml\n(campaign:\n  planner: fixed\n.*?)```", readme, re.S).group(1)
    campaign = yaml.safe_load(block)["campaign"]
    s = prepare(ROOT / "scenarios" / "quantum_dots.yaml", bus="memory",
                overrides={f"campaign.{k}": v for k, v in campaign.items()})
    summary = run(s, journal=tmp_path / "j.db")
    given = [p["params"] for p in campaign["planner_options"]["proposals"]]
    assert summary.proposed == summary.done == len(given) == 2 and "all 2 of" in summary.ended
    proposed = [json.loads(e["detail"]) for e in read_events(tmp_path / "j.db", "experiment.proposed")]
    assert proposed == given  # in order, as given

    lab = {"name": "boxless", "lab": "boxless", "devices": {"oven": {"driver": "machine", "steps": ["bake"],
                                                                     "duration": {"mean_s": 600}}},
           "workflow": [{"step": "bake", "device": "oven"}], "campaign": {"planner": "random", "budget": 3}}
    (tmp_path / "boxless.yaml").write_text(yaml.safe_dump(lab))
    with pytest.raises(ScenarioError, match=r"give at least one parameter with low and high, or run a list of "
                                            r"experiments as given \(campaign.planner: fixed"):
        check(prepare(tmp_path / "boxless.yaml"))
