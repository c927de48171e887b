"""The rl planner: its environment is a valid gymnasium env, short training improves it, and the
shipped policy proposes valid, non-duplicate experiments in a campaign."""

import tempfile
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from agents.planning_env import PlanningEnv, signature
from agents.rl_planner import RlPlanner
from agents.train_planner import evaluate, train_planner
from twin.campaign.decisions import Outcome
from twin.core.errors import PluginError
from twin.runtime.lab import prepare
from twin.tools.planner_bench import trial
from twin.learning.policies import load_policy
from twin.scenario.targets import score

ROOT = Path(__file__).resolve().parents[2]
POLICY = ROOT / "agents" / "policies" / "quantum_dots.zip"
torch.set_num_threads(1)


@pytest.fixture(scope="module")
def qd():
    return prepare(ROOT / "scenarios" / "quantum_dots.yaml")


def test_the_registered_planning_env_passes_the_gymnasium_checker(qd):
    env = gym.make("agents.planning_env:labtwin/Planning-v0", scenario=qd)
    check_env(env.unwrapped, skip_render_check=True)


def test_the_same_seed_gives_the_same_episode(qd):
    def episode(seed):
        env = PlanningEnv(qd)
        obs, _ = env.reset(seed=seed)
        env.action_space.seed(seed)
        out = [obs.tolist()]
        for _ in range(5):
            out.append(env.step(env.action_space.sample())[0].tolist())
        return out

    assert episode(3) == episode(3)
    assert episode(3) != episode(4)


def test_the_random_baseline_is_the_same_in_every_training(qd):
    from agents.train_planner import random_moves

    # the curve's first row is what PPO is measured against: drawn anew in each run it moved 0.23 - 0.33
    assert evaluate(qd, random_moves, episodes=6) == evaluate(qd, random_moves, episodes=6)


def test_a_lab_the_planner_cannot_learn_is_refused_before_any_progress_is_shown(tmp_path):
    from tests.conftest import twin_cli

    res = twin_cli("train", ROOT / "scenarios" / "jobshop.yaml", "--agent", "planner", "--steps", "10",
                   "--out", tmp_path / "p.zip")
    assert res.exit_code == 2
    assert "the rl planner learns to reach the scenario's targets, and it has none" in " ".join(res.stderr.split())
    assert "training the planner" not in res.stderr  # no bar at 0/10 for a training that never starts
    assert not (tmp_path / "p.zip").exists()


@pytest.mark.parametrize("change, says", [
    ({"chemistry.targets": [{"name": "heavy", "outputs": {"mass_mgg": {"min": 10}}}]},  # the balance declares none
     "read (mass_mgg) as a finite number, so the planner would learn nothing (their steps gave "),
    ({"devices.synthesiser.envelope": {"temperature_c": {"low": 220, "high": 221},
                                       "concentration_mm": {"low": 1, "high": 1.2}}},
     "(the last was refused: "),
])
def test_a_lab_where_no_experiment_is_scored_is_refused_before_training(tmp_path, change, says):
    """A target on an output no step gives (a typo), or a box the devices refuse nearly everywhere: every reward was
    the same, and `twin train --agent planner` went on for all its steps to a policy that learnt nothing, printing
    "success 0" with no word of why."""
    import yaml
    from tests.conftest import twin_cli

    raw = yaml.safe_load((ROOT / "scenarios" / "quantum_dots.yaml").read_text())
    raw["devices"]["balance"] = {"driver": "tests.agents.test_rl_planner:Balance", "steps": ["weigh"],
                                 "duration": {"mean_s": 60}}
    raw["workflow"].insert(1, {"step": "weigh", "device": "balance", "params": {"settle_s": 30}})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    lab = prepare(path, overrides=change)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(lab.model_dump(mode="json", exclude_none=True)))
    res = twin_cli("train", tmp_path / "bad.yaml", "--agent", "planner", "--steps", "1000", "--out", tmp_path / "p.zip")
    said = " ".join(res.stderr.split())
    assert res.exit_code != 0 and says in said, said
    assert "training the planner" not in res.stderr and not (tmp_path / "p.zip").exists()


def test_short_ppo_training_improves_its_own_return_and_leaves_no_log_directory(qd, tmp_path, monkeypatch):
    from stable_baselines3 import PPO

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # where SB3's default logger makes SB3-<time>/
    untrained = PPO("MlpPolicy", PlanningEnv(qd), seed=0, device="cpu")
    before = evaluate(qd, lambda o, _: untrained.predict(o, deterministic=True)[0], episodes=12)
    path = train_planner(qd, 8192, tmp_path / "p.zip", envs=4, eval_every=8192)
    model = load_policy(path, "planner", signature(list(qd.chemistry.parameters), ["peak_nm"]))
    after = evaluate(qd, lambda o, _: model.predict(o, deterministic=True)[0], episodes=12)
    assert after["return"] > before["return"] + 0.5, (before, after)
    assert after["success"] > before["success"]
    assert not list(tmp_path.glob("SB3-*"))


def test_the_policy_proposes_inside_the_box_and_never_repeats_a_pending_point(qd):
    box = qd.chemistry.parameters
    planner = RlPlanner(box, seed=1, targets=qd.chemistry.targets, policy=str(POLICY))
    history = [Outcome({"concentration_mm": 5.0 + i, "temperature_c": 250.0 + 5 * i, "time_s": 100.0 + 20 * i},
                       {"peak_nm": 500.0 + 10 * i}, None) for i in range(5)]
    pending = [p.params for p in planner.propose(4, history, [])]
    batch = [p.params for p in planner.propose(6, history, pending)]
    for p in pending + batch:
        assert all(box[k].low <= v <= box[k].high for k, v in p.items())
    keys = [tuple(round(v, 6) for v in p.values()) for p in pending + batch]
    assert len(set(keys)) == len(keys)


def test_a_failed_synthesis_gets_an_alternative_not_a_repeat(qd):
    planner = RlPlanner(qd.chemistry.parameters, seed=2, targets=qd.chemistry.targets[:1], policy=str(POLICY))
    history = [Outcome({"concentration_mm": 20.0, "temperature_c": 280.0, "time_s": 300.0}, {"peak_nm": 600.0}, None)]
    history += [Outcome({"concentration_mm": 3.0 + i, "temperature_c": 240.0, "time_s": 50.0}, {"peak_nm": 480.0}, None)
                for i in range(3)]
    first = planner.propose(1, history, [])[0].params
    failed = history + [Outcome(first, None, None, reason="synthesis failed")]
    second = planner.propose(1, failed, [])[0].params
    assert second != first


def test_a_campaign_with_the_rl_planner_reaches_every_target(qd):
    result = trial(qd, f"rl:{POLICY}", seed=0)
    assert result.reached, result
    assert result.experiments < qd.campaign.budget


def test_a_missing_or_mismatched_policy_is_a_clear_error(qd):
    with pytest.raises(PluginError, match="twin train"):
        RlPlanner(qd.chemistry.parameters, seed=0, targets=qd.chemistry.targets)
    cat = prepare(ROOT / "scenarios" / "catalyst.yaml")
    with pytest.raises(PluginError, match="different lab.*parameters"):
        RlPlanner(cat.chemistry.parameters, seed=0, targets=cat.chemistry.targets, policy=str(POLICY))


def test_the_env_scores_what_the_targets_score(qd):
    env = PlanningEnv(qd, random_goals=0.0)
    _, info = env.reset(seed=0, options={"target": qd.chemistry.targets[0]})
    assert info["distance"] == score(env._best.outputs, qd.chemistry.targets[0])


class HotKiln:
    """A furnace (the docs' kind of driver): over its limit it refuses for good; the first time, it is warming up."""

    labtwin_api = 1
    capabilities = frozenset({"anneal"})
    outputs = frozenset({"anneal_c"})
    option_names = frozenset({"max_c"})
    asked: list = []

    def __init__(self, setup):
        self.max_c, self.warm = float(setup.options.get("max_c", 900)), False

    async def run(self, step, params, sample, ctx):
        from twin import Refused, StepResult

        HotKiln.asked.append(ctx.clock.now())
        if params["anneal_c"] > self.max_c:
            raise Refused(f"{params['anneal_c']:.0f} C is over {self.max_c:.0f} C", infeasible=True)
        if not self.warm:
            self.warm = True
            raise Refused("warming up", infeasible=False)
        await ctx.clock.sleep(600)
        return StepResult({"anneal_c": params["anneal_c"]}, sample)

    async def safe_state(self):
        self.warm = False


def kiln_lab(max_c=850):
    return prepare(ROOT / "scenarios" / "bandgap.yaml", overrides={
        "devices.kiln": {"driver": "tests.agents.test_rl_planner:HotKiln", "instances": 1, "steps": ["anneal"],
                         "duration": {"mean_s": 600}, "options": {"max_c": max_c}},
        "chemistry.parameters.anneal_c": {"low": 400, "high": 950},
        "workflow": [{"step": "synthesise", "device": "synthesiser"}, {"step": "anneal", "device": "kiln"},
                     {"step": "measure", "device": "spectrometer"}],
        "orchestrator.retry": {"max_attempts": 3, "backoff_s": 120}})


def test_a_refusal_in_the_planning_env_is_taken_as_a_campaign_takes_it():
    """A driver's Refused stopped training with 'Error: warming up' (or its limit's words): the env now waits
    out a 'not now' and scores an experiment refused for good as one with nothing measured."""
    from twin import open_workcell

    lab = kiln_lab()
    cell = open_workcell(lab)
    HotKiln.asked.clear()
    ok = cell.run({**{n: p.low for n, p in lab.chemistry.parameters.items()}, "anneal_c": 700})
    assert not ok.infeasible and ok.outputs and len(HotKiln.asked) == 2
    assert HotKiln.asked[1] - HotKiln.asked[0] == 120  # asked again after the retry back-off, in lab time
    hot = cell.run({**{n: p.low for n, p in lab.chemistry.parameters.items()}, "anneal_c": 900})
    assert hot.outputs == {} and hot.infeasible == "kiln refused 'anneal': 900 C is over 850 C"
    env = PlanningEnv(kiln_lab(max_c=600))  # most of the box too hot
    check_env(env, skip_render_check=True)
    measured, run = [], env.workcell.run
    env.workcell.run = lambda params: measured.append(run(params)) or measured[-1]
    env.action_space.seed(3)
    env.reset(seed=3)
    rewards = [env.step(env.action_space.sample())[1] for _ in range(30)]
    assert any(m.infeasible for m in measured) and any(not m.infeasible for m in measured)
    assert all(r == r and abs(r) < 100 for r in rewards)  # finite, though some experiments measured nothing


class Balance:
    """Weighs the sample and hands it on as it was: `StepResult(outputs, None)`, as docs/drivers.md allows."""

    labtwin_api = 1
    capabilities = frozenset({"weigh"})
    needs_sample = frozenset({"weigh"})
    makes_sample: frozenset = frozenset()

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        from twin import Refused, StepResult

        if not sample or "id" not in sample:  # the lab names each sample it carries (docs/drivers.md)
            raise Refused(f"nothing on the balance, or not the lab's: {sample!r:.60}", infeasible=True)
        await ctx.clock.sleep(params["settle_s"])
        return StepResult({"mass_mg": 12.5}, None)

    async def safe_state(self):
        pass


def test_a_workcell_runs_an_experiment_as_a_campaign_does():
    """The planning env's workcell kept only the last step's outputs (a rinse after the measurement left the planner
    nothing to learn from: `twin train --agent planner` scored every experiment as measuring nothing), gave each
    step the experiment's parameters without the step's own, lost the sample after a step that hands it on as
    given (`None`), gave a sample no id, and sent a device what its envelope keeps it from."""
    from twin import open_workcell

    box = {n: p.model_dump() for n, p in kiln_lab().chemistry.parameters.items() if n != "anneal_c"}
    lab = prepare(kiln_lab(), overrides={
        "chemistry.parameters": box,
        "devices.balance": {"driver": "tests.agents.test_rl_planner:Balance", "steps": ["weigh"],
                            "duration": {"mean_s": 0, "plus_param": "settle_s"}},
        "devices.washer": {"driver": "machine", "steps": ["rinse"], "duration": {"mean_s": 300}},
        "workflow": [{"step": "synthesise", "device": "synthesiser"},
                     {"step": "anneal", "device": "kiln", "params": {"anneal_c": 700}},
                     {"step": "weigh", "device": "balance", "params": {"settle_s": 45}},
                     {"step": "measure", "device": "spectrometer"}, {"step": "rinse", "device": "washer"}]})
    at = {n: p.low for n, p in lab.chemistry.parameters.items()}
    cell = open_workcell(lab)
    cell.run(at)  # the kiln warms up
    measured = cell.run(at)
    assert not measured.infeasible and not measured.failed, measured
    assert measured.outputs["anneal_c"] == 700 and measured.outputs["mass_mg"] == 12.5, measured
    assert set(measured.outputs) >= {"band_gap_ev", "edge_nm"} and "spectrum" not in measured.outputs, measured
    fenced = open_workcell(prepare(kiln_lab(), overrides={"devices.kiln.envelope": {"anneal_c": {"low": 0,
                                                                                              "high": 800}}}))
    HotKiln.asked.clear()
    over = fenced.run({**{n: p.low for n, p in kiln_lab().chemistry.parameters.items()}, "anneal_c": 820})
    assert over.infeasible == "anneal_c 820 is outside devices.kiln.envelope.anneal_c [0, 800]" and not HotKiln.asked


def test_a_driver_that_is_never_ready_is_named_in_a_workcell():
    from twin import DriverError, open_workcell

    lab = kiln_lab()
    cell = open_workcell(lab)
    cell.drivers["kiln"].warm = False
    cell.drivers["kiln"].run = lambda *a: HotKiln.run(type("Cold", (), {"warm": False, "max_c": 850})(), *a)
    with pytest.raises(DriverError, match="kiln driver answered 'not now' to 'anneal' 3 times in a row in a "
                                          "workcell \\(last: warming up\\)"):
        cell.run({**{n: p.low for n, p in lab.chemistry.parameters.items()}, "anneal_c": 700})


class CloggingKiln(HotKiln):
    """A driver whose step fails (raises), as the docs' faults do: every other attempt, and always above 900 C."""

    calls = 0

    async def run(self, step, params, sample, ctx):
        from twin import DriverError, StepResult

        CloggingKiln.calls += 1
        if params["anneal_c"] > 900 or CloggingKiln.calls % 2:
            raise DriverError("column clogged")
        await ctx.clock.sleep(600)
        return StepResult({"anneal_c": params["anneal_c"]}, sample)


def test_a_driver_fault_in_the_planning_env_is_taken_as_a_campaign_takes_it():
    """A driver's own error (`raise DriverError("column clogged")`, as docs/drivers.md has faults) ended `twin train
    --agent planner` with "error: column clogged". Now the step is tried again (a campaign retries it), and an
    experiment whose every attempt fails measures nothing, marked failed; only a driver that has failed every
    experiment so far (ten) stops the training, named."""
    from twin import DriverError, open_workcell

    lab = prepare(kiln_lab(), overrides={"devices.kiln.driver": "tests.agents.test_rl_planner:CloggingKiln"})
    cell = open_workcell(lab)
    at = {n: p.low for n, p in lab.chemistry.parameters.items()}
    CloggingKiln.calls = 0
    ok = cell.run({**at, "anneal_c": 700})
    assert ok.outputs and not ok.failed and CloggingKiln.calls == 2  # the first attempt failed, the second ran
    hot = cell.run({**at, "anneal_c": 920})
    assert hot.outputs == {} and hot.failed == "kiln failed 'anneal': DriverError: column clogged (3 attempts)"
    env = PlanningEnv(lab)
    env.action_space.seed(1)
    env.reset(seed=1)
    measured, run = [], env.workcell.run
    env.workcell.run = lambda params: measured.append(run(params)) or measured[-1]
    rewards = [env.step(env.action_space.sample())[1] for _ in range(30)]
    assert all(r == r and abs(r) < 100 for r in rewards)  # finite, though some experiments measured nothing
    assert any(m.failed for m in measured) and any(m.outputs for m in measured)
    broken = open_workcell(lab)  # one that has never measured anything
    with pytest.raises(DriverError, match="the first 10 experiments in a workcell all failed; the last: kiln failed "
                                          "'anneal'"):
        for _ in range(10):
            broken.run({**at, "anneal_c": 920})


def test_a_lab_with_people_trains_its_planner_their_steps_taking_their_expected_time():
    """staffed_lab's technician loads each rack (driver: operator): the planning env's workcell loaded 'operator' as
    a driver and `twin train scenarios/staffed_lab.yaml --agent planner` stopped with "unknown driver 'operator'"."""
    from twin import open_workcell

    lab = prepare(ROOT / "scenarios" / "staffed_lab.yaml")
    params = {n: (p.low + p.high) / 2 for n, p in lab.chemistry.parameters.items()}
    with_person = open_workcell(lab).run(params)
    alone = prepare(lab, overrides={"workflow": [w.model_dump() for w in lab.workflow if w.device != "technician"]})
    without = open_workcell(alone).run(params)
    assert with_person.outputs and with_person.outputs == without.outputs  # the rack changes nothing measured
    assert with_person.lab_s == pytest.approx(without.lab_s + lab.devices["technician"].duration.mean_s)
    check_env(PlanningEnv(lab), skip_render_check=True)


def test_a_lab_whose_experiments_are_planned_routes_is_refused_with_the_trainer_it_needs():
    """aspirin's synthesiser reacts the route its route planner gives: `twin train scenarios/aspirin.yaml --agent
    planner` ran ten experiments without one, all failing, and then advised fixing the driver."""
    with pytest.raises(ValueError, match=r"aspirin: its experiments are synthesis routes, which its route planner "
                                         r"plans .* twin train SCENARIO --agent route"):
        PlanningEnv(prepare(ROOT / "scenarios" / "aspirin.yaml"))
