"""`twin.run` from Python as a notebook calls it: a scenario built as a mapping, keywords that are not its own."""

import copy
from pathlib import Path

import pytest
import yaml

import twin
from twin.core.errors import ScenarioError

ROOT = Path(__file__).resolve().parents[2]
FLAKY = ROOT / "scenarios" / "flaky_lab.yaml"


def test_a_scenario_given_as_the_mapping_its_file_holds_runs_as_the_file_does(tmp_path):
    raw = yaml.safe_load(FLAKY.read_text())
    kept = copy.deepcopy(raw)
    small = {"campaign.budget": 8}
    from_mapping = twin.run(raw, journal=tmp_path / "m.db", seed=4, overrides=small)
    from_file = twin.run(FLAKY, journal=tmp_path / "f.db", seed=4, overrides=small)
    assert (from_mapping.scenario, from_mapping.done, from_mapping.lab_hours) == \
        (from_file.scenario, from_file.done, from_file.lab_hours)
    assert raw == kept  # the overrides went into a copy


def test_numbers_and_paths_a_notebook_computes_are_taken_as_the_file_would_give_them():
    """numpy's integers are no ``int``: `devices.reactor.instances: Input should be a valid integer (got
    np.int64(2))` refused a lab built with numpy, and a path to a job shop was no text."""
    import numpy as np

    raw = yaml.safe_load(FLAKY.read_text())
    kept = copy.deepcopy(raw)
    raw["devices"]["reactor"]["instances"] = np.int64(2)
    raw["chemistry"]["parameters"]["temperature_k"]["low"] = np.float32(raw["chemistry"]["parameters"][
        "temperature_k"]["low"])
    raw["workflow"] = tuple(raw["workflow"])
    given = twin.prepare(raw, seed=np.int64(4), overrides={"campaign.budget": np.int64(8)})
    assert (given.devices["reactor"].instances, given.campaign.seed, given.campaign.budget) == (2, 4, 8)
    assert type(given.devices["reactor"].instances) is int and len(given.workflow) == len(kept["workflow"])
    assert raw["devices"]["reactor"]["instances"] == np.int64(2)  # the caller's mapping is left as it was
    shop = twin.prepare({"name": "shop", "jobshop": {"file": ROOT / "scenarios" / "jobshop" / "la01.txt"}})
    assert sorted(shop.devices) == [f"m{i}" for i in range(5)]
    raw["campaign"]["planner_options"] = {"box": raw}
    with pytest.raises(ScenarioError, match="it holds itself"):  # RecursionError deep inside, before
        twin.prepare(raw)
    deep: dict = {}
    raw["campaign"]["planner_options"] = deep
    for _ in range(5000):
        deep["a"] = deep = {}
    with pytest.raises(ScenarioError, match="nested more than 32 levels deep"):  # as a file is
        twin.prepare(raw)


def test_a_field_set_from_python_is_checked_as_the_files_would_be():
    """`s.campaign.budget = -3` on a loaded scenario was taken as it was, and the run proposed nothing."""
    from pydantic import ValidationError

    s = twin.load_scenario(FLAKY)
    with pytest.raises(ValidationError, match=r"budget\n.*greater than"):
        s.campaign.budget = -3
    with pytest.raises(ValidationError, match=r"instances"):
        s.devices["reactor"].instances = "two"
    s.campaign.budget = 3
    assert twin.run(s, bus="memory").proposed == 3


def test_a_mapping_with_a_problem_is_named_as_a_mapping_with_the_field():
    raw = yaml.safe_load(FLAKY.read_text())
    raw["devices"]["reactor"]["instances"] = "two"
    with pytest.raises(ScenarioError) as caught:
        twin.prepare(raw)
    assert "the scenario 'flaky_lab' (a mapping)" in str(caught.value)
    assert "devices.reactor.instances" in str(caught.value)
    with pytest.raises(ScenarioError, match=r"the scenario \(a mapping\).*\n.*name: required"):
        twin.prepare({"devices": {}})


def test_a_scenario_field_given_as_a_keyword_is_named_in_full():
    """`twin.run(f, budget=5)` said "prepare() got an unexpected keyword argument 'budget'"."""
    with pytest.raises(TypeError, match=r"unexpected keyword 'budget'; .* overrides=\{'campaign.budget': 5\}"):
        twin.run(FLAKY, budget=5)
    with pytest.raises(TypeError, match=r"unexpected keyword 'colour'; scenario fields go in overrides="):
        twin.run(FLAKY, colour="red")
    with pytest.raises(TypeError, match=r"overrides must be a dict .* \(got list\)"):
        twin.run(FLAKY, overrides=["campaign.budget=5"])
    # the keyword won without a word, where `twin run --seed 3 --set campaign.seed=5` is refused
    with pytest.raises(TypeError, match=r"seed=3 and overrides\['campaign.seed'\]=5 disagree"):
        twin.run(FLAKY, seed=3, overrides={"campaign.seed": 5})
    with pytest.raises(TypeError, match=r"bus='memory' and overrides\['bus.kind'\]='zenoh' disagree"):
        twin.prepare(FLAKY, bus="memory", overrides={"bus.kind": "zenoh"})
    assert twin.prepare(FLAKY, seed=3, overrides={"campaign.seed": 3}).campaign.seed == 3


def test_the_gym_environments_take_a_mapping_too():
    import gymnasium as gym

    import agents

    assert "labtwin/Scheduling-v0" in gym.registry and agents.ENVS
    raw = yaml.safe_load(FLAKY.read_text())
    raw["devices"]["reactor"]["instances"] = 5
    env = gym.make("labtwin/Scheduling-v0", scenario=raw, randomise=False)
    try:
        assert env.unwrapped.base.devices["reactor"].instances == 5
    finally:
        env.close()


def test_a_policy_description_is_read_from_a_path_given_as_text():
    """`twin.read_meta("agents/policies/x.zip")` was an AttributeError ('str' has no with_suffix)."""
    policy = "agents/policies/jobshop_scheduler.zip"
    assert twin.read_meta(str(ROOT / policy)) == twin.read_meta(ROOT / policy)
    assert twin.read_meta(str(ROOT / policy))["kind"] == "scheduler"
