"""The command line's arguments checked before anything runs: an option that disagrees with a --set of its field,
one another option or the lab makes meaningless, a file that cannot be written, a count, port, endpoint or lab
name that is not one. Each is refused naming what to give instead, where it used to be ignored or fail later."""

import json
from pathlib import Path

import pytest

from tests.conftest import twin_cli

ROOT = Path(__file__).resolve().parents[2]
FLAKY = str(ROOT / "scenarios" / "flaky_lab.yaml")


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
    from twin.campaign.journal_read import read_run

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
    # people: the campaign served their steps anyway, and --external said nothing
    (["run", "scenarios/staffed_lab.yaml", "--clock", "scaled", "--bus", "zenoh", "--external", "technician"],
     "--external technician: people (driver: operator), not devices: the campaign serves their steps itself"),
    # a lab that serves checked none of its --external names: a misspelt one served every device itself
    (["lab", "serve", "scenarios/shared_lab.yaml", "--speed", "100", "--external", "synthesiser"],
     "--external synthesiser: not a device of lab shared"),
])
def test_an_option_that_would_be_ignored_is_refused_before_anything_runs(args, says, tmp_path, monkeypatch):
    """Each ran as if the option had not been given (a bench of flaky_lab with --jobshop: six problems with its
    workflow instead)."""
    monkeypatch.chdir(ROOT)
    res = twin_cli(*args)
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and says in said, said


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


def test_a_bench_refuses_a_seed_set_for_all_its_runs():
    for args in (["planners", ROOT / "scenarios" / "quantum_dots.yaml"], ["schedulers", FLAKY, "--shapes"],
                 ["schedulers", FLAKY]):
        res = twin_cli("bench", *args, "--set", "campaign.seed=3", "--seeds", "2")
        assert res.exit_code == 2 and "--set campaign.seed: the runs' seeds are 0 to N−1" in res.output, res.output


def test_a_bench_refuses_a_set_of_the_field_it_compares_or_of_the_budget_its_option_gives_otherwise():
    qd = ROOT / "scenarios" / "quantum_dots.yaml"
    for args, field, option in ((["planners", qd], "campaign.planner", "--planners"),
                                (["schedulers", FLAKY, "--shapes"], "campaign.scheduler", "--schedulers"),
                                (["schedulers", FLAKY], "campaign.scheduler", "--schedulers")):
        res = twin_cli("bench", *args, "--set", f"{field}=random" if "planner" in field else f"{field}=mwkr",
                       "--seeds", "2")
        said = " ".join(res.output.split())
        assert res.exit_code == 2 and f"--set {field}: this bench runs each of {option} in its place" in said, said
        budget = twin_cli("bench", *args, "--set", "campaign.budget=5", "--budget", "6", "--seeds", "2")
        assert budget.exit_code == 2 and "--budget 6 and --set campaign.budget=5 disagree" in budget.output


def test_twin_lab_serve_takes_security_and_insecure_as_twin_run_does(tmp_path, monkeypatch):
    """A secure shared lab: `twin lab serve` had no --security, and its refusal to listen beyond loopback told it to
    "pass --security DIR … or pass --insecure", neither of which it took."""
    lab = str(ROOT / "scenarios" / "shared_lab.yaml")
    monkeypatch.chdir(tmp_path)
    res = twin_cli("lab", "serve", lab, "--connect", "tls/127.0.0.1:1", "--security", tmp_path / "nosuch")
    assert res.exit_code == 2 and f"{tmp_path / 'nosuch'} is not a lab security directory" in res.stderr, res.output
    assert not any((tmp_path / "runs").iterdir())  # the journals' directory it claimed, given back
    exposed = twin_cli("lab", "serve", lab, "--listen", "tcp/0.0.0.0:1")
    assert exposed.exit_code == 2 and "pass --security DIR" in " ".join(exposed.stderr.split()), exposed.output


def test_a_process_joining_a_lab_connects_where_its_lab_file_says_unless_told_otherwise(tmp_path):
    """`twin device serve lab.yaml --id hotplate` of a lab file whose bus.connect names its router stopped with
    "Missing option '--connect'", though the lab itself connects there from the same file."""
    import yaml

    from tests.conftest import qd_lab
    from twin.core.errors import BusError
    from twin.runtime.serve import _joined

    (tmp_path / "routed.yaml").write_text(yaml.safe_dump(qd_lab(**{"bus.connect": ["tcp/127.0.0.1:7950"]})))
    (tmp_path / "alone.yaml").write_text(yaml.safe_dump(qd_lab()))
    assert _joined(tmp_path / "routed.yaml", None, None, None).bus.connect == ["tcp/127.0.0.1:7950"]
    assert _joined(tmp_path / "routed.yaml", ["tcp/127.0.0.1:7951"], None, None).bus.connect == ["tcp/127.0.0.1:7951"]
    with pytest.raises(BusError, match="give --connect ENDPOINT: where the lab listens"):
        _joined(tmp_path / "alone.yaml", None, None, None)
    for args in (["device", "serve", tmp_path / "alone.yaml", "--id", "spectrometer-1"],
                 ["device", "health", tmp_path / "alone.yaml"],
                 ["scheduler", "serve", tmp_path / "alone.yaml", "--scheduler", "fifo"]):
        res = twin_cli(*args)
        said = " ".join(res.output.split())
        assert res.exit_code == 2 and "give --connect ENDPOINT" in said and "(bus.connect)" in said, said


@pytest.mark.parametrize("args,says", [
    (["validate", "scenarios/quantum_dots.yaml", "--set", "campaign.planner_options=" + "[" * 3000 + "]" * 3000],
     "nested more than 32 levels deep; a value given on the command line does not need that"),
    (["validate", "scenarios/quantum_dots.yaml", "--set", "campaign.planner_options={n_init: 3, n_init: 4}"],
     "line 1, column 13: key 'n_init' is given twice (first at column 2)"),
    (["validate", "scenarios/quantum_dots.yaml", "--set", "campaign.budget=[1, 2"], "not valid YAML"),
    (["whatif", "scenarios/quantum_dots.yaml", "--vary", "campaign.budget=" + "[" * 3000]
     + ["--seeds", "1"], "campaign.budget: Input should be a valid integer"),
])
def test_a_value_on_the_command_line_is_read_within_a_files_bounds(args, says):
    """3,000 '[' in a --set or --vary value was a RecursionError's traceback; a key given twice on one line, the last."""
    res = twin_cli(*args)
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and says in said and "Traceback" not in said, said
