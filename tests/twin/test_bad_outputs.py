"""Outputs and samples a driver hands back that the lab cannot use as they are: spectra that are not curves,
outputs that are not numbers, samples that cannot be carried; each is dropped or fails its attempt, said once, and
changes nothing else, alike on both runtimes."""

import json

import pytest

from tests.conftest import qd_lab
from twin.device.driver import StepResult
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run
from twin.scenario import parse


class OddSpectra:
    """A spectrometer whose spectra are JSON but not curves: the fifth of each kind is fine, the others not."""

    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm", "spectrum"})
    ODD = [{"y": ["high", "low"]}, {"y": 3.0}, {"y": [[1.0, 2.0], [3.0, 4.0]]}, {"start_nm": "blue", "y": [1.0]},
           {"x": [1.0, 2.0]}, {"y": [1.0, None, 2.0]}, {"y": []}, "a spectrum", {"y": [1e308, -1e308, 0.5]}]

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        self.n += 1
        spectrum = self.ODD[self.n % len(self.ODD)] if self.n % 5 else {"start_nm": 400.0, "step_nm": 2.0,
                                                                          "y": [0.0, 0.5, 1.0, 0.5]}
        return StepResult({"peak_nm": 404.0, "spectrum": spectrum}, sample)

    async def safe_state(self):
        pass


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_spectra_that_are_not_curves_are_not_drawn_and_change_nothing_else(tmp_path, runtime):
    """The recorder skips what it cannot draw: the campaign runs as it does unrecorded, the good spectra are drawn."""
    from tests.rrd import read_rrd
    from twin.view.watch import RecordOptions

    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_outputs:OddSpectra",
                          "devices.spectrometer.instances": 1,
                          "campaign.budget": 20}))
    plain = run(lab, journal=tmp_path / "plain.db", runtime=runtime)
    drawn = run(lab, journal=tmp_path / "drawn.db", runtime=runtime, record=RecordOptions(save=tmp_path / "r.rrd"))
    assert drawn.done == plain.done == 20 and drawn.attempts == plain.attempts == 40 and not drawn.failed_attempts
    strips = [r["LineStrips2D:strips"][0] for r in read_rrd(tmp_path / "r.rrd")["spectra/measurement"]]
    good = [[400.0, 300.0], [402.0, 150.0], [404.0, 0.0], [406.0, 150.0]]
    assert strips.count(good) == 4  # experiments 5, 10, 15, 20
    assert all(s == good or len(s) == 3 for s in strips), strips  # [1e308, -1e308, .5] at infinity, [1, None, 2] a gap


class OddNumbers:
    """A spectrometer whose peak comes as null (a NaN), a string, a boolean, or a number, in turn; its telemetry
    has a NaN reading every other time."""

    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm"})
    PEAKS = [float("nan"), "630", True, 630.0]

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        ctx.telemetry({"lamp_k": float("nan") if self.n % 2 else 300.0})
        self.n += 1
        return StepResult({"peak_nm": self.PEAKS[(self.n - 1) % 4]}, sample)

    async def safe_state(self):
        pass


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_an_output_that_is_not_a_number_is_never_scored_and_is_said_once(tmp_path, runtime, caplog):
    """null, "630" and true are not 630: no target is met by them (true once scored as 1), the first is noted and
    logged naming the output, and a NaN telemetry reading is an invalid message on either runtime."""
    import logging

    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_outputs:OddNumbers",
                          "devices.spectrometer.instances": 1, "campaign.budget": 8, "campaign.max_in_flight": 1,
                          "chemistry.targets": [{"name": "one", "outputs": {"peak_nm": {"value": 1, "tol": 5}}},
                                                {"name": "R", "outputs": {"peak_nm": {"value": 630, "tol": 5}}}]}))
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == 8 and "one" not in summary.targets_met_h and "R" in summary.targets_met_h
    noted = read_events(tmp_path / "j.db", "output.unscored")
    assert len(noted) == 1 and "peak_nm = null is not a number" in noted[0]["detail"]
    assert [r for r in caplog.records if "output.unscored" in r.getMessage()]
    assert summary.invalid_messages == 4  # the telemetry of steps 2, 4, 6, 8
    invalid = read_events(tmp_path / "j.db", "message.invalid")
    assert len(invalid) == 4 and all("readings" in e["detail"] and e["device"] == "spectrometer" for e in invalid)


def test_a_target_scores_only_finite_numbers():
    from twin.scenario.targets import score, unscorable

    target = parse(qd_lab()).chemistry.targets[0]  # R: peak_nm 630 ± 5
    assert score({"peak_nm": 630}, target) == 0 and score({"peak_nm": 640.0}, target) == 1.0
    for odd in (None, "630", True, float("nan"), float("inf")):
        assert score({"peak_nm": odd}, target) == float("inf"), odd
    assert unscorable({"peak_nm": "630", "other": "x"}, [target]) == {"peak_nm": "630"}
    assert unscorable({"intensity": 1.0}, [target]) == {}  # missing is not listed: not every workflow measures it


class OddSample:
    """A synthesiser whose samples are not what the lab can carry: in turn, t_made a word, null, a NaN, a list,
    far in the future, and a sample that is a number; every seventh is fine."""

    capabilities = frozenset({"synthesise"})
    SAMPLES = [{"t_made": "yesterday"}, {"t_made": None}, {"t_made": float("nan")}, {"t_made": [1]},
               {"t_made": 1e300}, 5]

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        self.n += 1
        if self.n % 7 == 0:
            return StepResult({}, {"kind": "qd", "peak_nm": 630.0, "fwhm_nm": 30.0, "amplitude": 1.0,
                                   "t_made": ctx.clock.now()})
        return StepResult({}, self.SAMPLES[self.n % 7 - 1])

    async def safe_state(self):
        pass


def test_a_result_whose_sample_the_lab_cannot_carry_fails_its_attempt_alike_on_both_runtimes(tmp_path):
    """Once it stopped the campaign (float(None)); now each is a failed attempt naming the device and the field,
    retried like any other, and the two runtimes agree to the attempt. A sample that is no mapping (a number) was
    an invalid message, dropped, and its step waited out its deadline: the driver's error now, at once."""
    lab = parse(qd_lab(**{"devices.synthesiser.driver": "tests.twin.test_bad_outputs:OddSample",
                          "campaign.budget": 6, "orchestrator.quarantine_after": 100}))
    fast = run(lab, journal=tmp_path / "fast.db", runtime="auto")
    slow = run(lab, journal=tmp_path / "slow.db", runtime="asyncio")
    assert fast.done + fast.abandoned == 6 and fast.done >= 1
    for field in ("done", "abandoned", "attempts", "failed_attempts", "invalid_messages", "timed_out"):
        assert getattr(fast, field) == getattr(slow, field), field
    assert fast.invalid_messages == 0 and fast.timed_out == 0
    reasons = [json.loads(e["detail"])["reason"] for e in read_events(tmp_path / "fast.db", "attempt.failed")
               if json.loads(e["detail"])["code"] == "driver_error"]
    assert {"'yesterday'", "'None'", "'[1]'", "after the lab's time now"} <= {
        w for r in reasons for w in ("'yesterday'", "'None'", "'[1]'", "after the lab's time now") if w in r}
    cannot_carry = [r for r in reasons if r.startswith("synthesiser returned a result the lab cannot use")]
    no_mapping = [r for r in reasons if "OddSample.run() returned a sample of type int 5: a sample is a mapping" in r]
    assert cannot_carry and no_mapping and len(cannot_carry) + len(no_mapping) == len(reasons)


def test_what_a_result_must_hold():
    from twin.campaign.results import problem

    assert problem({"outputs": {}, "sample": {"t_made": 10.0}}, now=20.0) == ""
    assert problem({"outputs": {}, "sample": None}, now=0.0) == ""
    assert problem({"outputs": {}, "sample": {"kind": "qd"}}, now=0.0) == ""  # no t_made: made when it arrives
    assert "t_made" in problem({"outputs": {}, "sample": {"t_made": True}}, now=0.0)
    assert "t_made" in problem({"outputs": {}, "sample": {"t_made": float("inf")}}, now=0.0)
    assert "after the lab's time" in problem({"outputs": {}, "sample": {"t_made": 100.0}}, now=20.0)
    assert "JSON object" in problem({"outputs": [1], "sample": None}, now=0.0)


class ListedOutputs:
    capabilities = frozenset({"measure"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        return StepResult([sample["peak_nm"]] if sample else None, sample)

    async def safe_state(self):
        pass


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_outputs_that_are_no_mapping_fail_the_step_at_once_as_the_drivers_error(tmp_path, runtime):
    """They were an invalid message, dropped: each step waited out its deadline, then was retried, until the
    device was quarantined."""
    from twin import driver_setup, run_step
    from twin.core.errors import DriverError

    with pytest.raises(DriverError, match=r"ListedOutputs.run\(\) returned outputs of type NoneType None: "
                                          r"outputs are what was measured, by name: "
                                          r"StepResult\(\{name: value, ...\}, sample\)"):
        run_step(ListedOutputs(driver_setup()), "measure", {}, None)
    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_outputs:ListedOutputs",
                          "campaign.budget": 2}))
    summary = run(lab, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.timed_out == 0 and summary.invalid_messages == 0 and summary.abandoned == 2
    failed = [json.loads(e["detail"]) for e in read_events(tmp_path / "j.db", "attempt.failed")]
    assert failed and all(f["code"] == "driver_error" and "returned outputs of type list" in f["reason"]
                          for f in failed)


class RenamedPeak:
    """A spectrometer whose driver calls the peak "peak", where the targets read peak_nm."""

    capabilities = frozenset({"measure"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        await ctx.clock.sleep(60)
        return StepResult({"peak": 630.0, "fwhm_nm": 30.0}, sample)

    async def safe_state(self):
        pass


class SynthesisOnly:
    """Proposes experiments whose route only synthesises: they measure nothing, on purpose."""

    def __init__(self, seed):
        import random
        self.rng = random.Random(seed)

    def propose(self, n, history, pending):
        from twin import Proposal, RouteStep

        return [Proposal({"concentration_mm": 10.0, "temperature_c": self.rng.uniform(220, 320), "time_s": 60.0},
                         route=[RouteStep("synthesise", "synthesiser")]) for _ in range(n)]


@pytest.mark.parametrize("runtime", ["auto", "asyncio"])
def test_a_target_output_the_workflow_never_brings_is_said_once_with_what_it_brought(tmp_path, runtime):
    """An instrument that names its peak otherwise ran a whole campaign to "best score inf" without a word; an
    experiment that ran the workflow as written without a target's output is now noted once, naming the output and
    what the steps gave. A route the planner chose that measures nothing is not."""
    renamed = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_bad_outputs:RenamedPeak",
                              "campaign.budget": 4}))
    summary = run(renamed, journal=tmp_path / "renamed.db", runtime=runtime)
    assert summary.done == 4 and not summary.targets_met_h
    noted = [e["detail"] for e in read_events(tmp_path / "renamed.db", "output.unscored")]
    assert len(noted) == 1 and "peak_nm, which a target reads, is not among the outputs" in noted[0]
    assert "(they gave: diameter_nm, fwhm_nm, peak)" in noted[0]
    routed = parse(qd_lab(**{"campaign.planner": "tests.twin.test_bad_outputs:SynthesisOnly", "campaign.budget": 3}))
    assert run(routed, journal=tmp_path / "routed.db", runtime=runtime).done == 3
    assert read_events(tmp_path / "routed.db", "output.unscored") == []
