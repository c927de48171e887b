"""Random shared labs (hypothesis): device counts, faults, crashes, priorities, budgets, consumables — the
campaigns in turns or one scheduler for the lab. Every campaign ends with its accounting invariant, no device
ever runs two steps at once, shared stocks never go below zero."""

import json

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.twin.shared_labs import LAB, assert_accounted, assert_one_step_at_a_time, events
from twin.campaign.journal_read import read_events
from twin.runtime.lab import prepare
from twin.runtime.shared_run import run_shared
from twin.scenario import load

lab_shapes = st.fixed_dictionaries({
    "spectrometers": st.integers(1, 2), "synthesisers": st.integers(1, 3),
    "fail_p": st.sampled_from([0.0, 0.1, 0.3]), "hang_p": st.sampled_from([0.0, 0.05]),
    "mtbc_h": st.sampled_from([0, 3]),
    "priorities": st.lists(st.integers(-1, 1), min_size=2, max_size=3),
    "budgets": st.lists(st.integers(2, 8), min_size=3, max_size=3),
    "seed": st.integers(0, 1000),
    "lab_scheduler": st.sampled_from([None, "mwkr", "spt"]),  # None: each campaign's own, in turns
    "vials": st.sampled_from([None, "lab", "spectrometer"]),  # none, one stock, or each spectrometer's own
    "vials_level": st.integers(1, 6), "refill_after_s": st.sampled_from([None, 1800]),
})


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(shape=lab_shapes)
def test_any_shared_lab_runs_one_step_per_device_and_accounts_for_everything(tmp_path_factory, shape):
    """Random labs, faults, crashes and priorities, the campaigns in turns or one scheduler for the lab: every
    campaign ends with its accounting invariant, no device ever runs two steps at once."""
    n = len(shape["priorities"])
    base = load(LAB)
    campaigns = []
    for i in range(n):
        c = base.campaigns[i % 2].model_dump(exclude_none=True)
        c.update(name=f"c{i}", priority=shape["priorities"][i])
        c["campaign"] = {**c["campaign"], "budget": shape["budgets"][i], "planner": "random"}
        campaigns.append(c)
    faults = {"fail_p": shape["fail_p"], "hang_p": shape["hang_p"], "mtbc_h": shape["mtbc_h"], "restart_s": 600}
    stocks = {}
    if shape["vials"]:
        vials = {"unit": "vials", "level": shape["vials_level"], "used_by": {"measure": 1}}
        if shape["vials"] == "spectrometer":
            vials["device"] = "spectrometer"
        if shape["refill_after_s"]:
            vials["simulate_refill"] = {"after_s": shape["refill_after_s"]}
        stocks = {"consumables": {"vials": vials}}
    s = prepare(base, seed=shape["seed"], overrides={**stocks,
        "campaigns": campaigns, "devices.spectrometer.instances": shape["spectrometers"],
        "devices.synthesiser.instances": shape["synthesisers"], "orchestrator.lab_scheduler": shape["lab_scheduler"],
        **{f"devices.{d}.faults": faults for d in ("synthesiser", "reactor", "spectrometer")}})
    where = tmp_path_factory.mktemp("lab")
    out = run_shared(s, where, handle_signals=False)
    assert len(out.campaigns) == n
    assert_accounted(out)
    assert_one_step_at_a_time(where)
    busy = [r for db in where.glob("*.db") for r in events(db, "msg.rejected") if "busy" in (r[6] or "")]
    assert not busy, f"a device was sent a step while it ran another: {busy[:2]}"
    if shape["vials"]:  # the campaigns share the stocks: never below zero, an instance's own used only on it
        taken = sorted((e["t_lab"], e["seq"], e["device"], json.loads(e["detail"])) for db in where.glob("*.db")
                       for e in read_events(db, "attempt.dispatched") if e["device"].startswith("spectrometer"))
        for _, _, device, d in taken:
            (stock,) = d["used"]
            assert stock == ("vials" if shape["vials"] == "lab" else f"vials@{device}")
            assert d["left"][stock] >= 0
