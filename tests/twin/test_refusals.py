"""Refusals are not faults: an infeasible request is abandoned at once, costs the device nothing, and teaches
the planner; a scenario's safe envelope stops such requests before they reach the device."""

import io
import json

import pytest
from rich.console import Console

from tests.conftest import qd_lab
from twin import Refused, StepResult
from twin.campaign.journal_read import read_events
from twin.cli.campaign_bar import waiting_for
from twin.core.errors import ScenarioError
from twin.runtime.lab import run
from twin.scenario import parse
from twin.view.report import render_summary

HOT_C = 270.0  # the measuring device's interlock: no sample made above this


class Interlocked:
    """A spectrometer whose cell refuses samples made hotter than HOT_C: infeasible, not broken."""

    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        if params["temperature_c"] > HOT_C:
            raise Refused(f"temperature_c {params['temperature_c']:.0f} is over the cell's {HOT_C:.0f}",
                          infeasible=True)
        await ctx.clock.sleep(60)
        return StepResult({"peak_nm": sample["peak_nm"]}, sample)

    async def safe_state(self):
        pass


def interlock_lab(**changes):
    return parse(qd_lab(**{"campaign.planner": "gp-bo", "campaign.budget": 30, "campaign.seed": 2,
                           "chemistry.targets": [{"name": "G", "outputs": {"peak_nm": {"value": 560, "tol": 5}}}],
                           **changes}))


def feasible_share(db, last):
    proposed = [json.loads(e["detail"]) for e in read_events(db, "experiment.proposed")][-last:]
    return sum(p["temperature_c"] <= HOT_C for p in proposed) / len(proposed)


@pytest.mark.parametrize("how", ["driver", "envelope"])
def test_an_interlock_costs_no_retries_no_quarantines_and_the_planner_learns_it(tmp_path, how):
    if how == "driver":
        lab = interlock_lab(**{"devices.spectrometer.driver": "tests.twin.test_refusals:Interlocked"})
    else:
        lab = interlock_lab(**{"devices.spectrometer.envelope": {"temperature_c": {"low": 200, "high": HOT_C}}})
    db = tmp_path / "j.db"
    s = run(lab, journal=db)
    infeasible = read_events(db, "experiment.abandoned")
    assert infeasible and all("infeasible" in e["detail"] for e in infeasible)
    assert s.quarantines == 0 and s.retried == 0
    assert s.abandoned == len(infeasible)
    if how == "envelope":
        assert s.failed_attempts == 0  # stopped before anything was sent: no step ran for nothing
        assert not [e for e in read_events(db, "attempt.dispatched") if e["device"].startswith("spectrometer")
                    and json.loads(e["detail"] or "{}").get("temperature_c", 0) > HOT_C]
    assert feasible_share(db, 10) >= 0.8  # GP-BO learnt where it may go


def test_a_busy_refusal_is_retried_and_does_not_count_as_an_attempt(tmp_path):
    class_path = "tests.twin.test_refusals:BusyOnce"
    s = run(parse(qd_lab(**{"devices.spectrometer.driver": class_path, "devices.spectrometer.instances": 1,
                            "campaign.budget": 3, "orchestrator.retry.max_attempts": 1})), journal=tmp_path / "j.db")
    assert s.done == 3 and s.abandoned == 0 and s.quarantines == 0
    # the summary says why there were more attempts than steps: each sample was answered "not now" once
    assert s.refused_now == 3 and s.attempts == 6 + 3
    out = io.StringIO()
    render_summary(s, Console(file=out, width=200))
    assert "9 (0 failed, 0 retried, 0 timed out, 3 answered 'not now' (sent again later, no attempt used))" in out.getvalue()


class BusyOnce(Interlocked):
    """Refuses each sample once ("only now": warming up), then measures it."""

    seen: set = set()

    async def run(self, step, params, sample, ctx):
        key = round(params["temperature_c"], 6)
        if key not in BusyOnce.seen:
            BusyOnce.seen.add(key)
            raise Refused("warming up", infeasible=False)
        await ctx.clock.sleep(60)
        return StepResult({"peak_nm": sample["peak_nm"]}, sample)


class AlwaysWarmingUp(Interlocked):
    async def run(self, step, params, sample, ctx):
        raise Refused("warming up", infeasible=False)


def test_a_step_refused_until_it_gives_up_is_counted_as_refused_and_says_by_whom(tmp_path):
    """The summary groups it as '<step>: refused' (it showed the whole reason as its kind, then again as its
    example)."""
    s = run(parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_refusals:AlwaysWarmingUp",
                            "devices.spectrometer.instances": 1, "campaign.budget": 2})), journal=tmp_path / "j.db")
    assert s.abandoned == 2 and s.abandoned_reasons == {"measure: refused": 2}, s.abandoned_reasons
    assert "refused" in s.abandoned_examples["measure: refused"]
    assert "last by spectrometer: warming up" in s.abandoned_examples["measure: refused"]


def test_a_box_that_misses_the_envelope_is_a_validation_error():
    with pytest.raises(ScenarioError, match=r"devices.spectrometer.envelope.temperature_c: .* does not overlap"):
        parse(qd_lab(**{"devices.spectrometer.envelope": {"temperature_c": {"low": 400, "high": 500}}}))
    with pytest.raises(ScenarioError, match=r"devices.spectrometer.envelope.pressure_bar: .* neither a parameter"):
        parse(qd_lab(**{"devices.spectrometer.envelope": {"pressure_bar": {"low": 1, "high": 2}}}))


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_a_lab_whose_only_spectrometer_is_gone_says_so_and_gives_up_instead_of_waiting(tmp_path, runtime):
    lab = parse(qd_lab(**{"devices.spectrometer.instances": 1, "campaign.budget": 20,
                          "devices.spectrometer.faults": {"mtbc_h": 0.05, "restart_s": 10_000_000},
                          "campaign.give_up_after_s": 7200, "campaign.max_lab_hours": 1000}))
    db = tmp_path / "j.db"
    lines = []  # what `twin run`'s progress line says, each time it is told
    s = run(lab, journal=db, runtime=runtime, on_progress=lambda core: lines.append(waiting_for(core.unavailable)))
    assert "[red]waiting: no usable spectrometer[/]" in lines and lines[0] == ""
    said = read_events(db, "devices.unavailable")
    assert said and json.loads(said[0]["detail"])["type"] == "spectrometer"
    gone = [e for e in read_events(db, "experiment.abandoned") if "no usable spectrometer" in e["detail"]]
    assert gone and s.pending == 0 and s.done + s.abandoned == s.proposed
    assert s.lab_hours < 10  # not the 1000 lab-h it would have waited


def test_an_answer_to_a_refused_attempt_never_counts_for_the_next_one(scenario_of):
    from tests.twin.test_core import msg, notes
    from tests.twin.test_operator import running
    from twin.campaign import Decided, TimerFired
    from twin.campaign.decisions import Assignment
    from twin.campaign.events import TimerKey, TimerKind
    from twin.core.messages import Kind

    core = running(scenario_of, **{"orchestrator.retry.max_attempts": 1})
    core.feed(msg(Kind.REJECTED, "synthesiser", "e0s0", 1, reason="warming up", infeasible=False))
    out = core.advance(5.0)
    assert notes(out, "task.refused")[0].attempt == 2  # the next attempt's number: the refused one is not reused
    core.feed(TimerFired(TimerKey(TimerKind.RETRY, "e0s0")))
    core.advance(70.0)
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    core.advance(70.0)
    assert ("e0s0", 2) in core.attempts and core.attempts[("e0s0", 2)].device == "synthesiser"
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 80.0}))  # the refused one
    out = core.advance(80.0)
    assert not notes(out, "attempt.done") and "e0s1" not in core.ready
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 2, outputs={}, sample={"t_made": 90.0}))
    out = core.advance(90.0)
    assert notes(out, "attempt.done") and "e0s1" in core.ready  # and one attempt allowed: the refusal did not count


class Moody:
    """A spectrometer that answers 'not now' to its 2nd-13th steps and 16th-26th, and measures the others."""

    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm"})

    def __init__(self, setup):
        self.calls = 0

    async def run(self, step, params, sample, ctx):
        self.calls += 1
        if 2 <= self.calls <= 13 or 16 <= self.calls <= 26:
            raise Refused("busy warming up", infeasible=False)
        await ctx.clock.sleep(60)
        return StepResult({"peak_nm": sample["peak_nm"]}, sample)

    async def safe_state(self):
        pass


def test_a_device_that_keeps_saying_not_now_is_an_alert_once_per_streak(tmp_path, caplog):
    """A stranger's MQTT instrument hung with its worker thread holding 'busy': 500 refusals and five experiments
    abandoned, and not a word until the summary."""
    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_refusals:Moody",
                          "devices.spectrometer.instances": 1, "campaign.budget": 5, "campaign.max_in_flight": 1,
                          "chemistry.targets": []}))
    with caplog.at_level("WARNING", logger="twin.alerts"):
        s = run(lab, journal=tmp_path / "j.db")
    alerts = read_events(tmp_path / "j.db", "device.refusing")
    assert [json.loads(a["detail"])["refusals"] for a in alerts] == [10, 10]  # the 2nd to 13th, the 16th to 26th
    assert all(a["device"] == "spectrometer" for a in alerts) and s.done == 5
    said = [r.getMessage() for r in caplog.records if r.name == "twin.alerts"]
    assert len(said) == 2 and "has answered 'not now' (busy warming up) to its last 10 steps" in said[0]
