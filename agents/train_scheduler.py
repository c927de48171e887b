"""Train the RL scheduler in `labtwin/Scheduling-v0`, evaluated against every rule.

By the scenario's ``training.method``: MaskablePPO on the reward (``ppo``), or DAgger from a teacher
(``imitate``, ``agents.imitation``: CP-SAT's schedules of job shops, or the best rule of each lab drawn). Either way ``Judge`` evaluates the policy on the
scenario as written (fixed seeds the training never uses) and on held-out labs drawn from its ``training``
ranges, against every dispatching rule, and keeps the best.
"""

from __future__ import annotations

import logging
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from agents.candidates import ENCODING, FEATURES, Observed, fits_of, lab_shape, outside, trained_encoding, widen
from agents.candidates import signature as candidate_signature
from agents.judging import (EVAL_SEEDS, baselines, campaign, evaluate_rules, held_out_labs, objective,
                            reference_note, reference_outcome, score, solver_reference)
from agents.rl_scheduler import RlScheduler
from agents.sb3_logging import without_log_dir
from agents.scheduling_env import SchedulingEnv
from agents.scheduling_features import signature
from twin import Scenario, load_policy, save_policy

log = logging.getLogger(__name__)
CANDIDATE_SETTINGS = dict(n_steps=1024, batch_size=512, n_epochs=8, gamma=0.995, gae_lambda=0.95, learning_rate=1e-4,
                          ent_coef=0.01)
PPO_SETTINGS = dict(n_steps=512, batch_size=256, n_epochs=10, gamma=0.995, gae_lambda=0.95, learning_rate=3e-4,
                    ent_coef=0.01, policy_kwargs=dict(net_arch=[128, 128]))


#: where a lab's training starts by default (``general_start``), and the start's score (× the best rule's objective)
#: above which the lab learns the best rule instead: "the rule did better" (above the band called level)
GENERAL_POLICY = Path(__file__).parent / "policies" / "flaky_scheduler.zip"
FALL_BACK_ABOVE = 1.005


def started_from(init: Path | None) -> dict[str, Any]:
    """What a policy file records of the policy it was trained from: the file, and ``lineage``, every stage of
    training before this one (oldest first: method, teacher, steps, when saved)."""
    if init is None:
        return {}
    from twin import read_meta

    meta = read_meta(Path(init))
    stage = {k: meta[k] for k in ("method", "teacher", "steps", "saved") if k in meta}
    return {"init": str(init), "lineage": [*meta.get("lineage", []), stage]}


def judge_signature(scenario: Scenario, encoding: str) -> dict:
    return candidate_signature(scenario, encoding) if encoding.startswith("candidates") else signature(scenario)


def initial_state(init: Path, scenario: Scenario, encoding: str, part: str = "") -> dict[str, torch.Tensor]:
    """The policy state in ``init`` to start training from; a candidate policy of an earlier encoding
    (``agents.candidates.WIDTHS``) widened to this one, deciding as it did until trained further. ``part``: only
    that module's state (``action_net``: the candidate scorer)."""
    from twin import read_meta

    from agents.candidate_policy import widened
    from agents.candidates import WIDTHS

    trained = read_meta(Path(init)).get("signature", {}).get("encoding")
    if encoding.startswith("candidates") and trained in WIDTHS:
        state = widened(load_policy(Path(init), "scheduler", candidate_signature(scenario, trained)).policy.state_dict())
    else:
        state = load_policy(Path(init), "scheduler", judge_signature(scenario, encoding)).policy.state_dict()
    if not part:
        return state
    return {k.removeprefix(part + "."): v for k, v in state.items() if k.startswith(part + ".")}


@dataclass(frozen=True)
class JudgeBasis:
    """What a Judge measures once, before any policy: the rules on the lab, the held-out labs and the best rule's
    objective on each, and CP-SAT's reference."""

    rules: dict[str, dict]
    held_out: list[Scenario]
    rule_spans: list[float]
    solver: dict


class Judge:
    """Evaluates a policy in training and keeps the best: its objective (what the reward sums to: makespan,
    degraded samples and abandoned experiments, weighted by ``training.weights``) relative to the best rule's,
    averaged over the scenario as written and ``held_out_count`` labs drawn from its ``training`` ranges with
    seeds training never uses (by default 6, or for random job shops 4 per size listed — 24 for six sizes: with 6
    shops, which round was kept depended more on the shops drawn than on the policy). The curve reports makespan
    against the best rule too, so a trade is visible, and against CP-SAT (``solver_reference``)."""

    def __init__(self, scenario: Scenario, out: Path, encoding: str, eval_seeds=EVAL_SEEDS,
                 held_out_count: int | None = None, on_progress: Callable[[int, dict | None], None] | None = None,
                 basis: JudgeBasis | None = None, **extra: Any) -> None:
        """``basis``: what another Judge of the same lab, seeds and held-out count measured (the rules, the
        held-out labs, CP-SAT's reference), taken as it is rather than measured again."""
        self.scenario, self.out, self.encoding, self.eval_seeds = scenario, out, encoding, eval_seeds
        self.on_progress, self.extra = on_progress, extra
        self.sign = judge_signature(scenario, encoding)
        if on_progress:  # the lab is one it can train on: the bar starts before the rules are measured
            on_progress(0, None)
        self.basis = basis or self._measured(scenario, eval_seeds, held_out_count, on_progress)
        self.rules, self.held_out = self.basis.rules, self.basis.held_out
        self.rule_spans, self.solver = self.basis.rule_spans, self.basis.solver
        self.best_rule = min(self.rules, key=lambda r: self.rules[r]["objective"])
        self.best: float | None = None
        self.curve: list[dict] = []
        self.trained_on: Observed | None = None  # what a policy taught by labels saw in them (imitation adds it)
        if on_progress and basis is None:
            on_progress(0, {"policy": f"best rule: {self.best_rule}", **self.rules[self.best_rule]})

    @staticmethod
    def _measured(scenario: Scenario, eval_seeds, held_out_count: int | None,
                  on_progress: Callable[[int, dict | None], None] | None) -> JudgeBasis:
        rules = evaluate_rules(scenario, eval_seeds)
        if held_out_count is None:
            held_out_count = max(6, 4 * len(scenario.training.jobshop_sizes))
        held_out = held_out_labs(scenario, held_out_count)
        rule_spans = [min(objective(campaign(lab, 0, decide), lab) for decide in baselines(lab).values())
                      for lab in held_out]
        note = reference_note(scenario, held_out)
        if on_progress and note:
            on_progress(0, {"policy": note})
        solver = solver_reference(scenario, eval_seeds, held_out)
        outcome = reference_outcome(solver)
        if on_progress and outcome:
            on_progress(0, {"policy": outcome})
        return JudgeBasis(rules, held_out, rule_spans, solver)

    def __call__(self, model: Any, done: int, fits: dict | None, policy: str, seen: dict | None = None) -> dict:
        """``seen``: what training itself measured, reported first."""
        s, rules, best_rule = self.scenario, self.rules, self.best_rule
        observed = Observed(FEATURES) if self.encoding.startswith("candidates") else None
        decide = self._decider(model, s, observed)
        runs = [campaign(s, seed, decide) for seed in self.eval_seeds]
        result = {**(seen or {}), **score(runs, s)}
        result["vs best rule"] = result["makespan h"] / rules[best_rule]["makespan h"]
        ratios = [result["objective"] / rules[best_rule]["objective"]]
        result["objective vs best rule"] = ratios[0]
        held = [campaign(lab, 0, self._decider(model, lab, observed)) for lab in self.held_out]
        if held:  # labs it never trained on: each against the best rule there
            ratios += [objective(summary, lab) / ref for summary, lab, ref in zip(held, self.held_out, self.rule_spans)]
            result["held-out vs best rule"] = statistics.mean(ratios[1:])
        result["score"] = statistics.mean(ratios)
        if "plans" in self.solver:  # job shops: makespan ÷ CP-SAT's plan, the scenario and every held-out shop
            spans = [result["makespan h"]] + [summary.lab_hours for summary in held]
            result["vs cp-sat plan"] = statistics.mean(a / b for a, b in zip(spans, self.solver["plans"]))
        elif "online" in self.solver:
            result["vs cp-sat"] = objective(runs[0], s) / self.solver["online"]  # on the seed CP-SAT ran
        self.curve.append({"steps": done, **result})
        if self.best is None or result["score"] <= self.best:
            self.best = result["score"]
            seen_range = observed.merge(self.trained_on).to_meta() if observed is not None else None
            save_policy(model, self.out, "scheduler", s, self.sign, steps=done, rules=rules, fits=fits,
                        best_rule=best_rule, curve=self.curve, **({"observed": seen_range} if seen_range else {}),
                        **self.extra)
        if self.on_progress:  # after saving: what the user reads is on disk
            self.on_progress(done, {"policy": policy, **result})
        return result

    def _decider(self, model: Any, lab: Scenario, observed: Observed | None):
        """The policy in training deciding ``lab``, what it sees added to ``observed``: the range it is judged on,
        which its file records and a lab beyond it is held inside (``agents.candidates.Observed``)."""
        agent = RlScheduler.from_model(model, lab, self.encoding)
        agent.encoder.seen = observed
        return agent.decide


def train_scheduler(scenario: Scenario, steps: int, out: Path, seed: int = 0, envs: int = 2,
                    eval_every: int = 20_000, on_progress: Callable[[int, dict | None], None] | None = None,
                    eval_seeds=EVAL_SEEDS, encoding: str = "candidates", held_out_count: int | None = None,
                    init: Path | None = None, judged: JudgeBasis | None = None) -> Path:
    """Train by the scenario's ``training.method``: ``ppo`` (MaskablePPO in the environment) or ``imitate``
    (DAgger from ``training.teacher``, ``agents.imitation``). ``encoding``: ``candidates`` (the
    candidate-scoring policy) or ``slots`` (an MLP over the fixed grid, the baseline; PPO only). ``init``: a policy
    of the same encoding to start from (a candidate policy of an earlier version: trained on in its columns'
    meaning, ``agents.candidates.trained_encoding``). ``judged``: the Judge's measures of this lab, made already
    (``JudgeBasis``)."""
    general = general_start(scenario, encoding, init)
    if general is not None:
        return _from_general(scenario, general, steps, out, on_progress, seed=seed, envs=envs,
                             eval_every=eval_every, eval_seeds=eval_seeds, held_out_count=held_out_count)
    scenario = with_teacher(scenario)
    if scenario.campaigns:
        scenario = lab_training(scenario, encoding, init)
    if encoding == "candidates":
        from twin import read_meta

        encoding = trained_encoding(read_meta(Path(init)).get("signature", {}).get("encoding") if init else None)
        if encoding != ENCODING:
            log.warning("%s reads labs as %s: the policy trained from it keeps those columns, so that it starts "
                        "deciding as that one did (a policy trained afresh reads %s: counts as shares of the lab)",
                        init, encoding, ENCODING)
    if scenario.training.method == "imitate" and encoding.startswith("candidates"):
        from agents.imitation import train_by_imitation

        return train_by_imitation(scenario, steps, out, seed=seed, workers=envs, eval_every=eval_every,
                                  on_progress=on_progress, eval_seeds=eval_seeds, held_out_count=held_out_count,
                                  init=init, encoding=encoding, judged=judged)
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    torch.set_num_threads(1)
    venv = DummyVecEnv([lambda: SchedulingEnv(scenario, encoding=encoding) for _ in range(envs)])
    venv.seed(seed)
    if encoding.startswith("candidates"):
        from stable_baselines3.common.vec_env import VecNormalize

        from agents.candidate_policy import CandidatePolicy

        # labs of 36 and of 300 operations in one training: returns differ tenfold, so rewards are scaled by
        # a running estimate of the returns' spread (training only: the policy never sees rewards)
        venv = VecNormalize(venv, norm_obs=False, norm_reward=True, gamma=CANDIDATE_SETTINGS["gamma"])
        model = MaskablePPO(CandidatePolicy, venv, seed=seed, verbose=0, device="cpu", **CANDIDATE_SETTINGS)
    else:
        model = MaskablePPO("MlpPolicy", venv, seed=seed, verbose=0, device="cpu", **PPO_SETTINGS)
    without_log_dir(model)
    if init is not None:
        model.policy.load_state_dict(initial_state(init, scenario, encoding))
    judge = Judge(scenario, out, encoding, eval_seeds, held_out_count, on_progress, judged, method="ppo",
                  **started_from(init))
    done = 0
    try:
        while done < steps:
            chunk = min(eval_every, steps - done)
            model.learn(chunk, reset_num_timesteps=False)
            done += chunk
            fits = None
            for env in venv.unwrapped.envs:
                fits = widen(fits, env.fits) if env.fits else fits
            judge(model, done, fits, "maskable-ppo")
    finally:
        venv.close()  # stops the campaigns in the environments, also on Ctrl-C
    return out.with_suffix(".zip")


def _from_general(scenario: Scenario, general: Path, steps: int, out: Path,
                  on_progress: Callable[[int, dict | None], None] | None, **options: Any) -> Path:
    """Training from the shipped general policy (``general_start``), improved on the lab's own best runs; where it
    scores worse than the best rule at the start, the best rule learnt afresh instead — and the start kept if that
    ends no better."""
    import shutil
    import tempfile

    from agents.imitation import StartWorse, train_by_imitation

    def say(text: str) -> None:
        if on_progress:
            on_progress(0, {"policy": text})

    start = scenario.model_copy(update={"training": scenario.training.model_copy(update={"teacher": "self"})})
    start = lab_training(start, "candidates", general) if start.campaigns else start
    try:
        return train_by_imitation(start, steps, out, seed=options["seed"], workers=options["envs"],
                                  eval_every=options["eval_every"], on_progress=on_progress,
                                  eval_seeds=options["eval_seeds"], held_out_count=options["held_out_count"],
                                  init=general, encoding=trained_encoding(general_encoding()),
                                  worse_above=FALL_BACK_ABOVE)
    except StartWorse as worse:
        began, judged = worse.score, worse.basis
    say(f"the shipped general policy scores {began:.3f} × the best rule here: learning the best rule instead, "
        "from scratch")
    rule = scenario.model_copy(update={"training": scenario.training.model_copy(update={"teacher": "best-rule"})})
    files = [out.with_suffix(".zip"), out.with_suffix(".json")]  # the start, as its evaluation saved it
    with tempfile.TemporaryDirectory() as aside:
        for f in files:
            shutil.copy(f, aside)
        try:
            return train_scheduler(rule, steps, out, on_progress=on_progress, judged=judged, **options)
        finally:  # also when stopped: the best policy evaluated is the one left at --out
            if _best_score(files[0]) > began:
                for f in files:
                    shutil.copy(Path(aside) / f.name, f)
                say(f"kept the shipped general policy: its start ({began:.3f}) did better than the rule learnt")


def _best_score(policy: Path) -> float:
    """The best score on a policy file's curve (infinite for none, or no file)."""
    from twin import TwinError, read_meta

    try:
        scores = [c["score"] for c in read_meta(policy).get("curve", []) if isinstance(c.get("score"), (int, float))]
    except (OSError, ValueError, TwinError):  # read_meta's PluginError: none there, or not a description
        return float("inf")
    return min(scores, default=float("inf"))


def general_encoding() -> str | None:
    """The columns the shipped general policy reads (a training from it keeps them)."""
    from twin import read_meta

    return read_meta(GENERAL_POLICY).get("signature", {}).get("encoding")


def general_start(scenario: Scenario, encoding: str, init: Path | None) -> Path | None:
    """The shipped general policy, where ``scenario`` trains as by default (``training.teacher: auto``, by
    imitation, no ``--init``, not a job shop) and is a lab of the shapes that policy was trained on: the training
    starts from it and improves on the lab's own best runs (``self``), unless it does worse than the best rule at
    the start (then the best rule is learnt). On three labs of a stranger's, 20,000 steps each, against the best
    rule learnt from scratch: 0.902 against 1.003 × the best rule's objective, 0.986 against 1.013, and 1.000
    against 1.005 (docs/benchmarks.md)."""
    from twin import read_meta

    t = scenario.training
    if (init is not None or t.teacher != "auto" or t.method != "imitate" or encoding != "candidates"
            or scenario.jobshop is not None or not GENERAL_POLICY.exists()):
        return None
    fits = fits_of(read_meta(GENERAL_POLICY), str(GENERAL_POLICY.with_suffix(".json")))
    return None if not fits or outside(fits, lab_shape(scenario)) else GENERAL_POLICY


def lab_training(lab: Scenario, encoding: str, init: Path | None) -> Scenario:
    """A lab of several campaigns trains its one scheduler by imitation: of the best rule in each variant of the
    lab (``training.teacher: best-rule``), or of the policy's own best of ``training.samples`` runs (``self``, the
    default, from a policy: ``--init``). Its campaigns' steps are candidates of one question, which PPO's
    environment of one campaign does not pose."""
    t = lab.training
    fix = ("train it from a policy with --init P.zip (e.g. agents/policies/flaky_scheduler.zip), or with --set "
           "training.teacher=best-rule")
    if encoding != "candidates" or t.method == "ppo" or t.teacher == "cp-sat":
        raise ValueError(f"{lab.name}: the scheduler of a lab of several campaigns learns by imitation "
                         f"(training.teacher self or best-rule; here {encoding}, {t.method}, {t.teacher}): {fix}")
    teacher = t.teacher
    if teacher in ("self", "self-pg") and init is None:
        raise ValueError(f"{lab.name}: the scheduler of a lab of several campaigns improves on a policy's own best "
                         f"runs (training.teacher self): {fix}")
    return lab.model_copy(update={"training": t.model_copy(update={"method": "imitate", "teacher": teacher})})


def with_teacher(scenario: Scenario) -> Scenario:
    """``training.teacher: auto`` made concrete where the shipped general policy is not the start
    (``general_start``): a lab of several campaigns improves on its policy's own best runs; a job shop with random
    shops to draw learns CP-SAT's schedules; any other lab the best rule of each lab drawn (the one teacher every
    lab has)."""
    t = scenario.training
    if t.teacher != "auto":
        return scenario
    teacher = "self" if scenario.campaigns else \
        "cp-sat" if scenario.jobshop is not None and t.jobshop_sizes else "best-rule"
    return scenario.model_copy(update={"training": t.model_copy(update={"teacher": teacher})})


def train_slot_scheduler(scenario: Scenario, steps: int, out: Path, **kwargs: Any) -> Path:
    """`twin train --agent scheduler-slots`: the fixed-grid policy, kept as a baseline."""
    return train_scheduler(scenario, steps, out, encoding="slots", **kwargs)
