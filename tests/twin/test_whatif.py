"""`twin whatif` as a user meets it: variants of a lab over paired seeds, the bottleneck named, files for machines
and for the viewer, and clear refusals of what cannot run."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

from tests.conftest import twin_cli
from twin.tools.whatif import cheapest_within

ROOT = Path(__file__).resolve().parents[2]
FLAKY = str(ROOT / "scenarios" / "flaky_lab.yaml")


def whatif(*args):
    res = twin_cli("whatif", *args, columns=80)
    return res.exit_code, res.stdout if "--json" in args else res.output  # progress lines go to stderr


def test_more_of_the_bottleneck_saves_lab_hours_and_more_of_another_type_does_not(tmp_path):
    code, out = whatif(FLAKY, "--vary", "devices.reactor.instances=3", "--vary", "devices.spectrometer.instances=2,3",
                       "--seeds", "3", "--json", "--csv", str(tmp_path / "w.csv"), "--save", str(tmp_path / "w.rrd"))
    assert code == 0, out
    data = json.loads(out)
    rows = {r["variant"]: r for r in data["variants"]}
    assert list(rows)[0] == "as written" and len(rows) == 3  # reactor=3 with spectrometer=2 (as written) or 3
    base = rows["as written"]
    assert base["bottleneck"] == "reactor" and base["utilisation"]["reactor"] > base["utilisation"]["spectrometer"]
    more = rows["devices.reactor.instances=3, devices.spectrometer.instances=2"]
    assert more["lab_hours_change"][1] < 0 and more["lab_hours"][1] < base["lab_hours"][1]
    both = rows["devices.reactor.instances=3, devices.spectrometer.instances=3"]
    assert abs(both["lab_hours"][1] - more["lab_hours"][1]) < 0.1 * more["lab_hours"][1]
    assert sorted((r["variant"], r["seed"]) for r in data["runs"]) == sorted((v, s) for v in rows for s in range(3))
    with open(tmp_path / "w.csv") as f:
        table = list(csv.DictReader(f))
    assert [r["variant"] for r in table] == list(rows) and float(table[0]["utilisation_reactor"]) > 0.5

    from tests.rrd import read_rrd, rerun_verify

    assert rerun_verify(tmp_path / "w.rrd").returncode == 0
    rrd = read_rrd(tmp_path / "w.rrd")
    labels = rrd["whatif/tradeoff"][0]["Points2D:labels"]
    assert len(labels) == 3 and labels[0] == "0: as written"
    assert len(rrd["whatif/utilisation/reactor"][0]["BarChart:values"][0]["buffer"]) == 3


def test_the_table_fits_80_columns_and_names_the_busiest_device():
    code, out = whatif(FLAKY, "--vary", "devices.reactor.instances=1,3", "--seeds", "2")
    assert code == 0, out
    assert max(len(line) for line in out.splitlines()) <= 80
    assert "as written, the busiest device type is reactor" in " ".join(out.split())
    written = next(line.split() for line in out.splitlines() if line.split()[:1] == ["2*"])  # the scenario's own
    # its experiments to target, as --json has them: value, lab-h, IQR, Δ, exp.
    assert "exp." in out and "exp.: experiments to the last target" in " ".join(out.split())
    code, as_json = whatif(FLAKY, "--vary", "devices.reactor.instances=1,3", "--seeds", "2", "--json")
    assert float(written[4]) == json.loads(as_json)["variants"][0]["experiments"] > 0


def test_a_number_is_shown_as_the_scenario_and_the_variants_give_it():
    code, out = whatif(FLAKY, "--vary", "devices.spectrometer.duration.mean_s=240,480.5", "--set", "campaign.budget=4",
                       "--seeds", "1")
    assert code == 0, out
    firsts = [line.split()[0] for line in out.splitlines() if line.split()[:1] and line.split()[0][:1].isdigit()]
    assert firsts[:2] == ["240*", "480.5"], out  # the model reads 240 as 240.0


def test_a_list_or_mapping_is_shown_short_and_kept_whole_in_json():
    """chemistry.targets as written filled thirteen lines of the table with its every field."""
    code, out = whatif("scenarios/quantum_dots.yaml", "--vary", "chemistry.targets=[]", "--set", "campaign.budget=4",
                       "--seeds", "1")
    assert code == 0, out
    firsts = [line.split()[0] for line in out.splitlines() if line.split()[:1] and line.split()[0][:1] == "["]
    assert firsts == ["[R,", "[]"], out
    assert "[R, G, B]*" in out and "'tol'" not in out
    code, out = whatif("scenarios/quantum_dots.yaml", "--vary", 'campaign.planner_options={"n_init": 3, "candidates": '
                       '1000, "refit_every": 1},{"n_init": 4}', "--set", "campaign.budget=4", "--seeds", "1", "--json")
    assert code == 0, out
    assert json.loads(out)["variants"][1]["changes"]["campaign.planner_options"]["refit_every"] == 1
    code, out = whatif("scenarios/quantum_dots.yaml", "--vary", 'campaign.planner_options={"n_init": 3, "candidates": '
                       '1000, "refit_every": 1},{"n_init": 4}', "--set", "campaign.budget=4", "--seeds", "1")
    assert '{"n_init": 3, "candidates":' in out and "refit_every" not in out, out  # cut at 40 characters


@pytest.mark.parametrize("args,says", [
    (["--vary", "devices.nope.instances=1,2"], "devices.nope"),
    (["--vary", "devices.reactor.instances"], "expected FIELD=V1,V2"),
    (["--vary", "devices.reactor.instances=0"], "devices.reactor.instances"),
    (["--vary", "devices.reactor.instances=2"], "nothing to compare"),
    (["--schedulers", "nope"], "nope"),
    (["--vary", "campaign.scheduler=fifo,rl:missing.zip"], "policy missing.zip does not exist"),
    (["--vary", "devices.reactor.instances=3", "--seeds", "0"], "Invalid value for '--seeds'"),
    (["--vary", "devices.spectrometer.driver=spectrometer,reactor"],
     "--vary devices.spectrometer.driver=reactor: 1 problem - devices.spectrometer.driver: 'reactor' runs"),
    (["--vary", "campaign.planner=random,nope"], "--vary campaign.planner=nope"),
    # seeds are the paired runs' own: a varied or set seed would be overwritten in every run, silently
    (["--vary", "campaign.seed=1,2"], "'campaign.seed=1,2': the runs' seeds are 0 to N−1 (--seeds N)"),
    (["--vary", "devices.reactor.instances=3", "--set", "campaign.seed=4"], "--set campaign.seed: the runs' seeds"),
    # fields no run of a what-if reads: the variants ran alike and the table printed identical rows
    (["--vary", "clock.mode=scaled,wall"], "'clock.mode=scaled,wall': a what-if runs every variant on a virtual clock"),
    (["--vary", "bus.kind=memory,zenoh"], "every variant on a memory bus of its own"),
    (["--vary", "lab=a,b"], "so every variant would run alike; vary what the lab is"),
    (["--vary", "devices.reactor.instances=1,,3"], "reactor.instances: Input should be a valid integer (got None)"),
    (["--vary", "campaigns.0.after=,,dots"], "an empty value (null) is given twice"),
    (["--vary", "devices.reactor.instances=3,3.0"], "3.0 is given twice"),
    # --planners replaced the values --vary gave the same field: every "random" row ran gp-bo
    (["--vary", "campaign.planner=random,lhs", "--planners", "gp-bo"],
     "--vary campaign.planner and --planners both vary campaign.planner: give all its values once"),
    (["--vary", "campaign.scheduler=fifo", "--schedulers", "mwkr"], "both vary campaign.scheduler"),
    (["--vary", "devices.reactor.instances=3", "--budget-hours", "-1"], "--budget-hours -1: give the lab-hours"),
    (["--vary", "devices.reactor.instances=3", "--budget-hours", "nan"], "--budget-hours nan: give the lab-hours"),
    (["--vary", "devices.reactor.instances=3", "--save", "w.jpg"], "--save w.jpg: give a Rerun recording, w.rrd, or a "
     "picture, w.png (nothing has run)"),  # it wrote a recording named w.jpg
])
def test_what_cannot_run_is_refused_before_anything_runs(args, says):
    code, out = whatif(FLAKY, *args)
    assert code == 2 and says in " ".join(out.split()) and "Traceback" not in out, out


def test_the_cheapest_variant_within_the_hours_must_meet_every_target_in_every_run():
    def row(name, hours, cost, reached=5):
        return {"variant": name, "runs": 5, "reached": reached, "lab_hours": (hours, hours, hours),
                "cost": (cost, cost, cost)}

    summary = [row("as written", 10, 500), row("fast, dear", 6, 900), row("slow, cheap", 12, 100),
               row("quick, cheap, unreliable", 5, 50, reached=4), row("fast, cheaper", 7, 800)]
    assert cheapest_within(summary, 8)["variant"] == "fast, cheaper"
    assert cheapest_within(summary, 12)["variant"] == "slow, cheap"
    assert cheapest_within(summary, 4) is None
    free = [row("as written", 10, 0), row("faster", 6, 0), row("fastest", 5, 0)]
    assert cheapest_within(free, 8)["variant"] == "fastest"  # of equal costs, the fewest lab-hours
    # a lab without targets (a job shop) is judged by its whole campaign: a run reached nothing, yet it ended
    shops = [row("as written", 10, 500, reached=0), row("two m0", 7, 800, reached=0), row("three", 6, 900, reached=0)]
    assert cheapest_within(shops, 8) is None and cheapest_within(shops, 8, targets=False)["variant"] == "two m0"


def test_an_iqr_has_the_medians_decimals_where_whole_numbers_would_hide_it():
    """A median of 15.7 stood beside an IQR of "16–16"."""
    from twin.tools.whatif import AS_WRITTEN, rows

    def row(lo, mid, hi):
        return {"variant": AS_WRITTEN, "runs": 3, "reached": 3, "lab_hours": (lo, mid, hi), "lab_hours_change": None,
                "cost_change": None, "changes": {}, "bottleneck": "", "utilisation": {}, "cost": (0, 0, 0)}

    (narrow,), (wide,) = rows([row(15.62, 15.7, 15.81)], [], {}, True, frozenset()), \
        rows([row(95.2, 140.3, 210.7)], [], {}, True, frozenset())
    assert narrow[:2] == ["15.7", "15.6–15.8"] and wide[:2] == ["140.3", "95–211"]
    (some,) = rows([row(12.2, 14.3, 17.9)], [], {}, True, frozenset())
    assert some[:2] == ["14.3", "12–18"]  # whole numbers where they show the spread: the table stays narrow


def test_each_instance_costs_its_hours_busy_or_not_and_the_cheapest_variant_weighs_them(tmp_path):
    from twin import run

    every_attempt = {f"devices.{t}.cost": 10.0 for t in ("synthesiser", "reactor", "spectrometer")}
    changes = {"campaign.budget": 6, **every_attempt, "devices.spectrometer.cost_per_hour": 30.0}
    for n in (1, 2, 3):
        summary = run(FLAKY, journal=tmp_path / f"{n}.db", bus="memory",
                      overrides={**changes, "devices.spectrometer.instances": n})
        assert summary.cost == pytest.approx(10.0 * summary.attempts + 30.0 * n * summary.lab_hours)
        assert summary.hours_cost == pytest.approx(30.0 * n * summary.lab_hours)
    shown = f"| cost | {summary.cost:,.0f} ({summary.hours_cost:,.0f} of it the devices' hours) |"
    assert shown in summary._repr_markdown_().splitlines()  # the viewer's summary panel, a notebook's view
    # the spectrometers are not the bottleneck: a third saves no hours and costs its own
    code, out = whatif(FLAKY, "--vary", "devices.spectrometer.instances=3", "--set",
                       "devices.spectrometer.cost_per_hour=30", "--set", "campaign.stop_on_target=true",
                       "--seeds", "2", "--json")
    rows = {r["variant"]: r for r in json.loads(out)["variants"]}
    assert code == 0 and rows["devices.spectrometer.instances=3"]["cost_change"][1] > 0


def test_fields_in_lists_vary_and_columns_say_which_field_they_are(tmp_path):
    from twin.runtime.lab import prepare
    from twin.tools.whatif import header, variants, written_values

    s = prepare("scenarios/staffed_lab.yaml")
    axes = ["consumables.vials.simulate_refill.after_s", "orchestrator.recovery.0.simulate.after_s",
            "devices.synthesiser.instances"]
    assert header(axes)[:3] == ["simulate_refill\nafter_s", "simulate\nafter_s", "synthesiser\ninstances"]
    assert written_values(s, axes) == dict(zip(axes, [3600.0, 600.0, 2]))
    chosen = variants(s, [(axes[1], [60.0])])
    assert prepare(s, overrides=dict(chosen[-1].changes)).orchestrator.recovery[0].simulate.after_s == 60.0
    res = twin_cli("whatif", "scenarios/staffed_lab.yaml", "--vary",
                   "orchestrator.recovery.3.timeout_s=60", "--seeds", "2", columns=80)
    assert res.exit_code == 2 and "'3' is not an index of it (0-0)" in res.output


def test_a_whole_section_or_list_varies_and_commas_inside_it_do_not_split_values():
    """`--vary devices.spectrometer.faults={fail_p: 0.0},{fail_p: 0.3, hang_p: 0.1}` was cut at every comma into
    '{fail_p: 0.0}', '{fail_p: 0.3' and ' hang_p: 0.1}', each refused as not a mapping."""
    code, out = whatif(FLAKY, "--vary", "devices.spectrometer.faults={fail_p: 0.0},{fail_p: 0.3, hang_p: 0.1}",
                       "--set", "campaign.budget=24", "--seeds", "3", "--json")
    assert code == 0, out
    rows = {r["variant"]: r for r in json.loads(out)["variants"]}
    assert set(rows) == {"as written", "devices.spectrometer.faults={'fail_p': 0.0}",
                         "devices.spectrometer.faults={'fail_p': 0.3, 'hang_p': 0.1}"}, list(rows)
    never, often = rows["devices.spectrometer.faults={'fail_p': 0.0}"], \
        rows["devices.spectrometer.faults={'fail_p': 0.3, 'hang_p': 0.1}"]
    assert never["abandoned"] <= rows["as written"]["abandoned"] <= often["abandoned"] and often["abandoned"] > 0
    from twin.tools.whatif import parse_vary

    assert parse_vary(["training.duration_scale=[0.5, 1.5],[0.7,1.3]", "campaign.planner='a,b',random"]) == [
        ("training.duration_scale", [[0.5, 1.5], [0.7, 1.3]]), ("campaign.planner", ["a,b", "random"])]


def test_a_job_shop_of_minutes_reads_in_lab_seconds_and_a_played_ahead_run_saves_them(tmp_path):
    """Playing the shop ahead (campaign.rollouts) shortens it by seconds of a shop of minutes: shown as such, not
    as '0.224' and '-0.007' lab-h (nor, before that, '0.2' and '-0.0')."""
    shop = tmp_path / "la02.yaml"
    shop.write_text(f"name: la02\nlab: jobshop\njobshop: {{file: {ROOT / 'scenarios' / 'jobshop' / 'la02.txt'}}}\n"
                    f"campaign: {{scheduler: 'rl:{ROOT / 'agents' / 'policies' / 'jobshop_scheduler.zip'}'}}\n")
    code, out = whatif(str(shop), "--vary", "campaign.rollouts=32", "--seeds", "1")
    assert code == 0, out
    assert "lab-s" in out and "lab-s: lab-seconds of the whole campaign" in " ".join(out.split())
    table = {line.split()[0]: line.split()[1:4] for line in out.splitlines() if line.split()[:1] in (["1*"], ["32"])}
    (greedy, _, _), (played, _, saved) = table["1*"], table["32"]
    from twin.runtime.lab import run

    alone = run(shop, journal=tmp_path / "j.db", bus="memory", agent_in_process=True)  # the same lab, run by itself
    assert int(greedy) == round(alone.lab_hours * 3600), out  # whole lab-seconds, as the run took
    assert int(played) < int(greedy) and int(saved) == int(played) - int(greedy), out


def test_a_lab_that_runs_alike_on_every_seed_runs_once_per_variant_and_one_with_chance_runs_every_seed():
    """A job shop (no chance in durations or faults) gives the same run on every seed: twenty were run and shown
    with an IQR of nothing; a variant that brings chance in runs them all, the scenario as written too."""
    code, out = whatif("scenarios/jobshop.yaml", "--schedulers", "mwkr", "--seeds", "20", "--json")
    assert code == 0, out
    doc = json.loads(out)
    runs = [(r["variant"], r["seed"]) for r in doc["runs"]]
    assert doc["seeds"] == 1 and runs == [("as written", 0), ("campaign.scheduler=mwkr", 0)]
    code, out = whatif("scenarios/jobshop.yaml", "--schedulers", "mwkr", "--seeds", "20")
    assert "runs alike on every seed" in out and "One run per variant" in " ".join(out.split())
    code, out = whatif("scenarios/jobshop.yaml", "--vary", "devices.m0.faults.fail_p=0,0.3", "--seeds", "3", "--json")
    doc = json.loads(out)
    assert doc["seeds"] == 3 and len(doc["runs"]) == 6


def test_a_policy_is_shown_by_its_files_name_and_kept_whole_in_json(tmp_path):
    policy = f"rl:{ROOT / 'agents' / 'policies' / 'jobshop_scheduler.zip'}"
    code, out = whatif("scenarios/jobshop.yaml", "--schedulers", policy, "--seeds", "1")
    assert code == 0, out
    assert "rl:jobshop_scheduler " in out and "/agents/" not in out.split("busiest")[1]
    code, out = whatif("scenarios/jobshop.yaml", "--schedulers", policy, "--seeds", "1", "--json")
    assert policy in out


def test_set_changes_the_lab_every_variant_starts_from_and_degraded_samples_get_a_column():
    """flaky_lab with one reactor: samples wait for it past chemistry.stability_s, so the table has a 'degr.'
    column; the 'as written' row is the lab with --set, and a variant with three reactors degrades fewer."""
    code, out = whatif(FLAKY, "--set", "devices.reactor.instances=1", "--set", "campaign.budget=20",
                       "--vary", "devices.reactor.instances=3", "--seeds", "3", "--json")
    assert code == 0, out
    rows = {r["variant"]: r for r in json.loads(out)["variants"]}
    base, more = rows["as written"], rows["devices.reactor.instances=3"]
    assert base["experiments"] <= 20 and base["degraded"] > more["degraded"]
    code, out = whatif(FLAKY, "--set", "devices.reactor.instances=1", "--set", "campaign.budget=20",
                       "--vary", "devices.reactor.instances=3", "--seeds", "3")
    assert code == 0, out
    lines = out.splitlines()
    assert "with --set devices.reactor.instances=1, campaign.budget=20" in " ".join(out.split())
    head = next(line for line in lines if "lab-h" in line and "IQR" in line).split()
    first = next(line for line in lines if line.split()[:1] == ["1*"]).split()  # the base's reactors, marked
    assert head[-2:] == ["degr.", "busiest"]  # and the busiest is "reactor NN%", two words
    assert float(first[-3]) == pytest.approx(base["degraded"], abs=0.05)
    assert "degr.: samples degraded (mean)" in " ".join(out.split())


def test_a_stock_that_runs_out_is_named_with_how_long_it_was_out(tmp_path):
    """A lab whose vials run out, refilled after a while: the busiest device is not the whole story, so what
    if says which stock was out and for how long (the summary's out_h), and a quicker refill shortens it."""
    import yaml

    from tests.conftest import qd_lab

    lab = qd_lab(**{"campaign.budget": 12, "campaign.planner": "random", "consumables": {
        "vials": {"unit": "vials", "level": 4, "used_by": {"measure": 1}, "simulate_refill": {"after_s": 1800}}}})
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(lab))
    code, out = whatif(tmp_path / "lab.yaml", "--vary", "consumables.vials.simulate_refill.after_s=600", "--seeds",
                       "3", "--json")
    assert code == 0, out
    rows = {r["variant"]: r for r in json.loads(out)["variants"]}
    slow, quick = rows["as written"]["stock_out"]["vials"], rows["consumables.vials.simulate_refill.after_s=600"]
    assert slow >= 2 * 1800 / 3600 - 1e-9 and 0 < quick["stock_out"]["vials"] < slow  # 12 vials needed, 4 a rack
    code, out = whatif(tmp_path / "lab.yaml", "--vary", "consumables.vials.simulate_refill.after_s=600", "--seeds",
                       "3", "--csv", tmp_path / "w.csv")
    assert f"vials was out of stock for {slow:.2f} lab-h (mean), until its refill" in " ".join(out.split())
    with open(tmp_path / "w.csv") as f:
        assert [float(r["out_of_stock_h_vials"]) for r in csv.DictReader(f)] == pytest.approx(
            [slow, quick["stock_out"]["vials"]], abs=1e-4)
    code, out = whatif(FLAKY, "--vary", "devices.reactor.instances=3", "--seeds", "2")
    assert code == 0 and "out of stock" not in out  # no stock, nothing said


def test_a_lab_whose_samples_never_degrade_has_no_degraded_column():
    code, out = whatif(FLAKY, "--set", "chemistry.stability_s=0", "--vary", "devices.reactor.instances=3",
                       "--seeds", "2")
    assert code == 0, out
    assert "degr." not in out


@pytest.mark.process
@pytest.mark.parametrize("stop, code, said", [("ctrl-c", 130, "interrupted"), ("kill", 143, "terminated (SIGTERM)")])
def test_ctrl_c_or_sigterm_stops_the_workers_at_once_and_says_so(tmp_path, stop, code, said):
    """Ctrl-C reaches the whole process group: the workers used to take it as a failed run and go on, and the
    pool waited for every run submitted (a whatif of 40 runs went on for its whole length, silently). `kill PID`
    (SIGTERM) reaches the command alone: it used to end at once, leaving its workers alive for good, orphaned,
    waiting for runs that would never come."""
    import contextlib
    import os
    import signal
    import subprocess
    import sys
    import time

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "twin", "whatif", str(ROOT / "scenarios" / "quantum_dots.yaml"),
                             "--vary", "devices.synthesiser.instances=2,3", "--seeds", "200"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "TMPDIR": str(scratch)}, cwd=ROOT)
    children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
    deadline = time.monotonic() + 60
    while len(children.read_text().split()) < 2 or not any(scratch.glob("labtwin-workers-*/*")):  # runs going
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    workers = children.read_text().split()
    if stop == "ctrl-c":
        os.killpg(proc.pid, signal.SIGINT)
    else:
        proc.send_signal(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=30)  # an orphaned worker holds the pipes open: this times out
    finally:
        if proc.poll() is None or stop == "kill":
            with contextlib.suppress(ProcessLookupError):  # orphans are still in the group: gone with it
                os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == code, (out, err)
    assert f"{said}: the runs still going were stopped" in err and "Traceback" not in err
    assert not [w for w in workers if Path(f"/proc/{w}").exists() and
                "zombie" not in Path(f"/proc/{w}/status").read_text()]
    assert not list(scratch.iterdir())  # the runs' temporary journals were removed


def test_a_column_of_noughts_is_left_out_and_a_crowded_table_keeps_the_busiest_type_readable():
    """With two varied fields, cost and degraded samples, the busiest type's column was squeezed to nothing at 80
    columns (every row followed by an empty line); a column of noughts (no experiment ever abandoned) took its
    room."""
    code, out = whatif(FLAKY, "--set", "devices.reactor.cost=100", "--set", "orchestrator.retry.max_attempts=50",
                       "--set", "campaign.budget=12", "--vary", "devices.reactor.instances=1,3",
                       "--vary", "devices.spectrometer.instances=1,3", "--seeds", "2")
    assert code == 0, out
    lines = out.splitlines()
    assert max(len(line) for line in lines) <= 80
    head = next(line for line in lines if "lab-h" in line and "IQR" in line).split()
    assert "aband." not in head and head[-2:] == ["degr.", "busiest"]
    assert "no run abandoned an experiment (no aband. column)" in " ".join(out.split())
    assert "exp." not in head and "no exp. column (experiments to target) at this width" in " ".join(out.split())
    rows = [line for line in lines if line.split()[:1] and line.split()[0].rstrip("*") in ("1", "2", "3")]
    assert len(rows) == 5 and all(row.split()[-1] == "reactor" or row.split()[-1].endswith("%") for row in rows)


def test_a_policy_varied_beside_a_field_is_shown_whole_and_folds_only_when_the_table_would_not_fit():
    """At 80 columns the scheduler column was cut to 13 letters: "rl:flaky_sche" over "duler"."""
    budget = ["--set", "campaign.budget=8", "--seeds", "1"]
    policy = "rl:agents/policies/flaky_scheduler.zip"
    code, out = whatif(FLAKY, "--vary", "devices.spectrometer.instances=1,2", "--schedulers", f"fifo,{policy}", *budget)
    assert code == 0, out
    assert max(len(line) for line in out.splitlines()) <= 80
    words = out.split()
    assert words.count("rl:flaky_scheduler") == 2 and "oldest-sample*" in words
    # three varied columns leave no room for the name whole: it folds, and each variant's busiest type keeps its
    # share on screen (rich had cut "reactor 86%" to "reactor 86" at the edge)
    code, out = whatif(FLAKY, "--vary", "devices.spectrometer.instances=1,2", "--vary",
                       "devices.reactor.duration.mean_s=300,400", "--schedulers", f"fifo,{policy}", *budget)
    assert code == 0, out
    assert max(len(line) for line in out.splitlines()) <= 80
    lines = out.splitlines()
    rule = next(i for i, line in enumerate(lines) if line.strip().startswith("─"))
    table = "\n".join(lines[rule + 1:next(i for i, line in enumerate(lines) if line.startswith("*: the scenario"))])
    assert len(re.findall(r"\b\d+%", table)) == 9 and table.count("reactor") == 9, table
