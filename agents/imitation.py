"""Learning to dispatch from a teacher: CP-SAT's schedules (job shops), the best rule, or the policy's own best runs.

PPO learns a job shop from its makespan alone, one number per episode; a solver knows, for a whole shop,
a schedule within a few percent of the optimum. So the candidate policy can learn from a teacher instead
(``training.method: imitate``):

- ``cp-sat`` (job shops, whose work is all known and durations hold): the teacher solves each random training
  shop once and keeps each machine's order of operations; in any state of that shop — also one its plan never
  reaches, after the learner chose differently — it chooses, per free machine, the candidate that machine's
  order runs first, unless the order's next operation there is not ready yet and that candidate would still be
  running when it could start (then: wait). Following it reproduces the plan;
- ``best-rule`` (any lab, faults and all): in each lab drawn from the ``training`` ranges, the dispatching rule
  with the best objective there (makespan, degraded, abandoned, weighted; the mean of ``teacher_seeds`` runs) is
  the teacher, so the policy learns which rule's choice fits which state and lab; with ``teacher_margin``, a rule
  other than the lab's best as written teaches only where it beats that one by the margin;
- ``self`` (any lab; self-labelling, Corsini et al., 2024): each lab drawn is rolled out ``training.samples``
  times by the policy itself in lockstep (one greedy, the rest sampled) and the best run's choices are the
  labels, so the greedy policy learns what its own best samples do; it starts from a policy (``--init``), such
  as one taught by CP-SAT, and improves on it without a teacher of its own. (In a lab with faults the best run
  may be the luckiest rather than the best decided: the runs share the lab's seed, not its faults' timing.)
- ``self-pg`` (any lab; policy gradient): each lab drawn is rolled out ``training.samples`` times, every run
  sampled, and each run's choices are reinforced by how much better than the runs' mean it ended (discouraged by
  how much worse), in units of their spread — REINFORCE with the runs' mean as the baseline (as POMO, Kwon et al.,
  2020). Self-labelling learns only the best run; this learns from every run, on the policy's own samples: a few
  labs at a time, one gradient pass each. It starts from a policy (``--init``);
- DAgger (Ross et al., 2011): round 0 follows the teacher; later rounds follow the learner (greedy and sampled,
  mixed with the teacher's choices with a probability that halves every round) and label every state it
  visits with the teacher's choices, so the learner is taught where its own mistakes take it;
- the learner is trained by cross-entropy on every label so far: minus the log of the probability it gives to
  the teacher's set of choices.

Solves and rollouts run in worker processes (``agents.training_workers``; one worker: the trainer's own process);
each returns compact samples (only the rows that exist). ``agents.train_scheduler.Judge`` evaluates and keeps the
best policy exactly as for PPO.
"""

from __future__ import annotations

import random
import statistics
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.candidates import (ENCODING, FEATURES, MAX_CANDIDATES, WAIT, CandidateEncoder, Observed,
                               fits_of, lab_shape, widen)
from agents.cpsat import jobshop
from agents.lockstep import SAMPLE_TEMPERATURES, lockstep
from agents.planned_labs import planned
from agents.scheduling_env import randomised
from agents.schedulers import rules_for
from agents.teachers import PlanTeacher, RuleTeacher, solve_settings
from agents.judging import EVAL_SEEDS, campaign, objective
from agents.label_fit import Sample, fit
from agents.train_scheduler import Judge, JudgeBasis, initial_state, started_from
from agents.training_workers import numbered, workers_for
from twin import PluginError, Scenario, jobshop_as_lab, load_plugin, prepare, random_jobshop, stepped


#: The teachers that are the policy itself: they start from a policy (``--init``)
ITSELF = ("self", "self-pg")
#: self-pg: labs rolled out between two gradient passes, and the rows in each gradient step
PG_LABS, PG_BATCH = 8, 1024


def rollout(lab: Scenario, teacher: PlanTeacher | RuleTeacher, choose, rng: random.Random,
            encoding: str = ENCODING) -> tuple[list[Sample], Any]:
    """One campaign of ``lab``, every state labelled by ``teacher``; ``choose(obs, mask, taught, rng)`` acts.
    Returns the samples and the campaign's summary."""
    encoder = CandidateEncoder(lab, encoding)
    c = stepped(lab)
    out: list[Sample] = []
    teacher.reset()
    try:
        while not c.done:
            obs, mask = encoder.encode(c.view)
            pairs = encoder.encoded
            n = len(pairs)
            taught = teacher.labels(c, pairs, bool(mask[WAIT]))
            allowed = np.append(mask[:n], mask[WAIT])
            rows = obs[:MAX_CANDIDATES * FEATURES].reshape(MAX_CANDIDATES, FEATURES)[:n].copy()
            out.append(Sample(rows, obs[MAX_CANDIDATES * FEATURES:].copy(), allowed, taught & allowed))
            action = choose(obs, mask, taught, rng)
            if action != WAIT:
                teacher.start(c, pairs[action][0])
            c.answer(encoder.decode(c.view, action))
        return out, c.summary
    finally:
        c.close()


def follow_teacher(obs, mask, taught, rng) -> int:
    options = [i for i in np.flatnonzero(taught[:-1])] or [WAIT]
    return int(rng.choice(options))


def learner(scorer: torch.nn.Module, greedy: bool, beta: float):
    """Acts by the policy's scores (its best, or a sample), or with probability ``beta`` by the teacher."""
    def choose(obs, mask, taught, rng) -> int:
        if rng.random() < beta:
            return follow_teacher(obs, mask, taught, rng)
        with torch.no_grad():
            logits = scorer(torch.as_tensor(obs).unsqueeze(0))[0]
            logits[~torch.as_tensor(mask)] = -torch.inf
            if greedy:
                return int(logits.argmax())
            return int(torch.distributions.Categorical(logits=logits).sample())
    return choose


def shop_task(args: tuple) -> tuple[list[Sample], dict]:
    """Worker: draw a shop from ``seed``, solve it, and roll it out ``len(modes)`` times; ``modes`` are
    ``teacher``, ``greedy`` or ``sample``. Returns the samples and what the runs measured."""
    base, seed, modes, state, beta, encoding = args
    torch.set_num_threads(1)
    rng = random.Random(f"imitate:{seed}")
    n_jobs, n_machines = rng.choice(base.training.jobshop_sizes)
    low, high = (int(x) for x in (base.training.operation_s or (1, 10)))
    inst = random_jobshop(n_jobs, n_machines, low, high, rng)
    lab = prepare(jobshop_as_lab(base, inst), seed=0)
    plan = jobshop(inst.jobs, inst.machines, **solve_settings(n_jobs, n_machines))
    samples, spans = _rollouts(lab, PlanTeacher(inst.jobs, plan.starts), modes, _scorer(state, seed), beta, rng,
                               lambda summary: summary.lab_hours * 3600 / plan.makespan, encoding)
    return samples, {"size": f"{n_jobs}x{n_machines}", "plan": plan.makespan, "optimal": plan.optimal, **spans}


def lab_task(args: tuple) -> tuple[list[Sample], dict]:
    """Worker: draw a lab from the scenario's ``training`` ranges with ``seed``, find the rule that does best
    there, and roll the lab out ``len(modes)`` times with that rule as the teacher."""
    base, seed, modes, state, beta, encoding = args
    torch.set_num_threads(1)
    rng = random.Random(f"imitate:{seed}")
    lab = planned(prepare(randomised(base, seed), seed=seed))
    rule, scores = teaching_rule(lab, seed, base.training)
    samples, ratios = _rollouts(lab, RuleTeacher(rule), modes, _scorer(state, seed), beta, rng,
                                lambda summary: objective(summary, lab) / scores[rule], encoding)
    return samples, {"rule": rule, "shape": lab_shape(lab), **ratios}


def teaching_rule(lab: Scenario, seed: int, t: Any) -> tuple[str, dict[str, float]]:
    """The rule that teaches ``lab`` (``training.teacher_seeds``, ``teacher_margin``, ``teacher_default``), and every
    rule's objective there, on the first of its runs (what the rollouts' ratios are measured against)."""
    seeds = [seed + 7_919 * k for k in range(t.teacher_seeds)]  # the first is the lab's own: one seed as before
    runs = {r: [objective(campaign(lab, sd, load_plugin("schedulers", r)().decide), lab) for sd in seeds]
            for r in rules_for(lab)}
    mean = {r: statistics.mean(v) for r, v in runs.items()}
    rule = min(mean, key=mean.get)
    default = t.teacher_default
    if t.teacher_margin > 0 and default in mean and mean[rule] > (1 - t.teacher_margin) * mean[default]:
        rule = default
    return rule, {r: v[0] for r, v in runs.items()}


def with_teacher_default(scenario: Scenario, best_rule: str) -> Scenario:
    """``scenario`` whose labs' teacher defaults to ``best_rule`` (the best on the lab as written, which training
    is judged against) where a margin is asked and no default given."""
    t = scenario.training
    if t.teacher_margin <= 0 or t.teacher_default is not None:
        return scenario
    return scenario.model_copy(update={"training": t.model_copy(update={"teacher_default": best_rule})})


def sampled_runs(lab: Scenario, scorer: torch.nn.Module, k: int,
                 temperatures: tuple[float, ...] = SAMPLE_TEMPERATURES,
                 encoding: str = ENCODING, greedy_first: bool = True,
                 generator: torch.Generator | None = None) -> list[tuple[list[Sample], Any]]:
    """``k`` campaigns of ``lab`` in lockstep (``agents.lockstep``), each state labelled with the choice the run
    made there: the samples and the summary of each run."""
    out: list[list[Sample]] = [[] for _ in range(k)]

    def label(i: int, encoder: CandidateEncoder, obs: np.ndarray, m: np.ndarray, action: int, _: Any) -> None:
        out[i].append(chosen(encoder, obs, m, action))

    summaries = lockstep(lab, scorer, k, temperatures, encoding, label, greedy_first=greedy_first,
                         generator=generator)
    return list(zip(out, summaries))


def chosen(encoder: CandidateEncoder, obs: np.ndarray, mask: np.ndarray, action: int) -> Sample:
    """The state ``encoder`` encoded as ``obs`` (only the rows that exist), labelled with the choice ``action``."""
    n = len(encoder.encoded)
    taught = np.zeros(n + 1, bool)
    taught[n if action == WAIT else action] = True
    rows = obs[:MAX_CANDIDATES * FEATURES].reshape(MAX_CANDIDATES, FEATURES)[:n].copy()
    return Sample(rows, obs[MAX_CANDIDATES * FEATURES:].copy(), np.append(mask[:n], mask[WAIT]), taught)


def self_task(args: tuple) -> tuple[list[Sample], dict]:
    """Worker: draw a job shop (``training.jobshop_sizes``) or a lab (the ``training`` ranges) from ``seed``, roll
    it out ``training.samples`` times with the policy, and return the best run's samples (``self``) or every
    run's, weighted by its advantage (``self-pg``)."""
    base, seed, _modes, state, _beta, encoding = args
    torch.set_num_threads(1)
    if base.training.jobshop_sizes and not base.campaigns:
        rng = random.Random(f"imitate:{seed}")
        n_jobs, n_machines = rng.choice(base.training.jobshop_sizes)
        low, high = (int(x) for x in (base.training.operation_s or (1, 10)))
        lab = prepare(jobshop_as_lab(base, random_jobshop(n_jobs, n_machines, low, high, rng)), seed=0)
        shape = None
    else:
        lab = planned(prepare(randomised(base, seed), seed=seed))
        shape = lab_shape(lab)
    if base.training.teacher == "self-pg":
        samples, info = _reinforced(lab, _scorer(state, seed), base.training.samples, seed, encoding)
        return samples, {**info, **({"shape": shape} if shape else {})}
    runs = sampled_runs(lab, _scorer(state, seed), base.training.samples, encoding=encoding)
    scores = [objective(summary, lab) for _, summary in runs]
    best = min(range(len(runs)), key=scores.__getitem__)
    info = {"greedy ÷ best": scores[0] / scores[best], "sampled ÷ best": statistics.mean(scores[1:]) / scores[best]}
    return runs[best][0], {**info, **({"shape": shape} if shape else {})}


def _reinforced(lab: Scenario, scorer: torch.nn.Module, k: int, seed: int,
                encoding: str) -> tuple[list[Sample], dict]:
    """``k`` runs of ``lab``, all sampled (temperature 1: the policy's own distribution, which the gradient is of),
    each state labelled with the run's choice and weighted by the run's advantage (``advantage_weighted``)."""
    runs = sampled_runs(lab, scorer, k, (1.0,), encoding, greedy_first=False,
                        generator=torch.Generator().manual_seed(seed))
    scores = np.array([objective(summary, lab) for _, summary in runs])
    return (advantage_weighted([labelled for labelled, _ in runs], scores),
            {"sampled ÷ best": float(scores.mean() / scores.min())})


def advantage_weighted(runs: list[list[Sample]], scores: np.ndarray) -> list[Sample]:
    """Every run's labelled choices, weighted by its advantage: (the runs' mean objective − its own) ÷ their spread,
    so that ``fit`` makes REINFORCE's step. Runs that all end alike teach nothing (weight 0)."""
    spread = float(scores.std())
    advantage = (scores.mean() - scores) / spread if spread > 0 else np.zeros(len(scores))
    samples = []
    for labelled, a in zip(runs, advantage):
        for sample in labelled:
            sample.weight = float(a)
        samples += labelled
    return samples


def _rollouts(lab: Scenario, teacher, modes, scorer, beta: float, rng: random.Random, measure,
              encoding: str = ENCODING):
    """``lab`` rolled out once per mode (``teacher``, ``greedy``, ``sample``), every state labelled; the samples,
    and ``measure(summary)`` per mode."""
    samples, measured = [], {}
    for mode in modes:
        choose = follow_teacher if mode == "teacher" or scorer is None else learner(scorer, mode == "greedy", beta)
        got, summary = rollout(lab, teacher, choose, rng, encoding)
        samples += got
        measured[mode] = measure(summary)
    return samples, measured


def _scorer(state: dict | None, seed: int) -> torch.nn.Module | None:
    if state is None:
        return None
    from agents.candidate_policy import CandidateScorer

    scorer = CandidateScorer()
    scorer.load_state_dict(state)
    scorer.eval()
    torch.manual_seed(seed)
    return scorer


def _round_seen(scenario: Scenario, rnd: int, itself: bool, jobshop: bool, measured: list[dict]) -> tuple[str, dict]:
    """What a round of labels was (for the curve), and how its labs went: against the best run (self-labelling),
    the plan (CP-SAT) or the rule (best-rule)."""
    if itself:
        return "self-labelled", {k: statistics.mean(m[k] for m in measured) for k in ("greedy ÷ best", "sampled ÷ best")}
    mode = "teacher" if rnd == 0 else "greedy"
    return (f"{scenario.training.teacher} teacher" if rnd == 0 else "imitation",
            {f"{mode} ÷ {'plan' if jobshop else 'rule'}": statistics.mean(m[mode] for m in measured)})


def training_fits(scenario: Scenario) -> dict:
    """The shapes a policy trained on ``scenario``'s random shops has seen."""
    machines = [m for _, m in scenario.training.jobshop_sizes]
    return {"steps": ["op"], "device_types": [min(machines), max(machines)], "instances": [1, 1]}


def check_imitable(scenario: Scenario, init) -> None:
    if scenario.training.teacher in ITSELF and init is None:
        raise ValueError(
            f"{scenario.name}: training.teacher '{scenario.training.teacher}' improves a policy on its own rollouts, "
            f"so it starts from one: pass --init POLICY.zip (e.g. one trained with training.teacher: cp-sat or "
            f"best-rule)")
    if scenario.training.teacher == "cp-sat" and (scenario.jobshop is None or not scenario.training.jobshop_sizes):
        raise ValueError(
            f"{scenario.name}: training.teacher 'cp-sat' learns from CP-SAT's schedules of random job shops, so it "
            f"needs a job-shop scenario (jobshop: file) with training.jobshop_sizes; for any other lab use "
            f"training.teacher: best-rule, or training.method: ppo")
    default = scenario.training.teacher_default
    if default is not None and default not in rules_for(scenario):
        raise ValueError(f"{scenario.name}: training.teacher_default {default!r} is not one of the rules that teach "
                         f"({', '.join(rules_for(scenario))})")


class StartWorse(Exception):
    """The policy training was to start from did worse than ``worse_above`` × the best rule at the start."""

    def __init__(self, score: float, basis: JudgeBasis) -> None:
        super().__init__(f"the start scored {score:.3f} × the best rule")
        self.score, self.basis = score, basis  # basis: what the judge measured, for a training that follows


def train_by_imitation(scenario: Scenario, steps: int, out, seed: int = 0, workers: int = 2,
                       eval_every: int = 20_000, on_progress=None, eval_seeds=None, held_out_count: int | None = None,
                       max_samples: int | None = None, epochs: int = 3, learning_rate: float | None = None,
                       init=None, encoding: str = ENCODING, worse_above: float | None = None,
                       judged: JudgeBasis | None = None):
    """Rounds of about ``eval_every`` labelled decisions each, ``steps`` in all; the policy is evaluated after every
    round and the best kept (``agents.train_scheduler.Judge``). ``init``: a policy file to start from; with
    ``worse_above``, ``StartWorse`` is raised if it scores above that at the start. ``judged``: the Judge's
    measures of the lab, made already. The most
    recent ``max_samples`` labels are trained on (by default 400,000 from a teacher; from the policy itself, the
    last three rounds', as older ones are an older policy's best)."""
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.candidate_policy import CandidatePolicy
    from agents.scheduling_env import SchedulingEnv
    from twin import read_meta

    check_imitable(scenario, init)
    itself = scenario.training.teacher in ITSELF
    gradient = scenario.training.teacher == "self-pg"
    max_samples = max_samples or (3 * eval_every if itself else 400_000)
    # a trained policy is tuned, not retaught; a policy gradient, noisier than a label, in smaller steps
    learning_rate = learning_rate or (1e-4 if gradient else 2e-4 if init is not None else 1e-3)
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    host = DummyVecEnv([lambda: SchedulingEnv(scenario, randomise=False, encoding=encoding)])  # SB3's spaces
    model = MaskablePPO(CandidatePolicy, host, seed=seed, verbose=0, device="cpu")
    host.close()
    net = model.policy.action_net
    fits = None
    if init is not None:
        net.load_state_dict(initial_state(Path(init), scenario, encoding, part="action_net"))
        try:
            fits = fits_of(read_meta(Path(init)), str(Path(init).with_suffix(".json")))
        except ValueError as exc:
            raise PluginError(str(exc)) from None
    optimizer = torch.optim.Adam(net.parameters(), lr=learning_rate)
    judge = Judge(scenario, out, encoding, eval_seeds or EVAL_SEEDS, held_out_count, on_progress, judged,
                  method="imitate", teacher=scenario.training.teacher, **started_from(init))
    scenario = with_teacher_default(scenario, judge.best_rule)
    jobshop = bool(scenario.training.jobshop_sizes and not scenario.campaigns) if itself else \
        scenario.training.teacher == "cp-sat"
    task = self_task if itself else shop_task if jobshop else lab_task
    if jobshop:
        fits = widen(fits, training_fits(scenario))
    trained_on = judge.trained_on = Observed(FEATURES)  # the range of what it learns from, kept with the policy
    started = read_meta(Path(init)) if init is not None else {}
    if "observed" in started and started.get("signature", {}).get("encoding") == encoding:  # and what it started from saw
        try:
            trained_on.merge(Observed.from_meta(started["observed"], FEATURES, str(Path(init).with_suffix(".json"))))
        except ValueError as exc:
            raise PluginError(str(exc)) from None
    if init is not None:
        shipped = worse_above is not None  # the lab says nothing of training: the general policy is the start
        start = judge(model, 0, fits, f"start ({Path(init).name}, shipped)" if shipped else "start (--init)")
        if shipped and start["score"] > worse_above:
            raise StartWorse(start["score"], judge.basis)
    data: list[Sample] = []
    done, rnd, shop, per_shop, counted = 0, 0, seed * 1_000_000, 150.0, 0  # counted: lab runs whose labels were counted
    with workers_for(workers) as pool:
        while done < steps:
            left = steps - done
            modes = ("self",) if itself else ("teacher",) if rnd == 0 else ("greedy", "sample", "sample")
            if rnd > 0 and left < max(min(eval_every, done) / 4, per_shop * len(modes) * workers / 2):
                break  # rounds gather about as many labels as asked: a last round of a few would cost a whole fit
            want = left if left < 1.5 * eval_every else eval_every
            state = None if rnd == 0 and init is None else {k: v.detach().clone() for k, v in net.state_dict().items()}
            beta = 0.0 if rnd == 0 else 0.5 ** rnd
            got, asked, measured, losses = 0, 0, [], []
            while got < want:  # a few labs, then more as their labels are counted; for self-pg, a gradient pass each
                if gradient:
                    labs = PG_LABS
                    state = {k: v.detach().clone() for k, v in net.state_dict().items()}
                elif counted == 0:  # what a lab gives is a guess (150) until some labs are counted: one each
                    labs = workers
                else:  # counted on a few labs only (random shops differ in size): half of what is left, then the rest
                    share = 2 if counted < 4 * workers else 1
                    labs = max(workers, round((want - got) / (per_shop * len(modes)) / share))
                arrived: list[tuple[int, tuple[list[Sample], dict]]] = []
                for i, result in pool.imap_unordered(
                        numbered, [(task, i, (scenario, shop + i, modes, state, beta, encoding)) for i in range(labs)]):
                    arrived.append((i, result))
                    got += len(result[0])
                    if on_progress:
                        on_progress(min(steps, done + got), None)
                fresh: list[Sample] = []
                for _, (samples, info) in sorted(arrived, key=lambda a: a[0]):  # as asked, not as the workers ended:
                    fresh += samples  # a seed trains the same policy again
                    for sample in samples:
                        trained_on.add(sample.rows, sample.glob)
                    measured.append(info)
                    if "shape" in info:
                        fits = widen(fits, info["shape"])
                shop += labs
                asked += labs
                counted += labs * len(modes)
                if not gradient:
                    data += fresh
                    per_shop = got / (asked * len(modes))
                    if want - got < per_shop * len(modes) * workers / 2:
                        break  # more labs would overshoot by more than they fill
                    continue
                net.train()
                losses.append(fit(net, fresh, 1, optimizer, batch_size=PG_BATCH, seed=seed + shop))
                net.eval()
            done += got
            if gradient:  # fitted as it went
                loss = statistics.mean(losses)
                policy, seen = "policy gradient", {"sampled ÷ best": statistics.mean(m["sampled ÷ best"]
                                                                                     for m in measured)}
            else:
                data = data[-max_samples:]
                net.train()
                loss = fit(net, data, epochs, optimizer, seed=seed + rnd)
                net.eval()
                policy, seen = _round_seen(scenario, rnd, itself, jobshop, measured)
            judge(model, done, fits, f"{policy} (loss {loss:.3f})", seen)
            rnd += 1
    return out.with_suffix(".zip")
