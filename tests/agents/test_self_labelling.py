"""Self-labelling (training.teacher: self): a policy's own best of several rollouts is what it learns next — the
labels replay that best run, the first run is the greedy policy's, and a training starts where --init left it."""

import json
import random
from pathlib import Path

import pytest
import torch

from agents.candidates import WAIT, CandidateEncoder, trained_encoding
from agents.imitation import _scorer, sampled_runs, self_task
from agents.rl_scheduler import RlScheduler
from agents.judging import campaign, objective
from agents.train_scheduler import train_scheduler
from twin import SteppedCampaign, jobshop_as_lab, random_jobshop, read_meta
from twin.runtime.lab import prepare
from tests.conftest import twin_cli

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "agents" / "policies" / "jobshop_scheduler.zip"
AS_SHIPPED = trained_encoding(read_meta(SHIPPED)["signature"]["encoding"])  # the columns it decides by
torch.set_num_threads(1)


def replay(lab, samples) -> float:
    """Lab-seconds of a campaign of ``lab`` that takes, state by state, the choice each sample is labelled with."""
    enc, c = CandidateEncoder(lab, AS_SHIPPED), SteppedCampaign(lab)
    try:
        for s in samples:
            enc.encode(c.view)
            assert len(enc.encoded) == len(s.rows) and s.taught.sum() == 1 and not (s.taught & ~s.allowed).any()
            k = int(s.taught.argmax())
            c.answer(enc.decode(c.view, WAIT if k == len(s.rows) else k))
        assert c.done, "the labels ended before the campaign did"
        return c.summary.lab_hours * 3600
    finally:
        c.close()


def test_the_runs_go_in_lockstep_the_first_greedy_and_each_label_replays_its_run(ft06, state):
    lab = prepare(jobshop_as_lab(ft06, random_jobshop(10, 10, 1, 50, random.Random(3))), seed=0)
    runs = sampled_runs(lab, _scorer(state, 0), 6, encoding=AS_SHIPPED)
    spans = [summary.lab_hours * 3600 for _, summary in runs]
    greedy = campaign(lab, 0, RlScheduler(lab, str(SHIPPED)).decide).lab_hours * 3600
    assert spans[0] == pytest.approx(greedy)
    assert len(set(spans)) > 1, "the sampled runs never left the greedy one"
    for samples, summary in runs:
        assert replay(lab, samples) == pytest.approx(summary.lab_hours * 3600)


def test_a_self_task_returns_its_best_run(ft06, state):
    small = prepare(ft06, overrides={"training.jobshop_sizes": [[10, 5]], "training.samples": 8})
    samples, info = self_task((small, 11, ("self",), state, 0.0, AS_SHIPPED))
    rng = random.Random("imitate:11")  # the shop the task drew
    n_jobs, n_machines = rng.choice(small.training.jobshop_sizes)
    lab = prepare(jobshop_as_lab(small, random_jobshop(n_jobs, n_machines, 1, 99, rng)), seed=0)
    runs = sampled_runs(lab, _scorer(state, 11), 8, encoding=AS_SHIPPED)
    best = min(objective(summary, lab) for _, summary in runs)
    assert info["greedy ÷ best"] >= 1.0 and info["sampled ÷ best"] >= 1.0
    assert replay(lab, samples) / 3600 == pytest.approx(min(s.lab_hours for _, s in runs))
    assert objective(runs[0][1], lab) / best == pytest.approx(info["greedy ÷ best"])


def test_self_labelling_needs_a_policy_to_start_from(ft06, tmp_path):
    own = prepare(ft06, overrides={"training.teacher": "self"})
    with pytest.raises(ValueError, match="pass --init POLICY.zip"):
        train_scheduler(own, 100, tmp_path / "x.zip")


def test_a_training_starts_where_init_left_off(ft06, tmp_path, rollouts_in_process):
    own = prepare(ft06, overrides={"training.teacher": "self", "training.jobshop_sizes": [[6, 6]],
                                   "training.samples": 4})
    out, seen = tmp_path / "tuned.zip", []
    train_scheduler(own, 600, out, envs=2, eval_every=300, eval_seeds=(0,), held_out_count=2, init=SHIPPED,
                    on_progress=lambda done, result: seen.append(result) if result and "objective" in result else None)
    meta = json.loads(out.with_suffix(".json").read_text())
    shipped = campaign(ft06, 0, RlScheduler(ft06, str(SHIPPED)).decide).lab_hours
    assert meta["teacher"] == "self" and meta["init"] == str(SHIPPED) and meta["curve"][0]["steps"] == 0
    before = json.loads(SHIPPED.with_suffix(".json").read_text())
    assert meta["lineage"][-1] == {k: before[k] for k in ("method", "teacher", "steps", "saved")}
    assert meta["lineage"][:-1] == before.get("lineage", [])
    assert meta["curve"][0]["makespan h"] == pytest.approx(shipped)  # evaluated before any step: the shipped policy
    assert meta["fits"]["steps"] == ["op"]
    assert [r["policy"].split(" (")[0] for r in seen[1:]][:2] == ["start", "self-labelled"]
    assert seen[2:] and all(r["greedy ÷ best"] >= 1 for r in seen[2:])


@pytest.mark.parametrize("args,says", [
    (["--agent", "planner", "--init", str(SHIPPED)], "the planner trainer has no such option"),
    (["--init", "nowhere.zip"], "--init nowhere.zip: no such policy file"),
])
def test_init_is_refused_where_it_cannot_work(args, says, tmp_path):
    res = twin_cli("train", "scenarios/jobshop.yaml", "--out", tmp_path / "p.zip", *args)
    assert res.exit_code != 0 and says in " ".join(res.stderr.split()), res.stderr
