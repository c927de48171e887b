"""Random labs for training: their shapes stay in the ranges, every type is on the workflow, they run to the end,
and a policy trained on them fits any workflow but still knows how many device types and instances it saw."""

import random
from pathlib import Path

import pytest

from agents.candidates import lab_shape, outside, widen
from twin.scenario.random_labs import random_lab
from agents.scheduling_env import randomised
from agents.judging import campaign
from agents.schedulers import RULES
from twin import load_plugin
from twin.runtime.lab import prepare
from twin.core.errors import ScenarioError
from twin.scenario import load

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def flaky():
    return prepare(ROOT / "scenarios" / "flaky_lab.yaml",
                   overrides={"training.random_labs": {"share": 1.0, "device_types": [2, 5], "instances": [1, 4]}})


def test_random_labs_stay_in_their_ranges_and_visit_every_type(flaky):
    seen_types, revisits = set(), 0
    for seed in range(40):
        lab = random_lab(flaky, random.Random(seed))
        k = len(lab.devices)
        seen_types.add(k)
        assert 2 <= k <= 5 and all(1 <= d.instances <= 4 for d in lab.devices.values())
        route = [w.device for w in lab.workflow]
        assert set(route) == set(lab.devices) and len(route) in (k, k + 1)
        assert all(a != b for a, b in zip(route, route[1:]))  # a revisit is never the step just done
        revisits += len(route) > k
        assert lab.chemistry.stability_s == flaky.chemistry.stability_s
        for d in lab.devices.values():  # each type is one of the scenario's, its mean duration scaled ×0.5–2
            assert any((t.duration.cv, t.setup_s, t.clean_s, t.faults.fail_p) ==
                       (d.duration.cv, d.setup_s, d.clean_s, d.faults.fail_p)
                       and 0.5 <= d.duration.mean_s / t.duration.mean_s <= 2.0 for t in flaky.devices.values())
        assert k <= lab.campaign.max_in_flight <= k + sum(d.instances for d in lab.devices.values())
    assert seen_types == {2, 3, 4, 5} and 0 < revisits < 40
    a, b = random_lab(flaky, random.Random(7)), random_lab(flaky, random.Random(7))
    assert a == b  # the same seed draws the same lab


def test_a_lab_with_stocks_and_questions_for_the_operator_draws_random_labs_without_them():
    """staffed_lab's stocks are used by its steps and its operator is asked about its syntheses: a drawn lab, whose
    stations run "op", copied them and failed validation — `twin bench schedulers scenarios/staffed_lab.yaml --shapes
    --random-labs 2` ended in a traceback."""
    staffed = prepare(ROOT / "scenarios" / "staffed_lab.yaml")
    assert staffed.consumables and staffed.orchestrator.recovery
    for seed in range(5):
        lab = random_lab(staffed, random.Random(seed))
        assert not lab.consumables and not lab.orchestrator.recovery
        s = campaign(prepare(lab), 0, load_plugin("schedulers", "fifo")().decide)
        assert s.done + s.abandoned == lab.campaign.budget


def test_every_rule_runs_a_random_lab_to_the_end_and_nothing_is_lost(flaky):
    lab = randomised(flaky, 3)
    assert lab_shape(lab)["steps"] == ["*"]
    for rule in RULES:
        s = campaign(lab, 0, load_plugin("schedulers", rule)().decide)
        assert s.done + s.abandoned == lab.campaign.budget, (rule, s)


def test_a_policy_trained_on_random_labs_fits_any_workflow_but_not_more_instances(flaky):
    fits = lab_shape(flaky)
    for seed in range(20):  # as the trainer widens its fits over the labs it draws
        fits = widen(fits, lab_shape(randomised(flaky, seed)))
    assert fits["steps"] == ["*", "measure", "prepare", "react"] and fits["device_types"] == [2, 5]
    other = prepare(ROOT / "scenarios" / "quantum_dots.yaml")  # step types never named in training
    assert outside(fits, lab_shape(other)) == []
    crowded = prepare(other, overrides={"devices.synthesiser.instances": 12})
    assert outside(fits, lab_shape(crowded)) == [f"12 instances of one type (trained on at most {fits['instances'][1]})"]
    assert outside(widen(None, lab_shape(flaky)), lab_shape(other))  # without random labs the step types are unseen


def test_bad_random_lab_ranges_name_the_field(tmp_path):
    text = (ROOT / "scenarios" / "flaky_lab.yaml").read_text()
    assert "  random_labs: {share: 0.5}\n" in text
    text = text.replace("  random_labs: {share: 0.5}\n", "  random_labs: {share: 0.5, device_types: [5, 2]}\n")
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ScenarioError, match=r"training\.random_labs.*device_types: \[5, 2\] must be low ≤ high"):
        load(bad)


def test_the_shipped_flaky_policy_schedules_a_lab_of_other_step_types_without_a_warning(caplog):
    from agents.rl_scheduler import RlScheduler

    qd = prepare(ROOT / "scenarios" / "quantum_dots.yaml", overrides={"campaign.budget": 8})
    with caplog.at_level("WARNING"):
        rl = RlScheduler(qd, str(ROOT / "agents" / "policies" / "flaky_scheduler.zip"))
    assert rl.misfit == "" and "trained on labs unlike" not in caplog.text
    s = campaign(qd, 0, rl.decide)
    assert s.done + s.abandoned == 8 and s.done >= 7


def test_each_device_type_draws_its_own_stage_scale_and_samples_their_own_stability():
    written = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides={"training.random_labs": None})
    t = written.training
    assert t.type_scale != (1.0, 1.0) and t.stability_scale != (1.0, 1.0)
    lo = t.duration_scale[0] * t.type_scale[0]
    hi = t.duration_scale[1] * t.type_scale[1]
    spreads, stabilities = [], set()
    for seed in range(30):
        lab = randomised(written, seed)
        ratios = {n: lab.devices[n].duration.mean_s / d.duration.mean_s for n, d in written.devices.items()}
        assert all(lo <= r <= hi for r in ratios.values())
        spreads.append(max(ratios.values()) / min(ratios.values()))  # one global scale would give 1.0
        fail = {n: lab.devices[n].faults.fail_p / d.faults.fail_p for n, d in written.devices.items()}
        assert all(t.fault_scale[0] * t.type_scale[0] <= f <= t.fault_scale[1] * t.type_scale[1] or
                   lab.devices[n].faults.fail_p == 0.5 for n, f in fail.items())
        stabilities.add(lab.chemistry.stability_s / written.chemistry.stability_s)
    assert max(spreads) > 2.0 and all(t.stability_scale[0] <= x <= t.stability_scale[1] for x in stabilities)
    assert len(stabilities) == 30
    unscaled = prepare(written, overrides={"training.type_scale": [1.0, 1.0], "training.stability_scale": [1, 1]})
    lab = randomised(unscaled, 5)
    assert lab.chemistry.stability_s == written.chemistry.stability_s
    assert len({round(lab.devices[n].duration.mean_s / d.duration.mean_s, 9) for n, d in written.devices.items()}) == 1


def test_a_share_of_the_labs_drawn_make_one_stage_the_bottleneck_and_the_rest_are_drawn_as_before():
    """flaky_lab's stages drawn up to 2.5× slower never made its synthesiser or spectrometer the bottleneck (the
    bench's bottleneck shapes need ×8.2 and ×20.7); with ``bottleneck_share`` that share of the labs drawn have one
    workflow stage, drawn, the busiest by the bench's margin. Without it, every lab is drawn as before."""
    from twin.scenario.bottleneck import MARGIN, stage_loads

    written = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides={"training.random_labs": None})
    shared = prepare(written, overrides={"training.bottleneck_share": 1.0})
    made = set()
    for seed in range(12):
        loads = stage_loads(randomised(shared, seed))
        busiest, *rest = sorted(loads, key=loads.get, reverse=True)
        assert loads[busiest] >= MARGIN * loads[rest[0]] * 0.999, loads
        made.add(busiest)
    assert made == {"synthesiser", "reactor", "spectrometer"}
    for seed in range(5):  # the share left at 0: the same labs, draw for draw
        assert randomised(written, seed) == randomised(prepare(written, overrides={"training.bottleneck_share": 0}),
                                                       seed)
