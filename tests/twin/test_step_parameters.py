"""A workflow step's own parameters (`workflow: [{step: cv, device: potentiostat, params: {cycles: 900}}]`) count
where the experiment's do: a duration's `plus_param`, a device's `envelope`, a consumable's amount `per` parameter,
the objective's time unit. The lab always took them (it merges the experiment's parameters with the step's);
validation and the weighing of lab time did not."""

from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from twin.campaign.consumables import amount
from twin.core.errors import ScenarioError
from twin.runtime.checks import check
from twin.scenario import load, parse

ROOT = Path(__file__).resolve().parents[2]


def write(tmp_path, raw, name="bad.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize("hold_s, warned", [(20000, True), (600, False)])
def test_a_hold_time_the_workflow_gives_is_weighed_against_the_deadline(tmp_path, caplog, hold_s, warned):
    """The reactor's steps last time_s; here the workflow gives it (not the planner's box) and the duration model
    leaves it out: a hold longer than the deadline is warned of, naming the field to give; a shorter one is not."""
    raw = yaml.safe_load((ROOT / "scenarios" / "flaky_lab.yaml").read_text())
    raw["devices"]["reactor"]["duration"].pop("plus_param")
    del raw["chemistry"]["parameters"]["time_s"]
    raw["workflow"][1]["params"] = {"time_s": hold_s}
    s = load(write(tmp_path, raw))
    with caplog.at_level("WARNING"):
        check(s)
    text = " ".join(r.getMessage() for r in caplog.records)
    assert (f"devices.reactor.duration: a step of reactor lasts at least time_s (up to {hold_s} lab-s here)" in text) \
        is warned, text


def test_the_advice_taken_the_hold_the_workflow_gives_is_in_the_steps_duration(tmp_path, caplog):
    """The warning above says to give `duration.plus_param: time_s`, and a parameter the workflow's step gives (not
    the planner's box) was refused there as "not a parameter of chemistry.parameters". Taken now: no warning, and
    every step lasts its hold with no attempt timed out; a hold that is not lab seconds is refused by its field."""
    import twin

    raw = yaml.safe_load((ROOT / "scenarios" / "flaky_lab.yaml").read_text())
    del raw["chemistry"]["parameters"]["time_s"]
    raw["workflow"][1]["params"] = {"time_s": 20000}
    for spec in raw["devices"].values():
        spec.pop("faults", None)
    raw["campaign"].update(budget=3, planner="random")
    s = load(write(tmp_path, raw))
    with caplog.at_level("WARNING"):
        check(s)
    assert "lasts at least time_s" not in caplog.text, caplog.text
    out = twin.run(s)
    assert out.done == 3 and out.timed_out == 0 and out.lab_hours > 20000 / 3600, out
    for bad in (-5, "long", True, 1e12):  # 1e12: the campaign ran to max_lab_hours, its steps never ending
        raw["workflow"][1]["params"] = {"time_s": bad}
        with pytest.raises(ScenarioError) as refused:
            load(write(tmp_path, raw))
        assert "workflow.1.params.time_s" in str(refused.value) and "lab seconds, from 0 to 1e+07" in str(refused.value)
    raw["workflow"][1]["params"] = {}
    with pytest.raises(ScenarioError) as refused:
        load(write(tmp_path, raw))
    assert "nor one a workflow step on reactor gives" in str(refused.value), refused.value
    with pytest.raises(ScenarioError, match=r"plus_param: 'time_s' reaches 2e\+07 lab-s \(its high\)"):
        parse(qd_lab(**{"chemistry.parameters.time_s": {"low": 10, "high": 2e7},
                        "devices.synthesiser.duration.plus_param": "time_s"}))


@pytest.mark.parametrize("hold_s, refused", [(3000, ""), (20000, "workflow.1.params.time_s: 20000 is outside "
                                                            "devices.reactor.envelope.time_s [0, 7200]")])
def test_an_envelope_may_bound_what_the_workflows_step_gives(tmp_path, hold_s, refused):
    """An envelope on a parameter the step gives (the planner's box has none) was refused as "not a parameter of
    chemistry.parameters"; it is checked against the step's value, which the lab checks before it sends a step."""
    raw = yaml.safe_load((ROOT / "scenarios" / "flaky_lab.yaml").read_text())
    del raw["chemistry"]["parameters"]["time_s"]
    raw["devices"]["reactor"]["duration"].pop("plus_param")
    raw["devices"]["reactor"]["envelope"] = {"time_s": {"low": 0, "high": 7200}}
    raw["workflow"][1]["params"] = {"time_s": hold_s}
    if not refused:
        assert load(write(tmp_path, raw)).devices["reactor"].envelope["time_s"].high == 7200
        return
    with pytest.raises(ScenarioError) as said:
        load(write(tmp_path, raw))
    assert refused in str(said.value), said.value


@pytest.mark.parametrize("shared", [False, True])
def test_an_amount_per_a_parameter_the_workflows_step_gives_is_taken(shared):
    """`per: {volume_ml: 1}` where the step gives `params: {volume_ml: 4}` (not the planner's box) was refused as "no
    parameter of the chemistry" (and, in a shared lab, dropped from the campaign's amounts), though a step's own
    parameters are what the lab takes amounts by."""
    from twin.scenario.sharing import campaign_scenarios

    raw = yaml.safe_load(open("scenarios/shared_lab.yaml"))
    raw["consumables"] = {"solvent": {"unit": "mL", "level": 500, "used_by": {
        "synthesise": {"fixed": 1, "per": {"volume_ml": 1}}}}}
    dots = next(c for c in raw["campaigns"] if c["name"] == "dots")
    next(w for w in dots["workflow"] if w["step"] == "synthesise")["params"] = {"volume_ml": 4}
    if not shared:
        raw.update(chemistry=dots["chemistry"], workflow=dots["workflow"])
        del raw["campaigns"]
        lab = parse(raw, "lab.yaml")
        assert amount(lab.consumables["solvent"].used_by["synthesise"], {"volume_ml": 4}) == 5
        return
    per = {name: dict(s.consumables["solvent"].used_by["synthesise"].per)
           for name, s in campaign_scenarios(parse(raw, "shared.yaml")).items()}
    assert per[dots["name"]] == {"volume_ml": 1}, per


def test_the_typical_step_counts_a_duration_the_workflows_step_gives():
    """`plus_param: time_s` given by the workflow's step (not the planner's box): the objective's time unit added
    nothing for it, and weighed a lab of 2-hour holds as one of 25-minute steps."""
    import yaml
    from twin import time_scale

    raw = yaml.safe_load((Path(__file__).resolve().parents[2] / "scenarios" / "flaky_lab.yaml").read_text())
    del raw["chemistry"]["parameters"]["time_s"]
    raw["workflow"][1]["params"] = {"time_s": 7200}
    held = time_scale(parse(raw))
    raw["workflow"][1]["params"] = {"time_s": 0}
    assert held - time_scale(parse(raw)) == pytest.approx(7200 / len(raw["workflow"]))
