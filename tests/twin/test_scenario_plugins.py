"""The plugins a scenario names — drivers, planners, schedulers, policy files — checked before anything runs: each
one that cannot be loaded, or is given what it does not take, is named with its file, field and the fix."""

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab, twin_cli
from twin.core.errors import DriverError, ScenarioError, TwinError
from twin.runtime.checks import check, checked
from twin.runtime.assembly import load_driver
from twin.scenario import load, parse

ROOT = Path(__file__).resolve().parents[2]


def write(tmp_path, raw, name="bad.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(raw) if not isinstance(raw, str) else raw)
    return path


def test_unknown_driver_lists_the_installed_ones(tmp_path):
    s = load(write(tmp_path, qd_lab(**{"devices.synthesiser.driver": "robot9000"})))
    with pytest.raises(DriverError) as info:
        load_driver(s, "synthesiser", "synthesiser")
    for name in ("robot9000", "synthesiser", "reactor", "spectrometer"):
        assert name in str(info.value)


def test_a_misspelt_planner_option_is_named_and_another_planners_option_is_not_refused(tmp_path):
    """planner_options went to the planner's constructor, whose **_ swallowed a typo (n_int for n_init) silently."""
    from twin.runtime.lab import make_planner, prepare

    typo = load(write(tmp_path, qd_lab(**{"campaign.planner": "gp-bo", "campaign.planner_options": {"n_int": 4}})))
    with pytest.raises(ScenarioError, match=r"campaign\.planner_options\.n_int: no installed planner takes an option "
                                          r"'n_int' \('gp-bo' takes n_init, "):
        check(typo)
    kept = load(write(tmp_path, qd_lab(**{"campaign.planner": "gp-bo", "campaign.planner_options": {"n_init": 4}}),
                      "ok.yaml"))
    assert make_planner(kept).n_init == 4
    swapped = prepare(kept, overrides={"campaign.planner": "random"})  # --planner random, or a bench's row
    assert make_planner(swapped).propose(1, [], [])  # gp-bo's option is not random's: not used, not refused
    from twin import run  # from Python too, where no command checked it first
    from twin.core.errors import PluginError

    with pytest.raises(PluginError, match=r"campaign\.planner_options\.n_int: no installed planner takes"):
        run(typo, journal=tmp_path / "j.db", bus="memory")


class Weighted:
    """A third party's scheduler with an option of its own."""

    def __init__(self, weight: float = 1.0, **_):
        self.weight = weight

    def decide(self, view):
        return []


def test_scheduler_options_reach_the_schedulers_that_name_them_and_a_misspelt_one_is_named(tmp_path):
    """cp-sat's time a decision (1 s) could not be set from a scenario: a wide lab's campaign took up to 30 min."""
    from twin.runtime.lab import make_scheduler, prepare

    opts = {"campaign.scheduler": "cp-sat", "campaign.scheduler_options": {"time_limit_s": 0.2}}
    s = load(write(tmp_path, qd_lab(**opts)))
    assert make_scheduler(s).time_limit_s == 0.2
    assert make_scheduler(s, "fifo").decide  # a rule beside it (a bench's row, the fallback) is not given it
    weighted = "tests.twin.test_scenario_plugins:Weighted"
    plugin = prepare(s, overrides={"campaign.scheduler_options": {"weight": 3.5}, "campaign.scheduler": weighted})
    assert make_scheduler(plugin).weight == 3.5
    check(plugin)  # its option is no typo, though the fallback rule (fifo) takes none
    benched = prepare(s, overrides={"campaign.scheduler_options": {"weight": 3.5}})  # cp-sat's lab, benched beside it
    check(benched, schedulers=[weighted])
    res = twin_cli("bench", "schedulers", write(tmp_path, qd_lab(**{"campaign.budget": 3}), "b.yaml"), "--seeds", "1",
                   "--schedulers", f"fifo,{weighted}", "--set", "campaign.scheduler_options.weight=2")
    assert res.exit_code == 0, res.stderr
    typo = load(write(tmp_path, qd_lab(**{**opts, "campaign.scheduler_options": {"time_limt_s": 0.2}}), "t.yaml"))
    with pytest.raises(ScenarioError, match=r"campaign\.scheduler_options\.time_limt_s: no installed scheduler takes "
                                          r"an option 'time_limt_s' \('cp-sat' takes time_limit_s; 'fifo' takes "
                                          r"none\); check its "):
        check(typo)
    res = twin_cli("bench", "schedulers", write(tmp_path, qd_lab(**{"campaign.budget": 3}), "b.yaml"), "--seeds", "1",
                   "--schedulers", f"fifo,{weighted}", "--set", "campaign.scheduler_options.wieght=2")
    assert res.exit_code == 2 and "'wieght'" in res.stderr and f"'{weighted}' takes weight" in res.stderr
    res = twin_cli("scheduler", "serve", tmp_path / "t.yaml", "--scheduler", "cp-sat", "--connect", "tcp/127.0.0.1:9")
    assert res.exit_code == 2 and "'time_limt_s'" in res.stderr  # an agent served elsewhere: said before it joins
    for bad in ("fast", 0, True):
        with pytest.raises(TwinError, match="time_limit_s: .* is not a number of seconds from 0.01 to 3600"):
            make_scheduler(prepare(s, overrides={"campaign.scheduler_options": {"time_limit_s": bad}}))


def test_a_policy_file_given_to_a_rule_is_refused_not_ignored():
    """`--scheduler mwkr:P.zip` ran MWKR and never read P.zip; `--planner lhs:P.zip` likewise."""
    from twin.runtime.lab import make_planner, make_scheduler, prepare

    root = Path(__file__).resolve().parents[2]
    shop = prepare(root / "scenarios" / "jobshop.yaml")
    policy = root / "agents" / "policies" / "jobshop_scheduler.zip"
    with pytest.raises(TwinError, match=rf"'mwkr' reads no policy file; a trained scheduler is rl:PATH "
                                        rf"\(`--scheduler rl:{policy}`\)"):
        make_scheduler(shop, f"mwkr:{policy}")
    assert make_scheduler(shop, f"rl:{policy}").follower is None  # a policy through rl: is read
    dots = prepare(root / "scenarios" / "quantum_dots.yaml")
    with pytest.raises(TwinError, match="planner 'lhs' reads no policy file"):
        make_planner(prepare(dots, overrides={"campaign.planner": "lhs:agents/policies/quantum_dots.zip"}))


def test_a_misspelt_driver_option_is_named_where_the_driver_lists_its_options(tmp_path):
    """`devices.reactor.options.kq` (for kp) reached the reactor, which read kp's default and said nothing."""
    from twin.runtime.lab import prepare

    catalyst = prepare(Path(__file__).resolve().parents[2] / "scenarios" / "catalyst.yaml")
    typo = prepare(catalyst, overrides={"devices.reactor.options": {"kp": 6.0, "kq": 3.0}})
    with pytest.raises(DriverError, match=r"devices\.reactor\.options\.kq: the 'reactor' driver takes no option 'kq' "
                                          r"\(it takes controller, dt_s, kd, ki, kp, telemetry_s\)"):
        load_driver(typo, "reactor", "reactor")
    assert load_driver(catalyst, "reactor", "reactor").pid["kp"] == 6.0
    plain = load(write(tmp_path, qd_lab(**{"devices.spectrometer.options": {"anything": 1}})))
    with pytest.raises(DriverError, match=r"takes no option 'anything' \(it takes none\)"):
        load_driver(plain, "spectrometer", "spectrometer")


def test_a_class_string_that_does_not_import_says_why(tmp_path):
    s = load(write(tmp_path, qd_lab(**{"devices.synthesiser.driver": "nowhere.module:Robot"})))
    with pytest.raises(DriverError, match="could not import 'nowhere.module'"):
        load_driver(s, "synthesiser", "synthesiser")


def test_a_driver_module_beside_the_scenario_is_not_imported_and_the_error_says_how(tmp_path):
    """A scenario may come from anyone: a .py beside it is not run; the error names it and says how to let it.
    (The `twin` command, as installed: `python -m` would put the folder on the path itself.)"""
    (tmp_path / "mine_robot.py").write_text("import sys\nsys.exit('the module ran')\n")
    path = write(tmp_path, qd_lab(**{"devices.synthesiser.driver": "mine_robot:Robot"}))
    command = Path(sys.executable).parent / "twin"
    res = subprocess.run([str(command), "validate", path.name], capture_output=True, text=True, cwd=tmp_path)
    assert res.returncode == 2 and "the module ran" not in res.stdout + res.stderr
    assert "mine_robot.py is in this folder" in res.stderr and "PYTHONPATH=." in res.stderr
    ok = subprocess.run([str(command), "validate", path.name], capture_output=True, text=True, cwd=tmp_path,
                        env={**os.environ, "PYTHONPATH": "."})
    assert "the module ran" in ok.stderr  # as told: now it is imported


def test_twin_run_names_the_file_and_field_of_a_driver_it_cannot_load_before_running(tmp_path):
    path = write(tmp_path, qd_lab(**{"devices.spectrometer.driver": "robot9000"}), "lab.yaml")
    journal = tmp_path / "j.db"
    res = twin_cli("run", path, "--bus", "memory", "--journal", journal)
    assert res.exit_code == 2
    assert f"{path}: 1 problem" in res.stderr and "devices.spectrometer.driver: unknown driver 'robot9000'" in (
        res.stderr)
    assert "lab 0 s" not in res.stderr and not journal.exists()  # refused before the progress bar, the journal


def test_a_device_type_served_elsewhere_is_not_loaded_here(tmp_path):
    """Its driver may be installed only where it is served (`twin device serve`); what it outputs is not known
    here, so targets are not checked against it. Not every instance elsewhere: this process loads it."""
    s = load(write(tmp_path, qd_lab(**{"devices.spectrometer.driver": "robot9000"})))
    check(s, external=s.instance_names("spectrometer"))
    with pytest.raises(ScenarioError, match="devices.spectrometer.driver"):
        check(s)
    two = load(write(tmp_path, qd_lab(**{"devices.spectrometer.driver": "robot9000",
                                        "devices.spectrometer.instances": 2}), "two.yaml"))
    with pytest.raises(ScenarioError, match="devices.spectrometer.driver"):
        check(two, external=two.instance_names("spectrometer")[:1])


def test_an_unknown_plugin_name_near_an_installed_one_says_which_was_meant():
    """`--planner gp_bo` and `--schedulers mwrk` listed what was installed without pointing at the near one."""
    from twin.core import plugins
    from twin.core.errors import PluginError

    for kind, name, meant in (("planners", "gp_bo", "gp-bo"), ("schedulers", "mwrk", "mwkr")):
        with pytest.raises(PluginError) as caught:
            plugins.load(kind, name)
        assert f"{name!r} (did you mean {meant!r}?). Installed: " in str(caught.value), caught.value
    with pytest.raises(PluginError) as caught:
        plugins.load("planners", "zzz")
    assert "did you mean" not in str(caught.value) and "Installed: fixed, gp-bo" in str(caught.value)


def test_a_lab_of_machines_needs_no_chemistry_model_and_one_that_simulates_names_it(tmp_path):
    """A parameter box for a lab whose devices only keep time was "chemistry.model: required field is missing",
    with no word of the model ('none') such a lab has; and a machine ran only "op" unless its options listed the
    steps the scenario had just given it."""
    from twin.runtime.lab import run

    machine = {"driver": "machine", "steps": ["mix"], "duration": {"mean_s": 300}}
    lab = {"name": "mixing", "devices": {"mixer": machine}, "workflow": [{"step": "mix", "device": "mixer"}],
           "chemistry": {"parameters": {"x": {"low": 0, "high": 1}}},
           "campaign": {"budget": 3, "planner": "random", "scheduler": "fifo"}}
    assert run(write(tmp_path, lab), journal=tmp_path / "j.db").done == 3
    simulating = qd_lab()
    simulating["chemistry"] = {k: v for k, v in simulating["chemistry"].items() if k != "model"}
    res = twin_cli("validate", write(tmp_path, simulating))
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "bad.yaml: 2 problems" in said, said  # each driver that simulates one
    for dtype in ("spectrometer", "synthesiser"):
        assert f"chemistry.model: none given, and the '{dtype}' driver of devices.{dtype} simulates a chemistry: " \
               "give chemistry.model, one of ['bandgap', 'catalyst', 'quantum_dots', 'synthesis']" in said


def test_a_workflow_that_measures_before_any_step_makes_a_sample_is_refused_naming_the_step(tmp_path):
    """A spectrometer's measure after only a machine step (which passes on a sample, and makes none): every
    experiment was abandoned at that step when it ran. Drivers now say which of their steps make a sample and
    which need one, and validation refuses the workflow, naming the step and what makes one here."""
    machine = {"driver": "machine", "steps": ["heat"], "options": {"steps": ["heat"]}, "duration": {"mean_s": 60}}
    person = {"driver": "operator", "steps": ["load"], "duration": {"mean_s": 60}}
    lab = qd_lab(**{"devices.oven": machine, "devices.tech": person,
                    "workflow": [{"step": "load", "device": "tech"}, {"step": "heat", "device": "oven"},
                                 {"step": "measure", "device": "spectrometer"}]})
    with pytest.raises(ScenarioError) as err:
        check(parse(lab, "lab.yaml"))
    assert ("workflow.2: measure on spectrometer needs a sample, and no step before it makes one (synthesise on "
            "synthesiser does): put a step that makes one first") in str(err.value)
    made = {**lab, "workflow": [{"step": "synthesise", "device": "synthesiser"}, *lab["workflow"]]}
    check(parse(made, "lab.yaml"))  # a sample made first, passed on by the person and the oven
    # a campaign of a shared lab is checked on the device types its workflow uses: what makes a sample is another's
    shared = yaml.safe_load((ROOT / "scenarios" / "shared_lab.yaml").read_text())
    shared["campaigns"][0]["workflow"] = [{"step": "measure", "device": "spectrometer"}]
    with pytest.raises(ScenarioError) as err:
        check(parse(shared, "lab.yaml"))
    assert ("campaigns.0 (dots): workflow.0: measure on spectrometer needs a sample, and no step before it makes one "
            "(prepare on synthesiser and synthesise on synthesiser do)") in str(err.value)
    # a lab where nothing makes one (a coater that only keeps time): the installed drivers that do are named
    coater = {**lab, "devices": {k: v for k, v in lab["devices"].items() if k != "synthesiser"}}
    with pytest.raises(ScenarioError) as err:
        check(parse(coater, "lab.yaml"))
    assert ("workflow.2: measure on spectrometer needs a sample, and no step before it makes one, nor does any "
            "device of the lab: put first a step on a device whose driver makes one (installed: ") in str(err.value)
    assert "synthesiser), or a driver of yours that declares makes_sample (docs/drivers.md)" in str(err.value)


def test_a_twin_that_makes_no_sample_for_a_driver_that_does_is_warned_of(caplog):
    """On a virtual clock a twin that only keeps time stands in for the synthesiser: the measurement after it
    would find no sample. Warned of (the twin still serves a what-if of device counts); on a scaled clock, where
    the synthesiser itself runs, not."""
    lab = qd_lab(**{"devices.synthesiser.twin": {"driver": "machine", "options": {"steps": ["synthesise"]}}})
    with caplog.at_level(logging.WARNING):
        check(parse(lab, "lab.yaml"))
    said = [r.getMessage() for r in caplog.records if "needs a sample" in r.getMessage()]
    assert said == ["with the twins (devices.*.twin) workflow.1: measure on spectrometer needs a sample, and no step "
                    "before it makes one: put a step that makes one first: on a virtual clock every experiment is "
                    "abandoned there"]
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        check(parse({**lab, "clock": {"mode": "scaled", "speed": 100}}, "lab.yaml"))
    assert not [r for r in caplog.records if "needs a sample" in r.getMessage()]


def test_a_driver_that_says_nothing_of_samples_may_make_one_and_a_bad_declaration_is_refused(monkeypatch):
    from devices.machine import Machine

    lab = qd_lab(**{"devices.oven": {"driver": "machine", "steps": ["heat"], "options": {"steps": ["heat"]},
                                     "duration": {"mean_s": 60}},
                    "workflow": [{"step": "heat", "device": "oven"}, {"step": "measure", "device": "spectrometer"}]})
    monkeypatch.delattr(Machine, "makes_sample")  # a third party's driver, written before the feature
    check(parse(lab, "lab.yaml"))
    monkeypatch.setattr(Machine, "makes_sample", "heat", raising=False)
    with pytest.raises(ScenarioError, match="(?s)lab.yaml: .*devices.oven.driver 'machine': makes_sample is 'heat', "
                                            r"not a set of step names: write makes_sample = frozenset\(\{'heat'\}\)"):
        checked(parse(lab, "lab.yaml"), "lab.yaml")


def test_every_plugin_that_does_not_load_is_named_at_once(tmp_path):
    """A driver, a planner and a scheduler misspelt were three tries of `twin validate`, one error each."""
    res = twin_cli("validate", write(tmp_path, qd_lab(**{"devices.spectrometer.driver": "spectrometr",
                                                         "campaign.planner": "gp_bo", "campaign.scheduler": "nope",
                                                         "campaign.fallback_scheduler": "fifo"})))
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "bad.yaml: 3 problems" in said, said
    for field, what in (("devices.spectrometer.driver", "spectrometr"), ("campaign.planner", "gp_bo"),
                        ("campaign.scheduler", "nope")):
        assert f"- {field}: " in said and repr(what) in said, (field, said)


def test_what_the_loaded_plugins_tell_is_said_at_once_too(tmp_path):
    """An option no planner takes and a target no device can meet were two tries, one error each."""
    lab = qd_lab(**{"campaign.planner_options": {"n_inti": 3}})
    lab["chemistry"]["targets"][0]["outputs"] = {"hue_deg": {"value": 120, "tol": 5}}
    res = twin_cli("validate", write(tmp_path, lab))
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "bad.yaml: 2 problems" in said, said
    assert "campaign.planner_options.n_inti: no installed planner takes an option 'n_inti'" in said, said
    assert "chemistry.targets.0.outputs.hue_deg: no device of the workflow produces 'hue_deg'" in said, said
    # a target only one installed driver measures, in a lab of machines that measure nothing: it is named
    machines = qd_lab(**{"devices": {"oven": {"driver": "machine", "steps": ["heat"], "duration": {"mean_s": 60}}},
                         "workflow": [{"step": "heat", "device": "oven"}]})
    res = twin_cli("validate", write(tmp_path, machines))
    assert ("chemistry.targets.0.outputs.peak_nm: no device of the workflow produces 'peak_nm' (oven declares no "
            "outputs): measure it with a step on a device whose driver does (installed: spectrometer), or drop the "
            "target") in " ".join(res.output.split()), res.output


class SerialPump:
    """A third party's driver on a serial port: one device holds a port alone."""

    capabilities = frozenset({"synthesise"})
    option_names = frozenset({"port"})

    def __init__(self, setup):
        self.claims = f"serial port {setup.options.get('port', '/dev/ttyUSB0')}"

    async def run(self, step, params, sample, ctx):
        raise NotImplementedError

    async def safe_state(self):
        pass


def test_two_devices_that_claim_one_topic_or_port_are_refused_naming_both():
    """Two MQTT instances on one topic (no {name} in it) both drove one instrument: each took the other's results
    as strangers' and failed its step. A driver's ``claims`` now says what an instance holds alone, and two devices
    claiming the same are refused before anything runs — on the lab's own clock; on a virtual one the twins run."""
    mqtt = {"driver": "mqtt", "instances": 2, "steps": ["measure"], "duration": {"mean_s": 60},
            "options": {"broker": "127.0.0.1:1883", "topic": "lab/reader", "steps": ["measure"]},
            "twin": {"driver": "spectrometer"}}
    scaled = {"clock": {"mode": "scaled", "speed": 100}}
    with pytest.raises(ScenarioError) as err:
        check(parse(qd_lab(**{"devices.spectrometer": mqtt, **scaled}), "lab.yaml"))
    assert ("devices.spectrometer: spectrometer-1 and spectrometer-2 both hold the MQTT topic lab/reader at "
            "127.0.0.1:1883 (options.topic; {name} in it gives each instance its own), which only one device can "
            "hold") in str(err.value)
    named = {**mqtt, "options": {**mqtt["options"], "topic": "lab/{name}"}}
    check(parse(qd_lab(**{"devices.spectrometer": named, **scaled}), "lab.yaml"))
    check(parse(qd_lab(**{"devices.spectrometer": mqtt, **scaled}), "lab.yaml"), external=["spectrometer-2"])
    check(parse(qd_lab(**{"devices.spectrometer": mqtt}), "lab.yaml"))  # virtual: the twins stand in
    pump = {"driver": "tests.twin.test_scenario_plugins:SerialPump", "options": {"port": "/dev/ttyUSB0"},
            "steps": ["synthesise"], "duration": {"mean_s": 60}}
    lab = qd_lab(**{"devices.synthesiser": pump, "devices.mixer": pump, **scaled,
                    "devices.spectrometer.driver": "spectrometer"})
    with pytest.raises(ScenarioError) as err:
        check(parse(lab, "lab.yaml"))
    assert "devices.mixer: synthesiser and mixer both hold serial port /dev/ttyUSB0, which only" in str(err.value)


def test_a_misspelt_class_of_a_module_is_named_with_the_class_meant(tmp_path):
    """`module 'devices.synthesiser' has no attribute 'Synth'` said nothing of what the module has."""
    for given, said in (("devices.synthesiser:Synth", " (did you mean devices.synthesiser:Synthesiser?)"),
                        ("tests.twin.test_scenario_plugins:Zzz", "; its classes: SerialPump, Weighted")):
        res = twin_cli("validate", write(tmp_path, qd_lab(**{"devices.synthesiser.driver": given})))
        assert res.exit_code == 2, res.output
        assert f"has no attribute {given.partition(':')[2]!r} (from {given!r}){said}" in " ".join(res.output.split())
