"""Learning job shops from CP-SAT's schedules (agents.imitation): the teacher's labels hold in any state, the
teacher reproduces its plan, and a short DAgger training beats random dispatching."""

import json
import random
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.candidates import WAIT, CandidateEncoder
from agents.cpsat import jobshop
from agents.imitation import PlanTeacher, follow_teacher, rollout
from agents.rl_scheduler import RlScheduler
from agents.train_scheduler import campaign, train_scheduler
from twin import SteppedCampaign, jobshop_as_lab, random_jobshop
from twin.runtime.lab import prepare
from twin.scenario.jobshop import read

ROOT = Path(__file__).resolve().parents[2]
torch.set_num_threads(1)


@pytest.fixture(scope="module")
def ft06():
    return prepare(ROOT / "scenarios" / "jobshop.yaml")


def teacher_for(lab, inst, limit=5.0):
    plan = jobshop(inst.jobs, inst.machines, time_limit_s=limit)
    return PlanTeacher(inst.jobs, plan.starts), plan


def test_following_the_teacher_reproduces_its_plan(ft06):
    inst = read(ROOT / "scenarios" / "jobshop" / "ft06.txt")
    teacher, plan = teacher_for(ft06, inst)
    samples, span = rollout(ft06, teacher, follow_teacher, random.Random(0))
    assert plan.makespan == 55 and span == pytest.approx(55)
    assert len(samples) >= 36 and all(s.taught.any() and not (s.taught & ~s.allowed).any() for s in samples)


def test_off_the_plan_every_state_still_gets_one_choice_per_free_machine_or_waiting(ft06):
    inst = random_jobshop(8, 5, 1, 20, random.Random(4))
    lab = prepare(jobshop_as_lab(ft06, inst), seed=0)
    teacher, plan = teacher_for(lab, inst, limit=2.0)
    enc, rng = CandidateEncoder(lab), np.random.default_rng(1)
    c = SteppedCampaign(lab)
    waited = 0
    try:
        while not c.done:  # a learner that ignores the teacher
            _, mask = enc.encode(c.view)
            pairs = enc.encoded
            taught = teacher.labels(c, pairs, bool(mask[WAIT]))
            chosen = [pairs[i][1] for i in np.flatnonzero(taught[:-1])]
            assert taught.any() and len(chosen) == len(set(chosen)), chosen
            assert not taught[-1] or (mask[WAIT] and not chosen)
            waited += bool(taught[-1])
            action = int(rng.choice(np.flatnonzero(mask)))
            if action != WAIT:
                teacher.start(c, pairs[action][0])
            c.answer(enc.decode(c.view, action))
        span = c.summary.lab_hours * 3600
    finally:
        c.close()
    assert span > plan.makespan  # it did leave the plan
    assert waited, "the teacher never waited for its plan's next operation"


def test_a_short_imitation_beats_random_dispatching_and_says_how_it_learnt(ft06, tmp_path):
    small = prepare(ft06, overrides={"training.jobshop_sizes": [[6, 6], [8, 5]]})
    out = tmp_path / "imitated.zip"
    seen = []
    train_scheduler(small, 3000, out, envs=2, eval_every=1500, eval_seeds=(0,), held_out_count=2,
                    on_progress=lambda done, result: seen.append(result) if result else None)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["method"] == "imitate" and meta["teacher"] == "cp-sat" and len(meta["curve"]) >= 2
    assert meta["fits"] == {"steps": ["op"], "device_types": [5, 6], "instances": [1, 1]}
    assert any("imitation" in r["policy"] for r in seen)
    rl = campaign(ft06, 0, RlScheduler(ft06, str(out)).decide).lab_hours
    enc, rng = CandidateEncoder(ft06), np.random.default_rng(1)

    def random_decide(view):
        _, mask = enc.encode(view)
        return enc.decode(view, int(rng.choice(np.flatnonzero(mask))))

    randoms = [campaign(ft06, 0, random_decide).lab_hours for _ in range(5)]
    assert rl < min(randoms), (rl, randoms)


def test_imitation_outside_a_job_shop_is_refused_with_what_to_use_instead(tmp_path):
    flaky = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides={"training.method": "imitate"})
    with pytest.raises(ValueError, match="training.method: ppo"):
        train_scheduler(flaky, 100, tmp_path / "x.zip")
