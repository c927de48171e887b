"""A candidate policy holds what it sees inside the range it was judged on (``observed`` in its file): a lab
larger than any it trained on reads as the most it knows, not as values its network never fitted."""

import json
import random
import shutil
from pathlib import Path

import pytest
import torch

from agents.candidates import GLOBALS, MAX_CANDIDATES, WIDTHS, Observed
from agents.observed_range import observe
from agents.rl_scheduler import RlScheduler
from agents.judging import campaign
from agents.train_scheduler import train_scheduler
from twin import PluginError, jobshop_as_lab, load_plugin, random_jobshop

ROOT = Path(__file__).resolve().parents[2]
# the earlier job-shop policy (candidates-v2, counts ÷ 10): a larger shop runs its inputs past anything it saw
POLICY = ROOT / "tests" / "data" / "jobshop_scheduler_v2.zip"
torch.set_num_threads(1)


def long_shop(ft06):
    """60 jobs on 5 machines: three times the jobs of the largest shop the policy trained on (20)."""
    return jobshop_as_lab(ft06, random_jobshop(60, 5, 1, 99, random.Random(1)))


def unheld(lab):
    agent = RlScheduler(lab, str(POLICY))
    agent.encoder.held = None
    return agent


def test_every_shipped_candidate_policy_records_the_range_it_was_judged_on():
    for name in ("jobshop_scheduler", "flaky_scheduler", "lab_scheduler"):
        meta = json.loads((ROOT / "agents" / "policies" / f"{name}.json").read_text())
        width = WIDTHS[meta["signature"]["encoding"]]
        held = Observed.from_meta(meta["observed"], width, name)
        assert (held.lo <= held.hi).all() and held.ghi.shape == (GLOBALS,)


def test_a_larger_lab_is_seen_inside_the_range_and_scheduled_near_the_rule(ft06):
    lab = long_shop(ft06)
    agent, raw_reader = RlScheduler(lab, str(POLICY)), unheld(lab).encoder
    held, width, beyond = agent.encoder.held, agent.encoder.width, []

    def decide(view):
        out = agent.decide(view)
        obs = agent.encoder.encode(view)[0]
        rows = obs[:MAX_CANDIDATES * width].reshape(MAX_CANDIDATES, width)[:len(agent.encoder.encoded)]
        glob = obs[MAX_CANDIDATES * width:]
        assert (rows >= held.lo - 1e-6).all() and (rows <= held.hi + 1e-6).all()
        assert (glob >= held.glo - 1e-6).all() and (glob <= held.ghi + 1e-6).all()
        raw = raw_reader.encode(view)[0][MAX_CANDIDATES * width:]
        beyond.append(bool((raw > held.ghi + 1e-6).any()))
        return out

    spans = {"held": campaign(lab, 0, decide).lab_hours, "unheld": campaign(lab, 0, unheld(lab).decide).lab_hours,
             "mwkr": campaign(lab, 0, load_plugin("schedulers", "mwkr")().decide).lab_hours}
    assert any(beyond)  # the lab did go beyond what the policy was judged on
    assert spans["held"] <= 1.25 * spans["mwkr"] and spans["unheld"] >= 2 * spans["mwkr"], spans


def test_inside_the_range_the_decisions_are_unchanged(ft06):
    shop = jobshop_as_lab(ft06, random_jobshop(10, 10, 1, 99, random.Random(5)))
    for lab in (ft06, shop):
        made = {}
        for name, agent in (("held", RlScheduler(lab, str(POLICY))), ("unheld", unheld(lab))):
            decisions = []
            campaign(lab, 0, lambda view, a=agent, d=decisions: d.append(a.decide(view)) or d[-1])
            made[name] = [[(x.task, x.device) for x in out] for out in decisions]
        assert made["held"] == made["unheld"]


@pytest.mark.parametrize("field, damage", [
    ("observed", {"rows": [[0.0], [1.0]], "globals": [[0.0] * GLOBALS, [1.0] * GLOBALS]}),
    ("observed", {"rows": "wide"}), ("observed", [1, 2]),
    ("observed", {"rows": [[1.0] * 29, [0.0] * 29], "globals": [[0.0] * GLOBALS] * 2}),
    ("fits", "oops"), ("fits", {"steps": ["op"], "device_types": [5, 6]}),
    ("fits", {"steps": "op", "device_types": [5, 6], "instances": [1, 1]}),
    ("fits", {"steps": ["op"], "device_types": [6, 5], "instances": [1, 1]}),
    ("fits", {"steps": ["op"], "device_types": [5, 6], "instances": [1, 1.5]})])
def test_a_damaged_record_of_what_it_saw_is_refused_naming_the_file(ft06, tmp_path, field, damage):
    copy = tmp_path / "p.zip"
    shutil.copy(POLICY, copy)
    meta = json.loads(POLICY.with_suffix(".json").read_text())
    meta[field] = damage
    copy.with_suffix(".json").write_text(json.dumps(meta))
    said = {"observed": "is not two ranges of finite numbers", "fits": "is not the shapes a policy was trained on"}
    with pytest.raises(PluginError, match=rf"p\.json: its '{field}' {said[field]}"):  # was a TypeError for 'fits'
        RlScheduler(ft06, str(copy))
    if field == "fits":  # and a training that starts from it
        with pytest.raises(PluginError, match=rf"p\.json: its 'fits' {said[field]}"):
            train_scheduler(ft06, 100, tmp_path / "next.zip", init=str(copy), envs=1)


def test_a_policy_saved_before_ranges_were_kept_gets_one_from_its_labs(ft06, tmp_path):
    observed = observe(POLICY, ft06, held_out_count=2)
    held = Observed.from_meta(observed, 29, "here")
    shipped = Observed.from_meta(json.loads(POLICY.with_suffix(".json").read_text())["observed"], 29, "shipped")
    # fewer labs than the shipped range was taken over: inside it, and not a single point
    assert (held.lo >= shipped.lo - 1e-6).all() and (held.hi <= shipped.hi + 1e-6).all()
    assert (held.hi > held.lo).sum() > 10


SHIPPED = ROOT / "agents" / "policies" / "jobshop_scheduler.zip"


def test_candidates_v4_reads_a_larger_shops_counts_as_shares_of_it(ft06):
    """What grows with the lab — a type's ready steps, the operations queued for it, a step's operations left —
    v3 divides by ten and v4 reads as a share of the lab: on a 60-job shop v3's run past 1, v4's stay in 0..1."""
    from agents.candidates import CandidateEncoder

    lab, columns = long_shop(ft06), [7, 11, 23]
    v3, v4, most = CandidateEncoder(lab, "candidates-v3"), CandidateEncoder(lab, "candidates-v4"), {3: 0.0, 4: 0.0}

    def decide(view):
        for version, enc in ((3, v3), (4, v4)):
            rows = enc.encode(view)[0][:MAX_CANDIDATES * 34].reshape(MAX_CANDIDATES, 34)[:len(enc.encoded)]
            most[version] = max(most[version], float(rows[:, columns].max(initial=0.0)))
        return load_plugin("schedulers", "mwkr")().decide(view)

    campaign(lab, 0, decide)
    assert most[3] > 1.5 and most[4] <= 1.0, most


def test_the_shipped_job_shop_policy_beats_mwkr_on_shops_larger_than_any_it_trained_on(ft06):
    """Trained on shops of up to 20 jobs × 15 machines; here 40 jobs × 10 and 50 × 20, two shops of each."""
    ratios = []
    for jobs, machines in ((40, 10), (50, 20)):
        for k in range(2):
            lab = jobshop_as_lab(ft06, random_jobshop(jobs, machines, 1, 99, random.Random(f"larger:{jobs}:{k}")))
            rl = campaign(lab, 0, RlScheduler(lab, str(SHIPPED)).decide).lab_hours
            ratios.append(rl / campaign(lab, 0, load_plugin("schedulers", "mwkr")().decide).lab_hours)
    assert sum(ratios) / len(ratios) < 1.0, ratios
