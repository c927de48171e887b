"""A workflow that every experiment fails in passes each field's check: a few trial experiments on the twin find
it before the campaign does (docs/operating.md, "Trial experiments")."""

import logging
from pathlib import Path

import yaml

from tests.conftest import qd_lab, twin_cli
from twin import DriverError, StepResult
from twin.runtime.checks import validate_file
from twin.runtime.trial import trial_warnings
from twin.scenario import load

ROOT = Path(__file__).resolve().parents[2]
REACT = "  - {step: react, device: reactor}\n"


def said(res) -> str:
    return " ".join(res.output.split())


def test_a_workflow_that_measures_a_feed_is_warned_of_by_validate_and_before_a_live_run(tmp_path, caplog):
    """A thin-film lab written as flaky_lab is, without its reactor's react: the spectrometer cannot measure the
    synthesiser's catalyst feed, so each of 40 experiments was abandoned at its last step; `twin validate` passed
    it, and a live run found it an experiment's length of lab time later."""
    text = (ROOT / "scenarios" / "flaky_lab.yaml").read_text()
    assert REACT in text
    (tmp_path / "ok.yaml").write_text(text)
    (tmp_path / "noreact.yaml").write_text(text.replace(REACT, ""))
    kept = twin_cli("validate", tmp_path / "ok.yaml")
    assert kept.exit_code == 0 and "warning" not in said(kept), said(kept)
    res = twin_cli("validate", tmp_path / "noreact.yaml")
    assert res.exit_code == 0, said(res)  # a warning: a device may refuse some parameters and not others
    assert ("noreact.yaml: warning: workflow: 3 trial experiments on the twin (random parameters from the "
            "chemistry's ranges, faults off, virtual clock) were all abandoned (spectrometer-") in said(res), said(res)
    assert ("refused 'measure': the spectrometer cannot measure a sample of kind 'feed' (a catalyst's feed, which a "
            "reactor's react makes a reaction; it measures crude, film, purified, qd, reaction)") in said(res)
    assert f"`twin run {tmp_path / 'noreact.yaml'} --clock virtual` shows where" in said(res), said(res)
    for clock, warned in ((["--clock", "scaled", "--speed", "2000"], True), ([], False)):  # a virtual run is itself
        caplog.clear()                                                                       # the trial
        run = twin_cli("run", tmp_path / "noreact.yaml", *clock, "--bus", "memory", "--budget", "1", "--json",
                       "--journal", tmp_path / f"{bool(clock)}.db")
        assert run.exit_code == 0, run.stderr
        assert any("3 trial experiments on the twin" in r.getMessage() for r in caplog.records) == warned, clock


class Jammed:
    """A third party's dispenser whose every step raises (its firmware was never flashed)."""

    capabilities = frozenset({"dispense"})
    makes_sample = frozenset({"dispense"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        raise DriverError("nozzle jammed")

    async def safe_state(self):
        pass


class Dispenser(Jammed):
    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        return StepResult({}, {"kind": "qd", "peak_nm": 500.0, "fwhm_nm": 30.0, "amplitude": 1.0,
                               "t_made": ctx.clock.now()})


def test_a_driver_that_fails_every_step_is_warned_of_and_one_that_works_is_not(tmp_path, caplog):
    for name, warned in (("Jammed", True), ("Dispenser", False)):
        lab = qd_lab(**{"devices.synthesiser.driver": f"tests.twin.test_trial:{name}",
                        "devices.synthesiser.steps": ["dispense"],
                        "workflow": [{"step": "dispense", "device": "synthesiser"},
                                     {"step": "measure", "device": "spectrometer"}]})
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump(lab))
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            validate_file(path)
        warnings = [r.getMessage() for r in caplog.records if "trial experiments" in r.getMessage()]
        assert bool(warnings) == warned, (name, warnings)
        if warned:
            assert "failed" in warnings[0] and "nozzle jammed" in warnings[0], warnings


def test_a_shared_labs_campaign_is_tried_on_its_own_and_named(tmp_path):
    raw = yaml.safe_load((ROOT / "scenarios" / "shared_lab.yaml").read_text())
    raw["campaigns"][1]["workflow"] = [w for w in raw["campaigns"][1]["workflow"] if w["step"] != "react"]
    path = tmp_path / "shared.yaml"
    path.write_text(yaml.safe_dump(raw))
    warnings = trial_warnings(load(path), path)
    assert len(warnings) == 1 and warnings[0].startswith("campaigns.1 (catalyst): workflow: 3 trial experiments"), \
        warnings
    assert trial_warnings(load(ROOT / "scenarios" / "shared_lab.yaml"), path) == []


class Midpoints:
    """A third party's planner whose experiments run the workflow as written, and which says so."""

    plans_routes = False

    def __init__(self, parameters):
        self.box = parameters

    def propose(self, n, history, pending):
        from twin import Proposal

        return [Proposal({k: (p.low + p.high) / 2 for k, p in self.box.items()}) for _ in range(n)]


class Unsaid(Midpoints):
    """The same planner, not saying whether it plans routes of its own: the trial cannot stand in for it."""

    plans_routes = None


def test_a_planner_of_its_own_is_tried_where_it_says_it_runs_the_workflow_as_written(tmp_path):
    text = (ROOT / "scenarios" / "flaky_lab.yaml").read_text().replace(REACT, "")
    for planner, tried in (("Midpoints", True), ("Unsaid", False)):
        path = tmp_path / f"{planner}.yaml"
        path.write_text(text.replace("planner: random", f"planner: tests.twin.test_trial:{planner}"))
        assert bool(trial_warnings(load(path), path)) == tried, planner


class Chatty(Dispenser):
    """A third party's driver that prints as it is made and as it runs (a stranger's debugging)."""

    def __init__(self, setup):
        print("dispenser ready")

    async def run(self, step, params, sample, ctx):
        print("dispensing", params)
        return await super().run(step, params, sample, ctx)


def test_validate_json_stays_one_document_when_a_driver_prints(tmp_path):
    import json

    lab = qd_lab(**{"devices.synthesiser.driver": "tests.twin.test_trial:Chatty",
                    "devices.synthesiser.steps": ["dispense"],
                    "workflow": [{"step": "dispense", "device": "synthesiser"},
                                 {"step": "measure", "device": "spectrometer"}]})
    path = tmp_path / "chatty.yaml"
    path.write_text(yaml.safe_dump(lab))
    res = twin_cli("validate", path, "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["files"][0]["ok"] is True, res.stdout
    assert "dispensing" not in res.stdout and "dispenser ready" not in res.stdout
