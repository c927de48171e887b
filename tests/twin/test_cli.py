"""`twin run`, `twin report` and Ctrl-C, as a user meets them."""

import json
import re
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests.conftest import twin_cli

ROOT = Path(__file__).resolve().parents[2]
TWIN = [sys.executable, "-m", "twin"]


@pytest.mark.process  # the README's command as a user runs it: a process of its own, on Zenoh
def test_run_prints_the_summary_and_report_prints_it_again(tmp_path):
    db = tmp_path / "qd.db"
    res = subprocess.run([*TWIN, "run", "scenarios/quantum_dots.yaml", "--budget", "6", "--journal", str(db)],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr
    for words in ("experiments", "6 done", "spectrometer", "% busy", "target R", str(db)):
        assert words in res.stdout
    assert "6/6" in res.stderr  # the progress bar reached the budget
    again = subprocess.run([*TWIN, "report", str(db)], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert again.returncode == 0
    assert again.stdout.split("journal")[0] == res.stdout.split("journal")[0]
    moved = db.rename(tmp_path / "kept.db")  # the report names the file it read, not where the run wrote it
    again = subprocess.run([*TWIN, "report", str(moved)], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert f"journal: {moved}  (twin report {moved})" in again.stdout and str(db) not in again.stdout


def test_a_lab_of_minutes_shows_its_time_in_seconds_and_one_of_hours_in_hours(tmp_path):
    import re

    res = twin_cli("run", "scenarios/jobshop.yaml", "--bus", "memory", "--journal", tmp_path / "shop.db")
    assert res.exit_code == 0, res.stderr
    shown = re.search(r"lab time\W+(\d+) s \((0\.\d{3}) h;", res.stdout)  # a job shop of about a minute
    assert shown and abs(int(shown[1]) / 3600 - float(shown[2])) < 0.001, res.stdout
    assert re.search(rf"6/6\s+lab {shown[1]} s", res.stderr)  # the progress bar, in the same seconds
    res = twin_cli("run", "scenarios/quantum_dots.yaml", "--budget", "6", "--bus", "memory", "--journal",
                   tmp_path / "qd.db")
    assert re.search(r"lab time\W+\d+\.\d\d h \(\d", res.stdout) and re.search(r"lab \d+\.\d h", res.stderr)


@pytest.mark.process
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_stops_cleanly_and_flushes_the_journal(tmp_path, sig):
    db = tmp_path / "flaky.db"
    proc = subprocess.Popen(
        [*TWIN, "run", "scenarios/flaky_lab.yaml", "--clock", "scaled", "--speed", "3600", "--quiet",
         "--journal", str(db), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not _has_experiments(db):
        time.sleep(0.1)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 128 + sig, err  # as a command a signal ended: a shell loop over runs stops too
    summary = json.loads(out)
    assert summary["stopped"] == f"interrupted ({sig.name})"
    assert summary["pending"] > 0 and summary["done"] + summary["abandoned"] + summary["pending"] == summary["proposed"]
    with sqlite3.connect(db) as c:
        statuses = [r[0] for r in c.execute("SELECT status FROM experiments")]
        cancelled = c.execute("SELECT COUNT(*) FROM events WHERE kind='attempt.cancelled'").fetchone()[0]
    assert len(statuses) == summary["proposed"]
    assert cancelled >= 1, "work in the lab at shutdown is cancelled, not forgotten"
    report = subprocess.run([*TWIN, "report", str(db)], capture_output=True, text=True, cwd=ROOT)
    assert report.returncode == 0 and "interrupted" in report.stdout
    assert f"continue it with twin resume {db}" in report.stdout.replace("\n", ""), report.stdout


def _has_experiments(db: Path) -> bool:
    if not db.exists():
        return False
    try:
        with sqlite3.connect(db) as c:
            return c.execute("SELECT COUNT(*) FROM events WHERE kind='experiment.done'").fetchone()[0] > 0
    except sqlite3.Error:
        return False


def test_train_prints_its_evaluation_curve_and_saves_a_policy_with_its_sidecar(tmp_path, monkeypatch):
    out = tmp_path / "heater.zip"
    rrd = tmp_path / "curve.rrd"
    monkeypatch.chdir(ROOT)
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # where SB3's default logger makes SB3-<time>/
    res = twin_cli("train", "scenarios/catalyst.yaml", "--agent", "controller", "--steps", "2880",
                   "--eval-every", "1440", "--out", str(out), "--save", str(rrd), columns=80)
    assert res.exit_code == 0, res.output
    curve = [ln for ln in res.stderr.splitlines() if " steps " in ln]
    assert [ln.split()[0] for ln in curve] == ["0", "1,440", "2,880"], res.stderr
    assert "training goes in rounds" not in res.stderr  # as many steps as asked: nothing to explain
    assert "pid" in curve[0] and "ppo-pure" in curve[1]
    meta = json.loads(out.with_suffix(".json").read_text())
    assert out.exists() and meta["kind"] == "controller" and meta["scenario"] == "catalyst"
    assert meta["versions"]["torch"].startswith("2.13.0")
    from tests.rrd import read_rrd, rerun_verify

    assert rerun_verify(rrd).returncode == 0
    curve = read_rrd(rrd)
    ppo = sorted(r["training_steps"] for r in curve["training/ppo-pure/return"])
    assert ppo == [1440, 2880] and [r["training_steps"] for r in curve["training/pid/return"]] == [0]
    assert not list(scratch.glob("SB3-*"))  # no empty log directory per evaluation, as SB3 makes by default


def test_train_an_unknown_agent_lists_what_is_installed(tmp_path):
    res = twin_cli("train", str(ROOT / "scenarios" / "catalyst.yaml"), "--agent", "nope", "--out",
                   str(tmp_path / "x.zip"), columns=80)
    assert res.exit_code == 2 and "unknown trainer 'nope'" in res.stderr and "planner" in res.stderr
    assert type(res.exception) is SystemExit  # an error said, not an exception raised


@pytest.mark.process
@pytest.mark.parametrize("sig, code, said", [(signal.SIGINT, 130, "interrupted"),
                                             (signal.SIGTERM, 143, "terminated (SIGTERM)")])
def test_ctrl_c_or_sigterm_stops_training_and_says_what_was_kept(tmp_path, sig, code, said):
    out = tmp_path / "s.zip"
    proc = subprocess.Popen([*TWIN, "train", "scenarios/jobshop.yaml", "--steps", "1000000", "--eval-every", "512",
                             "--out", str(out), "--set", "training.jobshop_sizes=[[6,6]]"],  # small shops: CP-SAT is quick
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    lines = []
    for line in proc.stderr:  # wait for the first evaluation (the rules'; CP-SAT has planned the Judge's shops)
        lines.append(line)
        if " steps " in line and "the reference:" not in line:  # not the line that says CP-SAT starts planning
            break
    proc.send_signal(sig)
    rest = proc.communicate(timeout=60)[1]
    assert proc.returncode == code, "".join(lines) + rest
    # before its first evaluation nothing is kept yet, and it says so (CP-SAT has run in this process by then,
    # so its own SIGINT handler, were it installed, would have killed the command without a word; SIGTERM
    # killed it so, its workers dying of broken pipes)
    assert f"{said}; no policy saved yet" in rest and "Traceback" not in rest
    assert not out.exists()


@pytest.mark.parametrize("command", [
    ["bench", "schedulers", "--seeds", "2"], ["bench", "schedulers", "--shapes", "--seeds", "2"],
    ["bench", "planners", "--seeds", "2"], ["whatif", "--vary", "campaign.budget=3,4", "--seeds", "2"],
    ["train", "--steps", "100", "--out", "p.zip"],
])
def test_a_lab_its_drivers_cannot_run_is_one_error_before_any_worker_starts(tmp_path, command):
    """A bench's campaigns load their drivers in worker processes: the lab is checked first, as `twin run` does."""
    text = (ROOT / "scenarios" / "flaky_lab.yaml").read_text().replace("steps: [measure]", "steps: [measure, wash]")
    lab = tmp_path / "lab.yaml"
    lab.write_text(text)
    res = twin_cli(*command[:2 if command[0] == "bench" else 1], str(lab),
                   *command[2 if command[0] == "bench" else 1:])
    out = " ".join(res.output.split())
    assert res.exit_code == 2 and "Traceback" not in out, out
    assert f"{lab}: 1 problem(s)" in out and "devices.spectrometer.driver: 'spectrometer' runs" in out
    assert "asks it for ['wash']" in out


def test_a_bench_of_schedulers_does_not_load_the_scenarios_own(tmp_path):
    """The bench runs the schedulers it is given: the scenario's policy file, missing here, is neither needed nor
    loaded (a policy for another lab only warned of a scheduler that was never run), while `twin run` needs it."""
    lab = tmp_path / "lab.yaml"
    lab.write_text((ROOT / "scenarios" / "flaky_lab.yaml").read_text().replace(
        "scheduler: oldest-sample", f"scheduler: rl:{tmp_path / 'nowhere.zip'}"))
    res = twin_cli("bench", "schedulers", str(lab), "--schedulers", "fifo,mwkr", "--seeds", "1",
                   "--budget", "4", "--workers", "1")
    assert res.exit_code == 0, res.output
    assert "fifo" in res.output and "mwkr" in res.output and "nowhere.zip" not in res.output
    res = twin_cli("validate", str(lab))
    assert res.exit_code == 2 and "campaign.scheduler" in res.output and "nowhere.zip" in res.output


def test_experiments_abandoned_by_deadlines_say_which_fields_set_them(tmp_path, caplog):
    """flaky_lab's reactor with the reaction time left out of its expected duration: its deadlines are too short,
    which the run warns of before it starts (the reactor declares that its steps last time_s) and explains after."""
    text = (ROOT / "scenarios" / "flaky_lab.yaml").read_text()
    short = tmp_path / "short.yaml"
    short.write_text(text.replace("duration: {mean_s: 300, cv: 0.2, plus_param: time_s}", "duration: {mean_s: 300, cv: 0.2}"))
    outs, warned = {}, {}
    for name, path in (("short", short), ("as written", ROOT / "scenarios" / "flaky_lab.yaml")):
        caplog.clear()
        res = twin_cli("run", path, "--bus", "memory", "--budget", "8", "--journal", tmp_path / f"{name}.db")
        assert res.exit_code == 0, res.stderr
        # the run's warnings are logged: on stderr in a process of its own, in caplog here
        outs[name], warned[name] = " ".join(res.stdout.split()), " ".join((res.stderr + caplog.text).split())
    # 300 + setup 120 + clean 600 = 1020 lab-s expected; × 1.5 + 600 = 2130; time_s goes up to 5400
    assert ("devices.reactor.duration: a reactor step lasts at least time_s (up to 5400 lab-s here), which the "
            "duration model leaves out, so its deadline is 2130 lab-s") in warned["short"]
    assert "give devices.reactor.duration.plus_param: time_s" in warned["short"]
    assert "devices.reactor.duration" not in warned["as written"]
    assert "react: timed_out — e.g. step 'react' failed 4 time(s); last: timed_out on reactor" in outs["short"]
    assert "the last attempt at react ran past its deadline" in outs["short"]
    assert "orchestrator.timeout_factor" in outs["short"] and "plus_param" in outs["short"]
    assert "why?" not in outs["as written"]


def test_a_workflow_that_measures_before_it_reacts_is_refused_per_experiment_without_blaming_the_instruments(tmp_path):
    """The spectrometer refuses a sample it cannot measure as infeasible (the workflow's doing): every experiment
    is abandoned at once with its reason, and no spectrometer is quarantined."""
    text = (ROOT / "scenarios" / "flaky_lab.yaml").read_text()
    order = ("  - {step: react, device: reactor}\n  - {step: measure, device: spectrometer}\n")
    assert order in text
    swapped = tmp_path / "swapped.yaml"
    swapped.write_text(text.replace(order, "  - {step: measure, device: spectrometer}\n  - {step: react, device: reactor}\n"))
    res = twin_cli("run", swapped, "--bus", "memory", "--budget", "6", "--json", "--journal", tmp_path / "j.db")
    assert res.exit_code == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["abandoned"] == 6 and summary["abandoned_reasons"] == {"infeasible": 6}
    assert summary["quarantines"] == 0 and summary["infeasible"] == 6
    assert "cannot measure a sample of kind 'feed'" in summary["abandoned_examples"]["infeasible"]
    assert "check the workflow's order" in summary["abandoned_examples"]["infeasible"]


def test_run_set_changes_any_field_and_a_bad_one_is_named(tmp_path):
    res = twin_cli("run", "scenarios/flaky_lab.yaml", "--set", "devices.spectrometer.instances=3",
                   "--set", "campaign.budget=5", "--journal", str(tmp_path / "j.db"), "--quiet",
                   "--json", columns=80)
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["done"] + summary["abandoned"] == 5
    assert sorted(d for d in summary["utilisation"] if d.startswith("spectrometer")) == [
        "spectrometer-1", "spectrometer-2", "spectrometer-3"]
    for item, says in (("campaign.budget=-4", "campaign.budget"), ("budget", "expected FIELD=VALUE"),
                       ("campaign.budget=[", "not YAML")):
        bad = twin_cli("run", "scenarios/flaky_lab.yaml", "--set", item, "-q")
        assert bad.exit_code == 2 and says in bad.output, bad.output


def test_an_option_and_a_set_of_its_field_that_disagree_are_refused_and_agreeing_ones_run(tmp_path):
    """--seed 3 --set campaign.seed=5 ran seed 3 without a word (the option won); each such pair is refused now."""
    for args, says in ((["--seed", "3", "--set", "campaign.seed=5"], "--seed 3 and --set campaign.seed=5 disagree"),
                       (["--scheduler", "fifo", "--set", "campaign.scheduler=mwkr"],
                        "--scheduler fifo and --set campaign.scheduler=mwkr disagree"),
                       (["--clock", "scaled", "--speed", "60", "--set", "clock.speed=3600"],
                        "--speed 60 and --set clock.speed=3600 disagree"),
                       (["--listen", "tcp/127.0.0.1:7000", "--set", "bus.listen=[tcp/127.0.0.1:7001]"],
                        "--listen tcp/127.0.0.1:7000 and --set bus.listen=[tcp/127.0.0.1:7001] disagree")):
        bad = twin_cli("run", "scenarios/flaky_lab.yaml", *args, "--journal", str(tmp_path / "bad.db"))
        assert bad.exit_code == 2 and says in " ".join(bad.output.split()), bad.output
        assert not (tmp_path / "bad.db").exists()
    res = twin_cli("run", "scenarios/flaky_lab.yaml", "--seed", "3", "--set", "campaign.seed=3", "--budget", "2",
                   "--journal", str(tmp_path / "j.db"), "--json")
    assert res.exit_code == 0 and json.loads(res.stdout)["seed"] == 3, res.output


def test_a_speed_alone_asks_for_a_scaled_clock_and_one_for_another_clock_is_refused(tmp_path):
    """--speed 100 on quantum_dots (a virtual clock) ran in virtual time without a word."""
    from twin.campaign.journal import read_run

    res = twin_cli("run", "scenarios/quantum_dots.yaml", "--speed", "200000", "--budget", "1", "--bus", "memory",
                   "--journal", str(tmp_path / "j.db"), "--json")
    assert res.exit_code == 0, res.output
    assert read_run(tmp_path / "j.db")["scenario"]["clock"] == {"mode": "scaled", "speed": 200000.0}
    for args, clock in ((["--clock", "virtual"], "virtual"), (["--set", "clock.mode=wall"], "wall")):
        bad = twin_cli("run", "scenarios/quantum_dots.yaml", "--speed", "5", *args, "--journal", str(tmp_path / "b.db"))
        said = " ".join(bad.output.split())
        assert bad.exit_code == 2 and f"--speed 5 paces a scaled clock, and this lab's clock is {clock}" in said, said
        assert not (tmp_path / "b.db").exists()
    served = twin_cli("lab", "serve", "scenarios/shared_lab.yaml", "--clock", "wall", "--speed", "3")
    assert served.exit_code == 2 and "--speed 3 paces a scaled clock, and this lab's clock is wall" in served.output


TINY = """
name: tiny
lab: tiny
devices:
  a: {driver: machine, instances: 1, steps: [one], duration: {mean_s: 60, cv: 0.2}}
  b: {driver: machine, instances: 2, steps: [two], duration: {mean_s: 90, cv: 0.2}}
chemistry: {parameters: {x: {low: 0, high: 1}}}
workflow: [{step: one, device: a}, {step: two, device: b}]
campaign: {budget: 3, planner: random, scheduler: fifo, seed: 0}
"""


def test_training_past_its_steps_says_why(tmp_path):
    """--steps 5 trained a whole episode of 6 decisions and the bar jumped from 5/5 to 6/6 without a word."""
    (tmp_path / "tiny.yaml").write_text(TINY)
    res = twin_cli("train", tmp_path / "tiny.yaml", "--steps", "5", "--envs", "1", "--eval-every", "5",
                   "--out", tmp_path / "p.zip")
    assert res.exit_code == 0 and (tmp_path / "p.zip").exists(), res.output
    said = " ".join(res.stderr.split())
    assert re.search(r"trained (\d+) steps for --steps 5: training goes in rounds", said), said


def test_a_lab_on_the_memory_bus_refuses_what_only_a_bus_with_sockets_could_do(tmp_path):
    """staffed_lab (bus: memory) with --listen ran, and twin ctl found nothing there; --external waited for a
    device that could never join, then abandoned its work."""
    res = twin_cli("run", "scenarios/staffed_lab.yaml", "--clock", "scaled", "--listen", "tcp/127.0.0.1:7447",
                   "--journal", tmp_path / "a.db")
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "--listen tcp/127.0.0.1:7447: the bus is memory (no sockets)" in said, said
    res = twin_cli("run", "scenarios/quantum_dots.yaml", "--bus", "memory", "--clock", "scaled", "--external",
                   "spectrometer", "--journal", tmp_path / "b.db")
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "devices ['spectrometer'] run in other processes, and the bus is memory" in said
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args,says", [
    (["run", "scenarios/quantum_dots.yaml", "--serve-port", "9000"], "--serve-port 9000: the port of --serve's server"),
    (["resume", "nowhere.db", "--web-port", "9001"], "--web-port 9001: the port of --serve's server"),
    (["bench", "schedulers", "scenarios/flaky_lab.yaml", "--random-labs", "2"], "--random-labs 2: an option of "
                                                                               "--shapes"),
    (["bench", "schedulers", "scenarios/flaky_lab.yaml", "--by", "objective"], "--by objective: an option of --shapes"),
    (["bench", "schedulers", "scenarios/flaky_lab.yaml", "--jobshop", "jobshop/ft06.txt"],
     "scenarios/flaky_lab.yaml has no `jobshop:` section"),
    (["bench", "planners", "scenarios/quantum_dots.yaml", "--budget", "0"], "Invalid value for '--budget'"),
    # read as no --speed: the device followed the lab's clock
    (["device", "serve", "scenarios/quantum_dots.yaml", "--id", "spectrometer", "--connect", "tcp/127.0.0.1:9",
      "--speed", "0"], "Invalid value for '--speed': 0: give lab seconds per wall second"),
    (["bench", "schedulers", "scenarios/flaky_lab.yaml", "--budget", "0"], "Invalid value for '--budget'"),
    # a type's name, not its instances': both synthesisers ran in the lab's process as if it had not been given
    (["run", "scenarios/quantum_dots.yaml", "--clock", "scaled", "--external", "synthesiser"],
     "--external synthesiser: not a device of lab qd (its devices: synthesiser-1, synthesiser-2, spectrometer"),
])
def test_an_option_that_would_be_ignored_is_refused_before_anything_runs(args, says, tmp_path, monkeypatch):
    """Each ran as if the option had not been given (a bench of flaky_lab with --jobshop: six problems with its
    workflow instead)."""
    monkeypatch.chdir(ROOT)
    res = twin_cli(*args)
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and says in said, said


def test_the_command_list_shows_each_summary_as_one_paragraph():
    """typer's rich mode kept a docstring's line breaks in `twin --help`'s list: "as tables (one file" over
    "each) and its provenance"."""
    res = twin_cli("--help", columns=100)
    assert res.exit_code == 0
    text = " ".join(res.stdout.split())
    assert "acts as tables (one file each) and its provenance" in text
    assert "or with --connect the devices of a running lab and their health" in text


def test_every_repeatable_option_says_what_it_takes_not_its_python_type():
    """typer shows a repeatable option's type as `<list[str]>`, which reads as if a list were typed; each says
    what one use takes instead (`--set FIELD=VALUE`, `--connect ENDPOINT`)."""
    from typer.main import get_command
    from twin.cli import app

    def commands(group, path: list[str]):  # typer's own click: a group is what has commands
        for name, command in group.commands.items():
            if hasattr(command, "commands"):
                yield from commands(command, [*path, name])
            else:
                yield " ".join([*path, name]), command

    repeatable = {(path, p.name): p.metavar for path, command in commands(get_command(app), [])
                  for p in command.params if getattr(p, "multiple", False)}
    assert len(repeatable) > 20 and [k for k, metavar in repeatable.items() if not metavar] == []
    res = twin_cli("run", "--help", columns=100)
    assert "list[" not in res.output and re.search(r"--set +FIELD=VALUE", res.output), res.output


@pytest.mark.parametrize("args", [
    ["run", "scenarios/quantum_dots.yaml", "--budget", "3", "--save", "{bad}/r.rrd"],
    ["whatif", "scenarios/quantum_dots.yaml", "--vary", "devices.synthesiser.instances=3", "--seeds", "1",
     "--csv", "{bad}/w.csv"],
    ["bench", "planners", "scenarios/quantum_dots.yaml", "--seeds", "1", "--csv", "{bad}/b.csv"],
    ["bench", "schedulers", "scenarios/jobshop.yaml", "--csv", "{bad}/b.csv"],
    ["train", "scenarios/quantum_dots.yaml", "--agent", "planner", "--steps", "100", "--out", "{bad}/p.zip"],
    ["devices", "--csv", "{bad}/d.csv"],
    ["route", "CCO", "--save", "{bad}/r.svg"],
    ["resume", "missing.db", "--save", "{bad}/r.rrd"],
])
def test_a_file_to_write_that_cannot_be_is_refused_before_anything_runs(args, tmp_path, monkeypatch):
    """A whatif or a bench ran to its end and then died with a traceback on its --csv (and training would have
    lost its policy): a path whose directory is a file is refused at once, naming the option."""
    (tmp_path / "a_file").write_text("not a directory")
    monkeypatch.chdir(tmp_path)
    bad = tmp_path / "a_file"
    args = [a.format(bad=bad) if "{bad}" in a else str(ROOT / a) if a.startswith("scenarios/") else a for a in args]
    res = twin_cli(*args)
    option = next(a for a in args if a.startswith("--") and "{" not in a and str(bad) in args[args.index(a) + 1])
    assert res.exit_code == 2, res.output
    assert f"error: {option} {bad}/" in res.output and f"its directory {bad} cannot be made" in res.output
    assert "nothing has run" in res.output and not (tmp_path / "runs").exists()


@pytest.mark.parametrize("args,option", [
    (["train", "scenarios/quantum_dots.yaml", "--agent", "planner", "--out", "p.zip", "--steps", "0"], "--steps"),
    (["train", "scenarios/quantum_dots.yaml", "--agent", "planner", "--out", "p.zip", "--envs", "0"], "--envs"),
    (["train", "scenarios/quantum_dots.yaml", "--agent", "planner", "--out", "p.zip", "--eval-every", "0"],
     "--eval-every"),
    (["bench", "planners", "scenarios/quantum_dots.yaml", "--seeds", "0"], "--seeds"),
    (["bench", "schedulers", "scenarios/flaky_lab.yaml", "--workers", "0"], "--workers"),
    (["run", "scenarios/quantum_dots.yaml", "--runtime", "fastest"], "--runtime"),  # refused once the run began
    (["resume", "p.db", "--runtime", "fastest"], "--runtime"),
])
def test_counts_below_one_are_refused_by_name(args, option, tmp_path, monkeypatch):
    """--steps 0 saved an untrained policy, --envs 0 was an IndexError, --eval-every 0 evaluated at step 0 for ever."""
    monkeypatch.chdir(tmp_path)
    args = [str(ROOT / a) if a.startswith("scenarios/") else a for a in args]
    res = twin_cli(*args)
    assert res.exit_code == 2 and f"Invalid value for '{option}'" in res.output, res.output
    assert not (tmp_path / "p.zip").exists()


def test_a_directory_as_the_trained_policys_file_is_refused(tmp_path):
    """--out runs (a directory) saved runs.zip and runs.json beside it, after the whole training."""
    res = twin_cli("train", ROOT / "scenarios" / "quantum_dots.yaml", "--out", tmp_path, "--steps", "10")
    assert res.exit_code == 2 and f"--out {tmp_path} is a directory: give the policy's file, e.g. " \
        f"{tmp_path / 'policy.zip'}" in " ".join(res.output.split()), res.output
    assert not tmp_path.with_suffix(".zip").exists() and not tmp_path.with_suffix(".json").exists()


def test_a_port_past_65535_is_refused_by_name(tmp_path, monkeypatch):
    """It was an OverflowError from bind() after the campaign had started."""
    monkeypatch.chdir(tmp_path)
    res = twin_cli("run", str(ROOT / "scenarios" / "quantum_dots.yaml"), "--serve", "--serve-port",
                   "99999")
    assert res.exit_code == 2 and "Invalid value for '--serve-port'" in res.output and not (tmp_path / "runs").exists()


@pytest.mark.parametrize("command", [
    ["ctl", "status", "--lab", "qd", "--connect", "{bad}"],
    ["watch", "--lab", "qd", "--connect", "{bad}", "--save", "{tmp}/w.rrd"],
    ["submit", "{tmp}/c.yaml", "--lab", "qd", "--connect", "{bad}"],
    ["devices", "--connect", "{bad}", "--lab", "qd"],
    ["router", "--listen", "{bad}"],
    ["device", "serve", "scenarios/quantum_dots.yaml", "--id", "spectrometer", "--connect", "{bad}"],
    ["scheduler", "serve", "scenarios/quantum_dots.yaml", "--scheduler", "fifo", "--connect", "{bad}"],
])
@pytest.mark.parametrize("bad", ["tcp/", "127.0.0.1:7447", "tcp/127.0.0.1:99999"])
def test_an_endpoint_that_is_not_one_is_named_with_how_to_write_it_before_anything_opens(tmp_path, command, bad):
    """`--connect tcp/` printed Zenoh's own parse error, cargo paths and all."""
    (tmp_path / "c.yaml").write_text("name: c\n")
    res = twin_cli(*[a.format(bad=bad, tmp=tmp_path) for a in command], columns=300)
    said = " ".join(res.output.split())
    assert res.exit_code == 2, said
    assert f"'{bad}' is not a Zenoh endpoint: write PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447" in said, said
    assert "cargo" not in said and "Json5Err" not in said


@pytest.mark.parametrize("command", [
    ["ctl", "status", "--lab", "{lab}", "--connect", "tcp/127.0.0.1:1"],
    ["ctl", "pause", "--lab", "{lab}", "--connect", "tcp/127.0.0.1:1"],
    ["watch", "--lab", "{lab}", "--connect", "tcp/127.0.0.1:1", "--save", "{tmp}/w.rrd"],
    ["submit", "{tmp}/c.yaml", "--lab", "{lab}", "--connect", "tcp/127.0.0.1:1"],
    ["devices", "--connect", "tcp/127.0.0.1:1", "--lab", "{lab}"],
])
@pytest.mark.parametrize("lab", ["qd/**", "*", "a b", "qd/campaign/x"])
def test_a_lab_name_that_is_not_one_is_refused_before_anything_opens(tmp_path, command, lab):
    """A lab's name is a chunk of its bus keys: `twin watch --lab '*'` subscribed to every lab's keys at once, and
    `--lab 'qd/**'` waited forever for a lab no scenario can name."""
    (tmp_path / "c.yaml").write_text("name: c\n")
    res = twin_cli(*[a.format(lab=lab, tmp=tmp_path) for a in command], columns=300)
    said = " ".join(res.output.split())
    assert res.exit_code == 2, said
    assert f"'{lab}' is not a lab's name: a scenario's `lab` is letters, digits, '_' or '-', at most 64" in said, said
    assert not (tmp_path / "w.rrd").exists()


@pytest.mark.parametrize("args,says", [
    # a lab's scenario sent as a campaign: five "unknown field" lines, none saying what a campaign file is
    (["submit", "scenarios/quantum_dots.yaml", "--lab", "qd", "--connect", "tcp/127.0.0.1:1"],
     "this is a lab's scenario (devices, lab, orchestrator), not a campaign for a lab: a campaign file keeps only"),
    (["security", "init", "/proc/labsec", "--lab", "qd"],  # a traceback from mkdir
     "/proc/labsec: cannot write the security directory there (No such file or directory)"),
    (["bench", "planners", "scenarios/quantum_dots.yaml", "--planners", ","],  # an empty table
     "--planners ',': name at least one planner"),
    (["bench", "schedulers", "scenarios/flaky_lab.yaml", "--schedulers", ""], "name at least one scheduler"),
])
def test_what_a_command_cannot_do_is_said_before_it_starts(args, says):
    res = twin_cli(*[str(ROOT / a) if a.startswith("scenarios/") else a for a in args], columns=300)
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and says in said and "Traceback" not in said, said


def test_twin_version_names_labtwin_and_the_libraries_a_run_records():
    from twin.runtime.run_record import versions

    res = twin_cli("--version")
    known = versions()
    assert res.exit_code == 0 and res.output.startswith(f"labtwin {known['labtwin']} (python {known['python']}")
    assert f"eclipse-zenoh {known['eclipse-zenoh']}" in res.output and f"torch {known['torch']}" in res.output
