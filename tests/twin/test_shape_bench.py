"""`twin bench schedulers --shapes`: a family of lab variants, each scheduler against the shape's best rule."""

import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import qd_lab, twin_cli
from twin.scenario import parse
from twin.tools.shape_bench import shapes, variants, verdict

ROOT = Path(__file__).resolve().parents[2]


def test_each_shape_compares_every_scheduler_with_its_best_rule_on_paired_seeds():
    s = parse(qd_lab(**{"campaign.budget": 4, "chemistry.stability_s": 3600}))
    names = [n for n, _ in variants(s)]
    assert names[0] == "as written" and "synthesiser bottleneck (mean_s ×2)" in names
    assert "samples keep ¼ as long" in names and len(names) == 1 + 3 * 2 + 1
    # two spectrometers behind one synthesiser: twice as long would still leave them waiting on it
    assert "spectrometer bottleneck (mean_s ×2.5)" in names
    results = shapes(s, ["fifo", "spt"], seeds=3)
    assert [c.shape for c in results] == names
    for c in results:
        assert c.diffs[c.best_rule] == (0.0, 0.0)
        other = "spt" if c.best_rule == "fifo" else "fifo"
        assert c.diffs[other][0] >= 0 and c.diffs[other][1] >= 0  # the best rule has the lowest mean
    assert (verdict(-1.0, 0.5), verdict(1.0, 0.5), verdict(0.2, 0.5)) == ("better", "worse", "same")


@pytest.mark.parametrize("seed", range(4))
def test_a_bottleneck_shape_makes_its_stage_the_busiest_of_the_lab_whatever_the_lab(seed, tmp_path):
    """The bottleneck shape doubled a stage's duration, which left flaky_lab's synthesisers 35 % busy beside its
    reactors' 90 %: a "synthesiser bottleneck" that was none. Each is now made the lab's busiest stage, by a
    quarter, on labs of any shape (drawn as training draws them)."""
    import random

    from twin import random_lab, run
    from twin.scenario.bottleneck import MARGIN, bottleneck, stage_loads

    lab = random_lab(parse(qd_lab(**{"campaign.budget": 12})), random.Random(seed))
    for name, variant in variants(lab):
        if " bottleneck (" not in name:
            continue
        stage = name.split(" bottleneck")[0]
        factor = bottleneck(lab, stage)
        assert name.endswith(f"(mean_s ×{factor:g})") and factor >= 2
        loads = stage_loads(variant)
        assert all(loads[stage] >= MARGIN * load * 0.999 for other, load in loads.items() if other != stage), loads
        used = run(variant, journal=tmp_path / f"{stage}.db").utilisation
        busy = {dtype: sum(u for device, u in used.items() if device.rsplit("-", 1)[0] == dtype) /
                variant.devices[dtype].instances for dtype in variant.devices}
        assert max(busy, key=busy.get) == stage, (name, busy)


def test_the_cli_refuses_shapes_of_a_job_shop_and_says_what_to_use(tmp_path):
    out = twin_cli("bench", "schedulers", "scenarios/jobshop.yaml", "--shapes", "--schedulers", "mwkr")
    assert out.exit_code == 2 and "--jobshop" in out.stderr


# what the bench's own process logs, which the test's process would catch
def test_a_bench_keeps_device_alerts_out_of_its_output_that_a_single_run_prints(tmp_path, caplog):
    crashing = ["devices.spectrometer.instances=1", "devices.spectrometer.faults.mtbc_h=0.5"]
    from twin import run

    with caplog.at_level("WARNING"):
        run(ROOT / "scenarios" / "flaky_lab.yaml", journal=tmp_path / "j.db", seed=0, bus="memory", clock="virtual",
            overrides={"campaign.budget": 8, "devices.spectrometer.instances": 1,
                       "devices.spectrometer.faults.mtbc_h": 0.5})
    assert "devices.unavailable spectrometer" in caplog.text  # one campaign alone says so
    res = subprocess.run([sys.executable, "-m", "twin", "bench", "schedulers", "scenarios/flaky_lab.yaml",
                          "--seeds", "2", "--budget", "8", "--workers", "1", "--schedulers",
                          "fifo,rl:agents/policies/flaky_scheduler.zip",
                          *[x for c in crashing for x in ("--set", c)]],
                         capture_output=True, text=True, cwd=ROOT, timeout=120, env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert res.returncode == 0, res.stderr
    assert "devices.unavailable" not in res.stderr
    rows = [line.split()[:1] for line in res.stdout.splitlines()]
    assert ["fifo"] in rows and ["rl:flaky_scheduler"] in rows, res.stdout
    raising = subprocess.run([sys.executable, "-m", "twin", "bench", "schedulers", "scenarios/flaky_lab.yaml",
                              "--seeds", "2", "--budget", "4", "--workers", "1", "--schedulers", "fifo", "--set",
                              "devices.spectrometer.driver=tests.twin.test_bad_drivers:Raises"],
                             capture_output=True, text=True, cwd=ROOT, timeout=120,
                             env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert raising.returncode == 0 and "driver raised" not in raising.stderr, raising.stderr[-2000:]
    assert any(line.split()[:1] == ["fifo"] for line in raising.stdout.splitlines()), raising.stdout


# in a process of its own: the workers' own stderr
def test_a_bench_of_several_shops_warns_of_a_policy_s_misfit_once_per_shop(tmp_path):
    """The workers made the scheduler again for each run and repeated the command's warning for every shop after
    the first (the first's they had inherited, forked after it)."""
    files = []
    for name in ("two_a", "two_b", "two_c"):
        (tmp_path / f"{name}.txt").write_text("2 2\n0 3 1 4\n1 2 0 5\n")
        files.append(str(tmp_path / f"{name}.txt"))
    res = subprocess.run([sys.executable, "-m", "twin", "bench", "schedulers", "scenarios/jobshop.yaml", "--jobshop",
                          ",".join(files), "--workers", "2", "--schedulers",
                          "fifo,mwkr,rl:agents/policies/jobshop_scheduler.zip"],
                         capture_output=True, text=True, cwd=ROOT, timeout=120, env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"})
    assert res.returncode == 0, res.stderr
    for name in ("two_a", "two_b", "two_c"):
        assert res.stderr.count(f"trained on labs unlike 'jobshop_{name}'") == 1, res.stderr
        assert f"{name} — 1 run per scheduler; CP-SAT optimum 8 lab-s" in res.stdout, res.stdout


def test_shapes_give_every_run_and_every_comparison_to_machines(tmp_path):
    import csv
    import json
    import statistics

    out = twin_cli("bench", "schedulers", "scenarios/quantum_dots.yaml", "--shapes", "--seeds", "2", "--budget", "3",
                   "--workers", "1", "--schedulers", "fifo,spt", "--csv", tmp_path / "runs.csv", "--json")
    assert out.exit_code == 0, out.stderr
    data = json.loads(out.stdout)
    shapes_run = {c["shape"] for c in data["comparisons"]}
    assert len(data["runs"]) == len(shapes_run) * 2 * 2 and "as written" in shapes_run
    with open(tmp_path / "runs.csv") as f:
        assert len(list(csv.DictReader(f))) == len(data["runs"])
    for c in data["comparisons"]:  # each verdict is the mean of the seeds' differences to the best rule
        span = {(r["scheduler"], r["seed"]): r["makespan_h"] for r in data["runs"] if r["shape"] == c["shape"]}
        diffs = [span[c["scheduler"], seed] - span[c["best_rule"], seed] for seed in (0, 1)]
        assert abs(statistics.mean(diffs) - c["diff_h"]) < 1e-9


def test_by_objective_each_degraded_sample_and_abandoned_experiment_counts_as_the_weights_say(tmp_path):
    import json

    from twin import time_scale

    raw = qd_lab(**{"chemistry.stability_s": 120, "campaign.max_in_flight": 4, "devices.synthesiser.instances": 2,
                    "devices.spectrometer.instances": 1, "devices.spectrometer.duration.mean_s": 200,
                    "training.weights": {"time": 2.0, "degraded": 3.0, "abandoned": 5.0}})
    lab = parse(raw)
    (tmp_path / "lab.yaml").write_text(__import__("yaml").safe_dump(raw))
    args = ["--shapes", "--seeds", "3", "--budget", "6", "--workers", "1", "--schedulers", "fifo,spt,oldest-sample",
            "--by", "objective", "--json"]
    out = twin_cli("bench", "schedulers", tmp_path / "lab.yaml", *args)
    assert out.exit_code == 0, out.stderr
    data = json.loads(out.stdout)
    unit = time_scale(lab)  # the shape as written: its typical step
    runs = {(r["scheduler"], r["seed"]): r for r in data["runs"] if r["shape"] == "as written"}
    assert any(r["degraded"] for r in runs.values())  # the objective differs from the makespan here

    def objective_h(r):
        return r["makespan_h"] + (3.0 * r["degraded"] + 5.0 * r["lost"]) * unit / 2.0 / 3600

    for c in (c for c in data["comparisons"] if c["shape"] == "as written"):
        assert c["by"] == "objective"
        diffs = [objective_h(runs[c["scheduler"], s]) - objective_h(runs[c["best_rule"], s]) for s in (0, 1, 2)]
        assert abs(sum(diffs) / 3 - c["diff_h"]) < 1e-6
        assert min(sum(objective_h(runs[n, s]) for s in (0, 1, 2)) for n in ("fifo", "spt", "oldest-sample")) == (
            sum(objective_h(runs[c["best_rule"], s]) for s in (0, 1, 2)))
    no_time = tmp_path / "no_time.yaml"
    no_time.write_text(__import__("yaml").safe_dump(qd_lab(**{"training.weights": {"time": 0}})))
    refused = twin_cli("bench", "schedulers", no_time, *args)
    assert refused.exit_code == 2 and "training.weights.time, which is 0" in refused.stderr


def test_a_lab_that_stops_at_its_targets_is_compared_with_a_word_on_chance():
    """catalyst's shapes by lab-h to target with a random planner: one scheduler's seed took 4 h and another's 31 h,
    as the first experiment to meet the target came at a different turn; the table now says so, and how to
    compare on the whole budget."""
    def bench(*extra):
        return twin_cli("bench", "schedulers", "scenarios/quantum_dots.yaml", "--shapes", "--seeds", "2", "--budget",
                        "3", "--workers", "1", "--schedulers", "fifo,spt", *extra, columns=100)

    said = " ".join(bench().stdout.split())
    assert "chance weighs on every row; --set campaign.stop_on_target=false compares the schedulers" in said
    said = " ".join(bench("--set", "campaign.stop_on_target=false").stdout.split())
    assert "chance" not in said and "as written" in said


def test_a_bench_runs_seed_by_seed_so_its_progress_is_a_fair_share_of_the_whole():
    """Name by name, a slow scheduler's runs all came last: the bar said a minute and a half was left of a bench
    that took eight more (online CP-SAT, a minute a run). Every name's runs now go seed by seed, and each name's
    results stay in seed order, as the paired comparisons read them."""
    from twin.tools.planner_bench import over_seeds

    class InOrder:  # the bench pool's map, in this process
        @staticmethod
        def map(one, jobs):
            return map(one, jobs)

    done: list[tuple[str, int]] = []
    results = over_seeds(lambda job: (job[1], job[2]), None, ["fifo", "cp-sat", "rl:p.zip"], 3, 1, done.append,
                         InOrder())
    assert [name for name, _ in done[:3]] == ["fifo", "cp-sat", "rl:p.zip"]  # a share of each in the first third
    assert results == {name: [(name, seed) for seed in range(3)] for name in ("fifo", "cp-sat", "rl:p.zip")}


def test_a_scheduler_that_may_take_minutes_a_campaign_is_said_before_the_bench_runs(monkeypatch):
    """cp-sat on a lab of 1,800 decisions a campaign (1 s each at most) sat behind a bar reading "about 0:00:30
    left" (from the rules' quick runs) for half an hour a campaign, unannounced."""
    from twin.runtime.lab import make_scheduler, prepare
    from twin.tools.scheduler_bench import slow_schedulers

    wide = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides={"campaign.budget": 600})
    made = {name: make_scheduler(wide, name) for name in ("mwkr", "cp-sat")}
    assert slow_schedulers(wide, made, 20) == ("cp-sat decides in up to 1 s of wall time, about 1,800 decisions a "
                                               "campaign here: up to 30 min for each of its 20 campaigns (--set "
                                               "campaign.scheduler_options.time_limit_s=S gives it less)")
    quick = prepare(ROOT / "scenarios" / "flaky_lab.yaml",  # the rule beside it takes no such option
                    overrides={"campaign.budget": 600, "campaign.scheduler_options": {"time_limit_s": 0.1}})
    made = {name: make_scheduler(quick, name) for name in ("mwkr", "cp-sat")}
    assert made["cp-sat"].time_limit_s == 0.1 and slow_schedulers(quick, made, 20) == ""  # 3 min at most
    small = prepare(ROOT / "scenarios" / "flaky_lab.yaml")  # 180 decisions: 3 min at most, said nothing
    assert slow_schedulers(small, {n: make_scheduler(small, n) for n in ("mwkr", "cp-sat")}, 20) == ""
    ft10 = prepare(ROOT / "scenarios" / "jobshop.yaml", overrides={"jobshop.file": "jobshop/ft10.txt"})
    cp_sat = {"cp-sat": make_scheduler(ft10, "cp-sat")}
    assert slow_schedulers(ft10, cp_sat, 1) == ""  # a job shop's decisions are its operations: 100, 100 s at most
    monkeypatch.setattr("twin.tools.scheduler_bench.SLOW_RUN_S", 60.0)
    assert "about 100 decisions a campaign here: up to 2 min for each of its 1 campaign" in \
        slow_schedulers(ft10, cp_sat, 1)
    res = twin_cli("bench", "schedulers", str(ROOT / "scenarios" / "flaky_lab.yaml"), "--schedulers", "mwkr",
                   "--seeds", "1", "--set", "campaign.budget=4")
    assert res.exit_code == 0 and "decides in up to" not in res.stderr
