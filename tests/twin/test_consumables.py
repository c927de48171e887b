"""Consumables: levels never go negative, a step that needs more than is left waits (one depletion note per item
until a refill), a refill — an operator's, or a simulated one in virtual time — lets it go on, and nothing is lost."""

import json

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from devices.spectrometer import Spectrometer
from tests.conftest import qd_lab
from tests.twin.test_core import QD, msg, notes
from tests.twin.test_operator import op, running
from twin.campaign import Decided, Operator, Proposed
from twin.campaign.consumables import amount
from twin.campaign.decisions import Assignment, Proposal
from twin.campaign.journal_read import read_events
from twin import Refused
from twin.core.errors import ScenarioError
from twin.core.messages import Kind
from twin.runtime.checks import check
from twin.runtime.lab import run
from twin.scenario import parse
from twin.scenario.sharing import campaign_scenarios

P = {"concentration_mm": 5, "temperature_c": 250, "time_s": 60}


def stocked(precursor, vials, refill_after=None, per=0.1, fixed=1.0, vials_per_spectrometer=False):
    c = {"precursor": {"unit": "mL", "level": precursor, "reorder_at": precursor / 2,
                       "used_by": {"synthesise": {"fixed": fixed, "per": {"concentration_mm": per}}}},
         "vials": {"unit": "vials", "level": vials, "used_by": {"measure": 1}}}
    if vials_per_spectrometer:  # each of the two spectrometers has its own rack of vials
        c["vials"]["device"] = "spectrometer"
    if refill_after is not None:
        for item in c.values():
            item["simulate_refill"] = {"after_s": refill_after}
    return c


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(precursor=st.floats(0.5, 30), vials=st.integers(1, 10), fixed=st.floats(0, 4), per=st.floats(0, 0.4),
       refill_after=st.one_of(st.none(), st.floats(0, 5000)), seed=st.integers(0, 1000),
       vials_per_spectrometer=st.booleans())
def test_levels_never_go_negative_and_every_depletion_pauses_its_work_once(tmp_path, precursor, vials, fixed, per,
                                                                            refill_after, seed,
                                                                            vials_per_spectrometer):
    s = parse(qd_lab(**{"campaign.budget": 10, "campaign.seed": seed,
                        "consumables": stocked(precursor, vials, refill_after, per, fixed, vials_per_spectrometer)}),
              "lab.yaml")
    db = tmp_path / f"c{seed}.db"
    summary = run(s, journal=db)
    assert summary.done + summary.abandoned + summary.pending == summary.proposed  # nothing lost
    events = read_events(db)
    full = {"precursor": precursor}
    full.update({f"vials@spectrometer-{i}": float(vials) for i in (1, 2)} if vials_per_spectrometer
                else {"vials": float(vials)})
    assert set(summary.consumables) == set(full)
    level = dict(full)
    depleted: dict[str, set[str]] = {k: set() for k in full}  # an episode's tasks that found the stock short
    episodes = dict.fromkeys(full, 0)
    starved: set[str] = set()  # tasks waiting for a refill (every stock they could use short)
    out_since: dict[str, float] = {}
    out_s = dict.fromkeys(full, 0.0)  # how long each stock was out, from its depletion note to its refill
    for e in events:
        d = json.loads(e["detail"]) if e["detail"] else {}
        if e["kind"] == "attempt.dispatched":
            for item, n in d.get("used", {}).items():
                assert n <= level[item] + 1e-6, f"{e['task']} took {n} of {item} with {level[item]} left"
                level[item] -= n
                assert abs(d["left"][item] - max(level[item], 0)) < 1e-5 and d["left"][item] >= 0
                if "@" in item:  # an instance's own stock: the step ran on that instance, never on a dry one
                    assert item == f"vials@{e['device']}" and not depleted[item]
            assert e["task"] not in starved, f"{e['task']} was dispatched while the item it waits for was short"
        elif e["kind"] == "consumable.depleted":
            item = d["item"]
            assert not depleted[item], f"a second depletion note for {item} before a refill"
            assert d["needed"] > d["level"]
            depleted[item].add(e["task"])
            episodes[item] += 1
            out_since[item] = e["t_lab"]
            if "@" not in item or all(depleted[k] for k in full if "@" in k):
                starved.add(e["task"])
        elif e["kind"] == "consumable.returned":  # a step refused: it never ran
            level[d["item"]] = min(full[d["item"]], level[d["item"]] + d["amount"])
            assert abs(d["level"] - level[d["item"]]) < 1e-5
        elif e["kind"] == "consumable.refilled":
            item = d["item"]
            level[item] = full[item] if d["amount"] is None else level[item] + d["amount"]
            assert d["who"] == "simulated operator" and refill_after is not None
            depleted[item] = set()
            starved = set()
            out_s[item] += e["t_lab"] - out_since.pop(item, e["t_lab"])
        elif e["kind"] == "campaign.summary":
            for item, since in out_since.items():  # out still at the end
                out_s[item] += e["t_lab"] - since
    assert all(c["left"] >= 0 for c in summary.consumables.values())
    assert {k: c["out_h"] for k, c in summary.consumables.items()} == pytest.approx(
        {k: v / 3600 for k, v in out_s.items()}, abs=1e-5)
    if refill_after is None and sum(episodes.values()):
        assert any(c["short"] for c in summary.consumables.values())


def test_a_short_step_waits_for_the_operators_refill_and_the_lab_goes_on(scenario_of):
    core = running(scenario_of, **{"consumables": stocked(100, 1), "campaign.budget": 3})
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0}))
    core.advance(60.0)
    core.feed(Decided([Assignment("e0s1", "spectrometer-1"), Assignment("e1s0", "synthesiser")]))
    core.advance(60.0)
    assert core.stocks.items["vials"].level == 0
    core.feed(msg(Kind.RESULT, "synthesiser", "e1s0", 1, outputs={}, sample={"t_made": 120.0}))
    out = core.advance(120.0)
    (short,) = notes(out, "consumable.depleted")
    assert short.detail == {"item": "vials", "level": 0, "unit": "vials", "needed": 1.0, "stocks": 1}
    assert short.task == "e1s1"
    assert "e1s1" in core.starved and "e1s1" not in core.ready
    assert core.short_of == ["vials"]  # what the progress line says the lab waits for
    core.feed(Operator("refill", "alice", "r1", item="gold"))
    out = core.advance(130.0)
    assert "there is no consumable 'gold' (this lab's: precursor, vials)" in notes(out, "operator.refused")[0].detail["why"]
    core.feed(Operator("refill", "alice", "r2", item="vials", amount=5))
    out = core.advance(140.0)
    assert notes(out, "consumable.refilled")[0].detail == {"item": "vials", "amount": 5, "level": 5.0,
                                                           "unit": "vials", "who": "alice"}
    assert "e1s1" in core.ready and not core.starved and not core.stocks.items["vials"].depleted
    assert core.short_of == []


@pytest.mark.parametrize("began", [False, True])
def test_a_step_refused_gives_back_what_its_dispatch_took_unless_it_had_begun(scenario_of, began):
    core = running(scenario_of, **{"consumables": stocked(100, 3), "campaign.budget": 2,
                                   "devices.spectrometer.cost": 5})
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0}))
    core.advance(60.0)
    core.feed(Decided([Assignment("e0s1", "spectrometer-1")]))
    core.advance(60.0)
    vials = core.stocks.items["vials"]
    assert (vials.level, vials.used) == (2, 1) and core.cost == 5
    core.feed(msg(Kind.REJECTED, "spectrometer-1", "e0s1", 1, reason="warming up", infeasible=False,
                  **({"began": True} if began else {})))
    out = core.advance(70.0)
    assert notes(out, "task.refused")  # sent again later, as any "not now"
    if began:  # a step a stop cancelled, sent again at the resume: it had used its vial
        assert not notes(out, "consumable.returned") and (vials.level, vials.used) == (2, 1) and core.cost == 5
    else:
        (back,) = notes(out, "consumable.returned")
        assert back.detail == {"item": "vials", "amount": 1, "level": 3.0, "unit": "vials"} and back.task == "e0s1"
        assert (vials.level, vials.used) == (3, 0) and core.cost == 0  # nor did it cost the spectrometer's time


class Warming(Spectrometer):
    """A spectrometer that answers "not now" (warming up) to its first three steps."""

    refusals = 0

    async def run(self, step, params, sample, ctx):
        if Warming.refusals < 3:
            Warming.refusals += 1
            raise Refused("warming up", infeasible=False)
        return await super().run(step, params, sample, ctx)


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_a_device_answering_not_now_uses_up_no_vials_and_costs_nothing(tmp_path, runtime):
    """Three "not now" answers had taken three vials for measurements that never ran: 8 used for 5 done; and each
    was charged the spectrometer's cost per attempt."""
    s = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_consumables:Warming",
                        "devices.spectrometer.instances": 1, "campaign.budget": 5, "devices.spectrometer.cost": 7,
                        "consumables": {"vials": {"unit": "vials", "level": 10, "used_by": {"measure": 1}}}}))
    Warming.refusals = 0
    summary = run(s, journal=tmp_path / "j.db", runtime=runtime)
    assert summary.done == 5 and summary.refused_now == 3 and summary.cost == 5 * 7
    assert summary.consumables["vials"]["used"] == 5 and summary.consumables["vials"]["left"] == 5
    from twin.campaign.journal_read import read_run
    from twin.tools.export import consumable_rows

    db = tmp_path / "j.db"
    rows = [r for r in consumable_rows(read_run(db), read_events(db)) if r["why"] != "start"]
    assert sum(r["change"] for r in rows) == -5 and rows[-1]["level"] == 5  # twin export's table says the same
    assert sum(r["why"].startswith("returned") for r in rows) == 3


def no_more_experiments(core, out, t):
    """Answer the planner's question, if it asked one, with nothing: the scheduler's comes next."""
    if [a for a in out if getattr(a, "what", "") == "plan"]:
        core.feed(Proposed([]))
        out = core.advance(t)
    return out


def test_an_instance_whose_own_stock_is_short_gets_no_step_and_the_other_takes_it(scenario_of):
    c = stocked(100, 1, vials_per_spectrometer=True)
    # a live clock: the refused answer below leaves the lab idle, which in virtual time would end it (a stall)
    core = running(scenario_of, **{"consumables": c, "campaign.budget": 3, "clock": {"mode": "scaled", "speed": 3600}})
    assert set(core.stocks.items) == {"precursor", "vials@spectrometer-1", "vials@spectrometer-2"}
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 60.0}))
    core.advance(60.0)
    core.feed(Decided([Assignment("e0s1", "spectrometer-1"), Assignment("e1s0", "synthesiser")]))
    out = core.advance(60.0)
    (sent,) = notes(out, "attempt.dispatched")[:1]
    assert sent.detail["used"] == {"vials@spectrometer-1": 1.0}
    assert sent.detail["left"] == {"vials@spectrometer-1": 0}
    core.feed(msg(Kind.RESULT, "spectrometer-1", "e0s1", 1, outputs={"peak_nm": 520.0, "fwhm_nm": 30.0}))
    core.feed(msg(Kind.RESULT, "synthesiser", "e1s0", 1, outputs={}, sample={"t_made": 120.0}))
    out = core.advance(120.0)
    assert core.devices["spectrometer-1"].free
    (dry,) = notes(out, "consumable.depleted")  # found by the next step, which can still go to spectrometer-2
    assert dry.detail["item"] == "vials@spectrometer-1" and dry.task == "e1s1" and "e1s1" in core.ready
    out = no_more_experiments(core, out, 120.0)
    (ask,) = [a for a in out if getattr(a, "what", "") == "schedule"]
    (step,) = [r for r in ask.view.ready if r.task == "e1s1"]
    assert "spectrometer-1" in step.avoid  # every scheduler, rule or policy, keeps off the dry instance
    core.feed(Decided([Assignment("e1s1", "spectrometer-1")]))
    out = core.advance(120.0)
    (invalid,) = notes(out, "scheduler.invalid")
    assert "spectrometer-1" in invalid.detail and "its own stock" in invalid.detail
    assert "e1s1" in core.ready and not notes(out, "attempt.dispatched")  # nothing valid: the pass ends
    assert "answered only pairs that cannot be carried out" in notes(out, "scheduler.stalled")[0].detail
    out = op(core, "refill", 130.0, item="vials@spectrometer-2", amount=4)  # one instance's stock
    (one,) = notes(out, "consumable.refilled")
    assert one.detail["item"] == "vials@spectrometer-2" and one.detail["level"] == 5.0
    assert core.stocks.items["vials@spectrometer-1"].depleted  # the other is still short
    out = no_more_experiments(core, out, 130.0)
    core.feed(Decided([Assignment("e1s1", "spectrometer-2")]))
    out = core.advance(130.0)
    assert notes(out, "attempt.dispatched")[0].detail["used"] == {"vials@spectrometer-2": 1.0}
    out = op(core, "refill", 140.0, item="vials")  # the item: every instance's stock, to its starting level
    assert sorted((n.detail["item"], n.detail["level"]) for n in notes(out, "consumable.refilled")) == [
        ("vials@spectrometer-1", 1.0), ("vials@spectrometer-2", 1.0)]
    assert not any(st.depleted for st in core.stocks.items.values())


def test_every_instance_short_makes_the_step_wait_and_virtual_time_says_who_must_refill(tmp_path):
    s = parse(qd_lab(**{"campaign.budget": 8, "consumables": {
        "vials": {"unit": "vials", "level": 2, "device": "spectrometer", "used_by": {"measure": 1}}}}), "lab.yaml")
    summary = run(s, journal=tmp_path / "j.db")
    assert summary.done == 4 and summary.pending >= 1 and summary.done + summary.pending == summary.proposed
    assert {k: v["left"] for k, v in summary.consumables.items()} == {"vials@spectrometer-1": 0,
                                                                       "vials@spectrometer-2": 0}
    assert "vials@spectrometer-1, vials@spectrometer-2" in summary.stopped
    used = [(e["device"], json.loads(e["detail"])["used"]) for e in read_events(tmp_path / "j.db")
            if e["kind"] == "attempt.dispatched" and e["device"].startswith("spectrometer")]
    assert sorted(d for d, _ in used) == ["spectrometer-1"] * 2 + ["spectrometer-2"] * 2
    assert all(u == {f"vials@{d}": 1.0} for d, u in used)


def test_crossing_the_reorder_point_says_when_it_runs_out(scenario_of):
    core, _ = __import__("tests.twin.test_core", fromlist=["started"]).started(
        scenario_of, **{"campaign.budget": 2, "consumables": stocked(10, 5, fixed=3, per=0)})
    from twin.campaign import Proposed
    from twin.campaign.decisions import Proposal

    core.feed(Proposed([Proposal(P), Proposal(P)]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "synthesiser")]))
    core.advance(0.0)
    core.feed(msg(Kind.RESULT, "synthesiser", "e0s0", 1, outputs={}, sample={"t_made": 600.0}))
    core.advance(600.0)
    core.feed(Decided([Assignment("e1s0", "synthesiser")]))
    out = core.advance(600.0)
    (low,) = notes(out, "consumable.low")
    assert low.detail["item"] == "precursor" and low.detail["level"] == 4.0
    assert low.detail["runs_out_in_s"] == pytest.approx(4.0 / (6.0 / 600.0))


@pytest.mark.parametrize("change, words", [
    ({"consumables": {"x": {"level": 5, "used_by": {"bake": 1}}}}, "consumables.x.used_by.bake: 'bake' is no device"),
    ({"consumables": {"x": {"level": -1, "used_by": {"measure": 1}}}}, "consumables.x.level"),
    ({"consumables": {"x": {"level": 5, "used_by": {}}}}, "consumables.x.used_by"),
    ({"consumables": {"x": {"level": 5, "used_by": {"measure": {"fixed": -2}}}}}, "fixed"),
    ({"consumables": {"x": {"level": 5, "device": "oven", "used_by": {"measure": 1}}}},
     "consumables.x.device: 'oven' is not a device type"),
    ({"consumables": {"x": {"level": 5, "device": "synthesiser", "used_by": {"measure": 1}}}},
     "consumables.x.used_by.measure: 'measure' does not run on a synthesiser"),
    ({"consumables": {"x": {"level": 5, "used_by": {"synthesise": {"fixed": 1, "per": {"temperature_c": -0.1}}}}}},
     r"consumables.x.used_by.synthesise: at temperature_c = 320 a step would use -31 units .*raise fixed to at "
     r"least 32"),
    ({"consumables": {"x": {"level": 5, "used_by": {"synthesise": {"per": {"stir_rpm": 0.1}}}}}},
     r"consumables.x.used_by.synthesise.per.stir_rpm: 'stir_rpm' is no parameter of the chemistry nor of a "
     r"workflow step \(concentration_mm, temperature_c, time_s\)"),
])
def test_a_consumable_that_cannot_work_is_refused_with_its_field(change, words):
    with pytest.raises(ScenarioError, match=words):
        parse(qd_lab(**change), "lab.yaml")


def test_an_amount_per_parameter_may_fall_with_it_while_no_step_uses_less_than_nothing():
    use = {"fixed": 7, "per": {"concentration_mm": 0.1, "time_s": -0.01}}  # at least 7 + 0.1 - 6 = 1.1
    lab = parse(qd_lab(consumables={"x": {"level": 50, "used_by": {"synthesise": use}}}), "lab.yaml")
    assert amount(lab.consumables["x"].used_by["synthesise"], {"concentration_mm": 1, "time_s": 600}) == \
        pytest.approx(1.1)


def test_a_shared_lab_takes_an_amount_per_parameter_only_from_the_campaigns_that_have_it():
    raw = yaml.safe_load(open("scenarios/shared_lab.yaml"))
    raw["consumables"] = {"precursor": {"level": 500, "used_by": {
        "synthesise": {"fixed": 2, "per": {"concentration_mm": 0.2}},  # only the dots campaign has it
        "prepare": {"fixed": 1, "per": {"temperature_k": 0.01}}}}}  # only the catalyst campaign
    per = {name: {step: dict(use.per) for step, use in s.consumables["precursor"].used_by.items()}
           for name, s in campaign_scenarios(parse(raw, "shared.yaml")).items()}
    assert per == {"dots": {"synthesise": {"concentration_mm": 0.2}, "prepare": {}},
                   "catalyst": {"synthesise": {}, "prepare": {"temperature_k": 0.01}}}
    raw["consumables"]["precursor"]["used_by"]["prepare"]["per"] = {"temperature_kk": 0.01}
    with pytest.raises(ScenarioError, match="per.temperature_kk: 'temperature_kk' is no parameter of the chemistry nor of a "
                                            r"workflow step \(concentration_mm, temperature_c, temperature_k, time_s\)"):
        parse(raw, "shared.yaml")


def test_fail_over_never_avoids_the_only_instance_with_stock_left(scenario_of):
    """spectrometer-1 is out of its own vials, spectrometer-2 failed the step and was restocked: the retry must
    be offered spectrometer-2 (fail-over avoids a failed instance only while another usable one exists)."""
    from tests.twin.test_core import SetTimer, TimerFired, TimerKind, started

    vials = {"unit": "vials", "level": 1, "device": "spectrometer", "used_by": {"measure": 1}}
    core, _ = started(scenario_of, **{"campaign.budget": 2, "consumables": {"vials": vials},
                                      "workflow": [{"step": "measure", "device": "spectrometer"}]})
    core.feed(Proposed([Proposal({**QD, "concentration_mm": 1}), Proposal({**QD, "concentration_mm": 2})]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "spectrometer-1"), Assignment("e1s0", "spectrometer-2")]))
    core.advance(0.0)
    core.feed(msg(Kind.RESULT, "spectrometer-1", "e0s0", 1, outputs={"peak_nm": 600}, sample=None))
    core.feed(msg(Kind.FAULT, "spectrometer-2", "e1s0", 1, code="failed", reason="lamp"))
    out = core.advance(10.0)
    retry = [a for a in out if type(a) is SetTimer and a.key.kind == TimerKind.RETRY]
    op(core, "refill", 11.0, item="vials@spectrometer-2", amount=1)
    core.feed(TimerFired(retry[0].key))
    out = no_more_experiments(core, core.advance(10.0 + retry[0].delay), 10.0 + retry[0].delay)
    asks = [a for a in out if getattr(a, "what", "") == "schedule"]
    assert asks, "the retry is offered no device: fail-over avoided the only instance with vials left"
    assert asks[0].view.ready[0].avoid == frozenset({"spectrometer-1"})  # dry; spectrometer-2 failed it, has vials


def test_a_step_barred_from_the_only_instance_with_stock_waits_for_a_refill(scenario_of):
    """The operator sent a failed step to another device, and that one's own vials are out: the step waits for a
    refill of that stock (and says so) rather than sitting ready for a device it may not use."""
    from tests.twin.test_core import started

    vials = {"unit": "vials", "level": 2, "device": "spectrometer", "used_by": {"measure": 1}}
    rules = [{"device": "spectrometer", "options": ["another_device", "abandon"], "default": "abandon"}]
    core, _ = started(scenario_of, **{"campaign.budget": 3, "campaign.max_in_flight": 3,
                                      "consumables": {"vials": vials},
                                      "orchestrator.retry.max_attempts": 1, "orchestrator.recovery": rules,
                                      "workflow": [{"step": "measure", "device": "spectrometer"}]})
    core.feed(Proposed([Proposal({**QD, "concentration_mm": c}) for c in (1, 2, 3)]))
    core.advance(0.0)
    core.feed(Decided([Assignment("e0s0", "spectrometer-1"), Assignment("e1s0", "spectrometer-2")]))
    core.advance(0.0)
    core.feed(msg(Kind.RESULT, "spectrometer-2", "e1s0", 1, outputs={"peak_nm": 600}, sample=None))
    core.advance(5.0)
    core.feed(Decided([Assignment("e2s0", "spectrometer-2")]))
    core.advance(5.0)
    assert core.stocks.levels() == {"vials@spectrometer-1": 1.0, "vials@spectrometer-2": 0.0}
    core.feed(msg(Kind.FAULT, "spectrometer-1", "e0s0", 1, code="failed", reason="lamp"))
    core.advance(10.0)
    core.feed(Operator("answer", "alice", "r1", question="q1", option="another_device"))
    out = core.advance(20.0)
    assert "e0s0" in core.starved and "e0s0" not in core.ready
    (short,) = notes(out, "consumable.depleted")
    assert short.detail["item"] == "vials@spectrometer-2" and short.task == "e0s0"
    out = op(core, "refill", 30.0, item="vials@spectrometer-2")
    assert "e0s0" in core.ready and not core.starved


def test_a_stock_that_runs_out_is_said_on_the_log_with_the_refill_to_make(tmp_path, caplog):
    """On a live clock nobody but a person refills a stock, and the lab waited for one without a word on the
    terminal (only the journal and `twin ctl pending` had it): the depletion is an alert now, naming the item and
    the command; here in virtual time, with its simulated refill."""
    lab = parse(qd_lab(**{"campaign.budget": 4, "consumables": stocked(100, 1, refill_after=600)}), "lab.yaml")
    with caplog.at_level("WARNING", logger="twin.alerts"):
        run(lab, journal=tmp_path / "j.db")
    said = [r.getMessage() for r in caplog.records if r.name == "twin.alerts"]
    assert len(said) == len(read_events(tmp_path / "j.db", "consumable.depleted")) > 0
    assert said[0].startswith("vials is out (0 vials left, 1 vial needed by e") and "`twin ctl refill vials`" in said[0]
    assert "another instance" not in said[0]  # the lab's one stock: no instance has its own


def test_stock_a_live_lab_on_a_memory_bus_cannot_have_refilled_is_warned_of(caplog):
    lab = parse(qd_lab(consumables=stocked(10, 5), clock={"mode": "wall"}), "lab.yaml")
    with caplog.at_level("WARNING", logger="twin.runtime.checks"):
        check(lab)
    assert [m for m in caplog.messages if "memory bus" in m] == [
        "on a wall clock and a memory bus, which twin ctl cannot reach (it reaches a campaign over Zenoh only): "
        "consumables precursor, vials may run out, and the steps that need one would wait to the end for a `twin ctl "
        "refill`. Run it with --bus zenoh --listen tcp/127.0.0.1:7447 (and twin ctl … --connect there)"]


def test_a_reorder_point_not_below_the_level_is_warned_of(caplog):
    """Taken for a typo (a reorder point of 500 for a 250 mL stock): low from the first step, never news again."""
    lab = parse(qd_lab(consumables={"precursor": {"unit": "mL", "level": 250, "reorder_at": 250,
                                                  "used_by": {"synthesise": 1}}}), "lab.yaml")
    with caplog.at_level("WARNING", logger="twin.runtime.checks"):
        check(lab)
    assert [m for m in caplog.messages if "reorder_at" in m] == [
        "consumables.precursor.reorder_at: 250 is not below its level, 250 mL, so consumable.low says it is low at its "
        "first step and never after a refill; give the level at which to reorder, below the starting one"]


@pytest.mark.parametrize("holders, elsewhere", [(1, False), (2, True)])
def test_a_stock_of_an_only_instance_that_runs_out_is_not_said_to_send_its_steps_elsewhere(tmp_path, holders,
                                                                                            elsewhere, caplog):
    """A technician's own gloves: 'its steps go to another instance that has some' where there is none."""
    lab = qd_lab(**{"campaign.budget": 3, "devices.spectrometer.instances": holders,
                    "consumables": {"vials": {"unit": "vials", "level": 1, "device": "spectrometer",
                                              "used_by": {"measure": 1}, "simulate_refill": {"after_s": 600}}}})
    with caplog.at_level("WARNING", logger="twin.alerts"):
        run(parse(lab, "lab.yaml"), journal=tmp_path / "j.db")
    said = [m for m in caplog.messages if " is out (" in m]
    assert said and all(("go to another instance that has some, or wait" in m) == elsewhere for m in said), said


def test_a_stock_crossing_its_reorder_point_on_a_live_clock_says_when_it_runs_out_and_who_can_refill_it(caplog):
    from twin.campaign import Note
    from twin.runtime.asked_of_people import tell

    low = Note(600.0, "consumable.low", detail={"item": "vials", "level": 3, "unit": "vials", "reorder_at": 4,
                                                "runs_out_in_s": 4320.0})
    with caplog.at_level("WARNING", logger="twin.alerts"):
        tell(low, None, speed=20.0)  # a memory bus: nothing outside reaches the campaign
    assert caplog.messages == ["consumable.low vials: 3 vials left, below its reorder point (4); at the rate so far "
                               "it runs out in 4,320 lab-s (216 s of wall time): reorder it; nobody can say it is "
                               "refilled: twin ctl reaches a campaign over Zenoh, and this lab's bus is memory"]


def test_a_quantity_of_one_takes_its_units_singular():
    """"1 tiles left" and "1 vials needed": a unit written as a plural now takes its singular for exactly one."""
    from twin.core.counts import quantity

    said = [quantity(v, u) for v, u in ((1, "vials"), (2, "vials"), (0, "vials"), (1.0, "tiles"), (1, "boxes"),
                                        (1, "glasses"), (1, "mL"), (1, "pcs"), (1, "kits"), (1, "s"), (1, ""),
                                        (0.5, "L"), (1, "Vials"))]
    assert said == ["1 vial", "2 vials", "0 vials", "1 tile", "1 box", "1 glass", "1 mL", "1 pc", "1 kit", "1 s", "1",
                    "0.5 L", "1 Vials"]
