"""Each class of bad scenario gets one message per problem naming file, field and value; exit 2, no traceback."""

import json
import logging
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab, twin_cli
from twin.core.errors import ScenarioError
from twin.scenario import parse
from twin.scenario import load

ROOT = Path(__file__).resolve().parents[2]


def write(tmp_path, raw, name="bad.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(raw) if not isinstance(raw, str) else raw)
    return path


def twin(*args):
    return subprocess.run([sys.executable, "-m", "twin", *args], capture_output=True, text=True, cwd=ROOT)


@pytest.mark.parametrize(
    "changes, field, shown",
    [
        ({"campaign.budget": "lots"}, "campaign.budget", "'lots'"),
        ({"campaign.budgett": 3}, "campaign.budgett", "unknown field"),
        ({"devices.synthesiser.faults": {"fail_p": 1.5}}, "devices.synthesiser.faults.fail_p", "1.5"),
        ({"chemistry.parameters.time_s": {"low": 10, "high": 5}}, "chemistry.parameters.time_s", "below high"),
        ({"clock.mode": "sundial"}, "clock.mode", "'sundial'"),
        ({"devices.synthesiser.cost": {"per_hour": 40}}, "devices.synthesiser.cost", "got a mapping of per_hour"),
        ({"devices.synthesiser.instances": {}}, "devices.synthesiser.instances", "got an empty mapping, {}"),
    ],
)
def test_each_bad_field_is_named_with_its_value(tmp_path, changes, field, shown):
    path = write(tmp_path, qd_lab(**changes))
    with pytest.raises(ScenarioError) as info:
        load(path)
    text = str(info.value)
    assert str(path) in text and field in text and shown in text


@pytest.mark.parametrize("changes, says", [
    ({"campaign.budgett": 3}, "campaign.budgett: unknown field; did you mean campaign.budget?"),
    ({"devices.synthesiser.faults": {"fial_p": 0.1}},
     "devices.synthesiser.faults.fial_p: unknown field; did you mean devices.synthesiser.faults.fail_p?"),
    ({"workflow": [{"step": "synthesise", "device": "synthesiser", "parms": {}}]},
     "workflow.0.parms: unknown field; did you mean workflow.0.params?"),
    ({"colour": "red"}, "colour: unknown field; the top level has bus, campaign, campaigns, chemistry, clock"),
    ({"targets": []}, "targets: unknown field; did you mean chemistry.targets?"),  # a field in the wrong section
    ({"campaign.model": "none"}, "campaign.model: unknown field; did you mean chemistry.model?"),
    ({"fail_p": 0.1}, "fail_p: unknown field; did you mean devices.<name>.faults.fail_p?"),
])
def test_an_unknown_field_is_shown_with_the_field_it_was_likely_meant_to_be(tmp_path, changes, says):
    """It said only "unknown field (check the spelling)", leaving the user to find the name in `twin schema`."""
    with pytest.raises(ScenarioError) as info:
        load(write(tmp_path, qd_lab(**changes)))
    assert any(p.startswith(says) for p in info.value.problems), info.value.problems


def test_validate_checks_a_file_with_the_overrides_a_run_would_be_given():
    """`twin validate FILE --set ...` was "No such option: --set": an override was checked only by running it."""
    path = ROOT / "scenarios" / "quantum_dots.yaml"
    bad = twin_cli("validate", path, "--set", "devices.synthesiser.instances=100000")
    said = " ".join(bad.output.split())
    assert bad.exit_code == 2 and "devices.synthesiser.instances: Input should be less than or equal to 64" in said
    assert twin_cli("validate", path, "--set", "devices.synthesiser.instances=3").exit_code == 0


def test_a_number_written_with_an_exponent_is_a_number_in_a_file_in_set_and_in_vary(tmp_path):
    """PyYAML reads YAML 1.1, where 1e3 is text: `mean_s: 1e3` was refused as "not a valid number (got '1e3')"."""
    from twin.tools.whatif import parse_vary

    text = yaml.safe_dump(qd_lab()).replace("budget: 8", "budget: 8\n  max_lab_hours: 2.5e1")
    text = text.replace("mean_s: 60", "mean_s: 6E+1", 1)
    s = load(write(tmp_path, text))
    assert s.campaign.max_lab_hours == 25.0 and s.devices["synthesiser"].duration.mean_s == 60.0
    ok = twin_cli("validate", write(tmp_path, text), "--set", "devices.spectrometer.duration.mean_s=1e3")
    assert ok.exit_code == 0, ok.output
    count = twin_cli("validate", write(tmp_path, text), "--set", "campaign.budget=1e2")
    assert count.exit_code == 2 and "campaign.budget: Input should be a valid integer (got 100.0): write it as a " \
        "whole number, 100" in " ".join(count.output.split()), count.output
    assert parse_vary(["devices.spectrometer.duration.mean_s=1e3,1.5e3,-2e-1,1e"]) == [
        ("devices.spectrometer.duration.mean_s", [1000.0, 1500.0, -0.2, "1e"])]


def test_a_single_value_where_a_list_goes_is_shown_as_the_list_to_write():
    """`--set bus.listen=tcp/127.0.0.1:7500` said only "Input should be a valid list", not how to write one there."""
    bad = twin_cli("validate", ROOT / "scenarios" / "quantum_dots.yaml", "--set", "bus.listen=tcp/127.0.0.1:7500")
    said = " ".join(bad.output.split())
    assert bad.exit_code == 2 and "bus.listen: Input should be a valid list (got 'tcp/127.0.0.1:7500'): write a " \
        "list, [tcp/127.0.0.1:7500] (quoted on a command line: --set 'bus.listen=[tcp/127.0.0.1:7500]')" in said, said
    fixed = twin_cli("validate", ROOT / "scenarios" / "quantum_dots.yaml", "--set", "bus.listen=[tcp/127.0.0.1:7500]")
    assert fixed.exit_code == 0, fixed.output


def test_every_problem_is_reported_not_just_the_first(tmp_path):
    path = write(tmp_path, qd_lab(**{"campaign.budget": -1, "campaign.seed": "x", "clock.speed": 0}))
    with pytest.raises(ScenarioError) as info:
        load(path)
    assert len(info.value.problems) == 3


def test_workflow_naming_a_missing_device_type(tmp_path):
    path = write(tmp_path, qd_lab(workflow=[{"step": "synthesise", "device": "robot"}]))
    with pytest.raises(ScenarioError, match="'robot' is not a device type"):
        load(path)


def test_a_lab_without_devices_says_so_and_a_device_type_it_lacks_says_there_are_none(tmp_path):
    path = write(tmp_path, {"name": "x", "workflow": [{"step": "a", "device": "robot"}]})
    with pytest.raises(ScenarioError) as err:
        load(path)
    assert err.value.problems[0].startswith("devices: none; a lab needs at least one device type")
    assert err.value.problems[1] == "workflow.0.device: 'robot' is not a device type of this lab (it has none)"


@pytest.mark.parametrize("changes, says", [
    ({"jobshop": "ft06.txt"}, "jobshop: should be a mapping of its fields: file, instance "),
    ({"devices.synthesiser.duration": 600}, "devices.synthesiser.duration: should be a mapping of its fields: "
                                            "mean_s, cv, "),
])
def test_a_section_given_as_a_value_says_which_fields_it_takes(tmp_path, changes, says):
    with pytest.raises(ScenarioError) as err:
        load(write(tmp_path, qd_lab(**changes)))
    assert err.value.problems[0].startswith(says), err.value.problems


@pytest.mark.parametrize("use, problems", [
    ({"fixed": -2}, ["consumables.x.used_by.measure.fixed: Input should be greater than or equal to 0 (got -2)"]),
    ("one", ["consumables.x.used_by.measure: Input should be a valid number (got 'one')",
             "consumables.x.used_by.measure: should be a mapping of its fields: fixed, per (`twin schema` says what "
             "each means) (got 'one')"]),
])
def test_a_field_of_a_number_or_a_section_names_the_field_not_the_members_of_the_union(tmp_path, use, problems):
    """``used_by``'s ``float | Usage``: pydantic names each member (``measure.Usage.fixed``, ``measure.float``) and
    says a mapping is no number; the file's reader wants the field, and a mapping's own problems only."""
    with pytest.raises(ScenarioError) as err:
        load(write(tmp_path, qd_lab(consumables={"x": {"level": 5, "used_by": {"measure": use}}})))
    assert err.value.problems == problems


def test_problems_across_fields_are_listed_one_each_under_their_own_field(tmp_path):
    path = write(tmp_path, qd_lab(**{"workflow": [{"step": "synthesise", "device": "robot"},
                                                  {"step": "measure", "device": "spectrometer"}],
                                     "training.instances": {"hplc": [1, 2]}}))
    with pytest.raises(ScenarioError) as err:
        load(path)
    assert [p.split(":")[0] for p in err.value.problems] == ["training.instances.hplc", "workflow.0.device"]


def test_cli_validate_exits_2_without_a_traceback(tmp_path):
    bad = write(tmp_path, qd_lab(**{"devices.synthesiser.driver": "robot9000", "campaign.budget": "x"}), "a.yaml")
    broken = write(tmp_path, "name: [unclosed\n", "b.yaml")
    good = ROOT / "scenarios" / "quantum_dots.yaml"
    res = twin("validate", str(bad), str(broken), str(good))
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert "campaign.budget" in res.stderr and "'x'" in res.stderr
    assert "b.yaml" in res.stderr and "line 2, column 1" in res.stderr
    assert "✓" in res.stdout and "quantum_dots.yaml" in res.stdout


def test_cli_run_of_a_bad_scenario_exits_2(tmp_path):
    bad = write(tmp_path, qd_lab(**{"devices.synthesiser.driver": "robot9000"}))
    res = twin_cli("run", bad, "--quiet")
    assert res.exit_code == 2
    assert "robot9000" in res.stderr and "Installed:" in res.stderr


def test_shipped_scenarios_validate(caplog):
    res = twin_cli("validate", *sorted(str(p) for p in (ROOT / "scenarios").glob("*.yaml")))
    assert res.exit_code == 0, res.stderr
    assert "warning" not in res.stdout + res.stderr, res.stdout + res.stderr
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text  # a process prints these


def test_a_device_type_no_step_runs_on_is_warned_of_when_the_planner_runs_the_workflow_as_written(tmp_path):
    """A second spectrometer type the workflow never names stays idle: said before the run, naming it. Not for a
    planner that may propose routes of its own (bandgap's multi-fidelity one sends work to `dft`, which no
    workflow step names), nor for people."""
    spare = {"driver": "spectrometer", "instances": 2, "steps": ["measure"], "duration": {"mean_s": 60}}
    person = {"driver": "operator", "instances": 1, "steps": ["load"], "duration": {"mean_s": 60}}
    lab = write(tmp_path, qd_lab(**{"devices.spare": spare, "devices.technician": person,
                                    "campaign.planner": "gp-bo"}), "lab.yaml")
    res = twin_cli("validate", lab, str(ROOT / "scenarios" / "bandgap.yaml"))
    assert res.exit_code == 0, res.stderr
    warnings = [line for line in res.stderr.splitlines() if "warning:" in line]
    assert len(warnings) == 1 and "devices.spare: no workflow step runs on it" in warnings[0], res.stderr
    assert "its 2 instances will stay idle" in warnings[0] and str(lab) in warnings[0]
    routed = twin_cli("validate", str(ROOT / "scenarios" / "bandgap.yaml"), "--set", "campaign.planner=gp-bo")
    assert "devices.dft: no workflow step runs on it" in routed.stderr  # gp-bo sends nothing to dft


def test_a_planner_that_aims_at_targets_is_warned_of_in_a_lab_with_none():
    """GP-BO with no targets only explores, silently; random and the fixed list are what such a lab means."""
    qd = str(ROOT / "scenarios" / "quantum_dots.yaml")
    for planner, lab in (("gp-bo", qd), ("mf-gp-bo", str(ROOT / "scenarios" / "bandgap.yaml"))):
        res = twin_cli("validate", lab, "--set", "chemistry.targets=[]", "--set", f"campaign.planner={planner}")
        assert res.exit_code == 0, res.stderr
        said = " ".join(res.stderr.split())
        assert f"chemistry.targets: none, and planner '{planner}' chooses each experiment by its chance of meeting a " \
               "target, so it only explores" in said, said
    for planner in ("random", "lhs"):
        res = twin_cli("validate", qd, "--set", "chemistry.targets=[]", "--set", f"campaign.planner={planner}")
        assert res.exit_code == 0 and "warning" not in res.stderr, res.stderr


def test_validate_shows_each_warning_under_the_file_that_gave_it(tmp_path):
    """A lab whose measuring device only keeps time in the twin (the `machine` driver) can meet no target on a
    virtual clock: valid, warned of, and the warning names its file — not the other file checked beside it."""
    twin_only_times = {"driver": "machine", "options": {"steps": ["measure"]}}
    twinned = write(tmp_path, qd_lab(**{"devices.spectrometer.twin": twin_only_times}), "twinned.yaml")
    plain = write(tmp_path, qd_lab(), "plain.yaml")
    res = twin_cli("validate", twinned, plain)
    assert res.exit_code == 0, res.stderr
    assert f"✓ {twinned} (1 warning)" in res.stdout and f"✓ {plain}\n" in res.stdout
    warnings = [line for line in res.stderr.splitlines() if "warning:" in line]
    assert len(warnings) == 1 and warnings[0].startswith(f"! {twinned}: warning: ")
    assert "no experiment meets that target" in warnings[0]


@pytest.mark.parametrize("dotted, says", [
    ("devices.spectrometr.instances", "devices.spectrometr: not in the scenario; did you mean devices.spectrometer?"),
    ("devices.spectrometer.durration.mean_s", "did you mean devices.spectrometer.duration?"),
])
def test_an_override_through_a_misspelt_name_says_which_was_meant(tmp_path, dotted, says):
    from twin.runtime.lab import prepare

    path = write(tmp_path, qd_lab())
    with pytest.raises(ScenarioError) as from_file:
        load(path, {dotted: 3})
    with pytest.raises(ScenarioError) as from_scenario:  # a variant of a loaded scenario (twin whatif, benches)
        prepare(load(path), overrides={dotted: 3})
    assert says in str(from_file.value) and says in str(from_scenario.value)
    misspelt = says.split(":")[0] if ":" in says else dotted.rsplit(".", 1)[0]
    for caught in (from_file, from_scenario):  # said once, not echoed by what it would lack as a new entry
        first, *rest = caught.value.problems
        assert first.startswith(misspelt + ": not in the scenario; did you mean"), first
        assert not any(p.startswith((misspelt + ".", misspelt + ":")) for p in rest), rest
    new = load(path, {"devices.centrifuge.instances": 2, "devices.centrifuge.driver": "synthesiser",
                      "devices.centrifuge.steps": ["spin"], "devices.centrifuge.duration.mean_s": 60})
    assert new.devices["centrifuge"].instances == 2  # a name far from every other is a new entry, not a typo


def test_an_override_of_a_device_the_scenario_lacks_says_which_it_has_before_what_a_new_one_needs(tmp_path):
    """`twin whatif aspirin.yaml --vary devices.reactor.instances=1,2` listed only the missing driver, steps and
    duration of a new device 'reactor', as if the user had meant to make one."""
    with pytest.raises(ScenarioError) as caught:
        load(write(tmp_path, qd_lab()), {"devices.reactor.instances": 2})
    first, *rest = caught.value.problems
    assert first == "devices.reactor: not in the scenario; devices has spectrometer, synthesiser"
    assert "devices.reactor.driver: required field is missing" in rest


def test_twin_schema_gives_every_field_its_meaning():
    """The README says `twin schema` prints every field with its meaning: an editor shows it as the field's hint."""
    import json

    res = subprocess.run([sys.executable, "-m", "twin", "schema"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    schema = json.loads(res.stdout)
    models = {"Scenario": schema, **schema["$defs"]}
    bare = [f"{name}.{field}" for name, model in models.items() for field, spec in model.get("properties", {}).items()
            if not spec.get("description")]
    assert not bare, bare
    assert "the sample waits (and ages)" in models["DeviceType"]["properties"]["clean_s"]["description"]


def test_a_json_schema_validator_takes_every_shipped_scenario_by_twin_schema_and_names_each_mistake():
    """Editors check scenario files against `twin schema` with a JSON Schema validator, not labtwin's: a schema that
    refused a valid file, or let a misspelt field by, would mislead them as they type."""
    import json

    import jsonschema

    validator = jsonschema.Draft202012Validator(json.loads(twin_cli("schema").stdout))
    for path in sorted((ROOT / "scenarios").glob("*.yaml")):
        assert not [e.message for e in validator.iter_errors(yaml.safe_load(path.read_text()))], path
    doc = yaml.safe_load((ROOT / "scenarios" / "quantum_dots.yaml").read_text())
    doc["devices"]["synthesiser"]["instancs"] = 2
    doc["campaign"]["budget"] = -3
    doc["lab"] = "bad lab/x"
    assert {tuple(e.path) for e in validator.iter_errors(doc)} == {("lab",), ("devices", "synthesiser"),
                                                                   ("campaign", "budget")}


def test_a_scenario_given_as_dash_is_read_from_standard_input_and_its_paths_from_the_current_directory(
        tmp_path, monkeypatch):
    """`cat lab.yaml | twin run -` said "-: file not found"."""
    monkeypatch.chdir(ROOT)
    ok = twin_cli("validate", "-", input=(ROOT / "scenarios" / "quantum_dots.yaml").read_text())
    assert ok.exit_code == 0 and ok.stdout.startswith("✓ -"), ok.stdout + ok.stderr
    bad = twin_cli("validate", "-", input="lab: x\n")
    assert bad.exit_code == 2 and "-: 1 problem" in bad.stderr and "name: required field is missing" in bad.stderr
    monkeypatch.chdir(ROOT / "scenarios")  # jobshop/ft06.txt
    shop = twin_cli("run", "-", "--bus", "memory", "--json", "--journal", str(tmp_path / "j.db"),
                    input=(ROOT / "scenarios" / "jobshop.yaml").read_text())
    assert shop.exit_code == 0, shop.stderr
    assert json.loads(shop.stdout)["scenario"] == "jobshop_ft06"
    # a bench loads its scenario once per shop: the second load read an empty stream ("-: 1 problem")
    shops = twin_cli("bench", "schedulers", "-", "--jobshop", "jobshop/ft06.txt,jobshop/la01.txt", "--schedulers",
                     "mwkr", "--json", input=(ROOT / "scenarios" / "jobshop.yaml").read_text())
    assert shops.exit_code == 0, shops.stderr
    assert [t["lab"] for t in json.loads(shops.stdout)["labs"]] == ["ft06", "la01"]


def test_a_job_shop_file_given_as_a_scenario_says_how_to_run_it(tmp_path):
    import re
    import shlex

    shop = ROOT / "scenarios" / "jobshop" / "la01.txt"
    with pytest.raises(ScenarioError) as caught:
        load(shop)
    said = str(caught.value)
    assert "la01.txt looks like a job-shop instance" in said
    command = shlex.split(re.search(r"run it with `(twin run [^`]+)`", said).group(1))
    assert command[:3] == ["twin", "run", "scenarios/jobshop.yaml"] and command[3] == "--set"
    field, value = command[4].split("=", 1)
    assert load(ROOT / command[2], {field: value}).jobshop.file == str(shop)  # the command it gives runs
    with pytest.raises(ScenarioError) as plain:
        load(write(tmp_path, "just some words here and 1 2\n", "words.yaml"))
    assert "job-shop" not in str(plain.value)


def _prepare_in_worker(overrides: dict) -> None:
    from twin.runtime.lab import prepare

    prepare(Path(__file__).resolve().parents[2] / "scenarios" / "flaky_lab.yaml", overrides=overrides)


def test_errors_cross_a_process_pool_whole():
    """A bench or a sweep runs its labs in worker processes: an error raised there came back as "TypeError:
    ScenarioError.__init__() missing 1 required positional argument" and broke the pool."""
    import pickle
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from twin.core.messages import InvalidMessage

    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
        with pytest.raises(ScenarioError) as caught:
            pool.submit(_prepare_in_worker, {"campaign.budget": -1}).result()
    assert caught.value.problems and "campaign.budget" in caught.value.problems[0]
    assert str(caught.value).startswith(caught.value.source)
    again = pickle.loads(pickle.dumps(InvalidMessage("spectrometer-1", "no body")))
    assert (again.sender, again.reason, str(again)) == ("spectrometer-1", "no body",
                                                        "invalid message from spectrometer-1: no body")


def test_faults_given_to_people_are_refused_naming_the_field_as_no_fault_would_ever_happen():
    """The twin injects faults around a driver; people (driver: operator) have none, so `fail_p: 0.5` on a
    technician was accepted and nothing ever failed (a bench's "technician flaky" shape ran the lab as written)."""
    from twin.tools.shape_bench import variants

    person = {"driver": "operator", "instances": 1, "steps": ["load"], "duration": {"mean_s": 60}}
    with pytest.raises(ScenarioError) as err:
        parse(qd_lab(**{"devices.technician": {**person, "faults": {"fail_p": 0.5}}}), "lab.yaml")
    assert "devices.technician: faults: people (driver: operator) are not simulated to fail" in str(err.value)
    lab = parse(qd_lab(**{"devices.technician": {**person, "faults": {"fail_p": 0}}}), "lab.yaml")  # none: fine
    names = [name for name, _ in variants(lab)]
    assert "technician bottleneck (mean_s ×2)" in names and "technician flaky (20 % fail)" not in names
    assert "synthesiser flaky (20 % fail)" in names


def test_a_lab_file_for_twin_lab_serve_is_checked_with_serve(tmp_path):
    """A lab that takes its campaigns later has no workflow: plain validate refused it, and pointed nowhere."""
    lab = {k: v for k, v in qd_lab().items() if k not in ("workflow", "campaign")}
    path = write(tmp_path, lab)
    plain = twin_cli("validate", path)
    assert plain.exit_code == 2 and "needs none of them: `twin validate --serve` checks one" in plain.output
    assert twin_cli("validate", "--serve", path).exit_code == 0
    lab["devices"]["spectrometer"]["driver"] = "spectromter"  # each device's driver is made, standing by
    lab["devices"]["synthesiser"]["driver"] = "synthesizer"
    bad = twin_cli("validate", "--serve", write(tmp_path, lab))
    said = " ".join(bad.output.split())
    assert bad.exit_code == 2 and "2 problems" in said, said
    assert "devices.spectrometer.driver: unknown driver 'spectromter' (did you mean 'spectrometer'?)" in said
    assert "devices.synthesiser.driver: unknown driver 'synthesizer'" in said
    shared = twin_cli("validate", "--serve", ROOT / "scenarios" / "shared_lab.yaml")  # campaigns: each checked
    assert shared.exit_code == 0, shared.output


def test_validate_json_gives_each_files_problems_and_warnings_and_strict_fails_on_warnings(tmp_path):
    """A CI that keeps scenario files clean read ✓/✗ lines and had no way to fail on a warning."""
    (tmp_path / "clean.yaml").write_text(yaml.safe_dump(qd_lab()))
    (tmp_path / "warned.yaml").write_text(yaml.safe_dump(qd_lab(**{"devices.oven": {
        "driver": "machine", "steps": ["heat"], "duration": {"mean_s": 60}}})))  # no workflow step runs on it
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(qd_lab(**{"campaign.budget": -1})))
    files = [tmp_path / n for n in ("clean.yaml", "warned.yaml", "bad.yaml")]
    res = twin_cli("validate", *files, "--json")
    out = json.loads(res.stdout)
    assert res.exit_code == 2 and out["ok"] is False
    assert [(c["ok"], len(c["problems"]), len(c["warnings"])) for c in out["files"]] == [(True, 0, 0), (True, 0, 1),
                                                                                         (False, 1, 0)]
    assert out["files"][2]["problems"][0].startswith("campaign.budget: ")
    assert "devices.oven: no workflow step runs on it" in out["files"][1]["warnings"][0]
    assert twin_cli("validate", *files[:2]).exit_code == 0
    strict = twin_cli("validate", *files[:2], "--strict")
    assert strict.exit_code == 2 and "warned.yaml (1 warning): --strict fails it" in strict.stdout, strict.stdout
    assert json.loads(twin_cli("validate", files[0], "--json", "--strict").stdout)["ok"] is True


@pytest.mark.parametrize("given,meant", [("quantum_dot.yaml", "quantum_dots.yaml"), ("flaky.yml", "flaky_lab.yaml"),
                                         ("Catalyst.yaml", "catalyst.yaml"), ("nothing_like_it.yaml", None)])
def test_a_missing_scenario_names_the_file_beside_it_likely_meant(given, meant):
    res = twin_cli("validate", str(ROOT / "scenarios" / given))
    assert res.exit_code == 2 and "file not found" in res.stderr
    said = " ".join(res.stderr.split())
    if meant is None:
        assert "check the path" in said and "did you mean" not in said
    else:
        assert f"did you mean {ROOT / 'scenarios' / meant}?" in said
