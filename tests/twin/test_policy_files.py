"""A policy file from someone else: loading it runs none of its code, and a damaged one is a clear error."""

import base64
import io
import json
import os
import pickle
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.conftest import twin_cli
from twin import PluginError, load_scenario

ROOT = Path(__file__).resolve().parents[2]
POLICIES = ROOT / "agents" / "policies"


class _Runs:
    """Pickles as a call of ``os.system``: what a hostile file would put where SB3 keeps a space."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


def _rewritten(src: Path, out: Path, change) -> Path:
    """A copy of the policy ``src`` (and its description) whose ``data`` went through ``change``."""
    data = json.loads(zipfile.ZipFile(src).read("data"))
    change(data)
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(out, "w") as zout:
        for item in zin.infolist():
            zout.writestr(item, json.dumps(data) if item.filename == "data" else zin.read(item.filename))
    shutil.copy(src.with_suffix(".json"), out.with_suffix(".json"))
    return out


def _hostile(src: Path, out: Path, key: str, marker: Path) -> Path:
    def change(data):
        data[key][":serialized:"] = base64.b64encode(pickle.dumps(_Runs(f"touch {marker}"))).decode()
    return _rewritten(src, out, change)


@pytest.mark.parametrize("key", ["observation_space", "action_space", "policy_class", "lr_schedule"])
def test_a_scheduler_policy_that_would_run_a_command_is_refused_and_runs_nothing(tmp_path, key):
    from agents.rl_scheduler import RlScheduler

    marker = tmp_path / "ran"
    bad = _hostile(POLICIES / "jobshop_scheduler.zip", tmp_path / "bad.zip", key, marker)
    with pytest.raises(PluginError, match=rf"bad.zip: its '{key}' asks for posix.system.*does not run code"):
        RlScheduler(load_scenario(ROOT / "scenarios" / "jobshop.yaml"), policy=str(bad))
    assert not marker.exists()


def test_a_planner_policy_that_would_run_a_command_is_refused_and_runs_nothing(tmp_path):
    from agents.rl_planner import RlPlanner

    marker = tmp_path / "ran"
    bad = _hostile(POLICIES / "quantum_dots.zip", tmp_path / "bad.zip", "observation_space", marker)
    qd = load_scenario(ROOT / "scenarios" / "quantum_dots.yaml")
    with pytest.raises(PluginError, match="does not run code from a policy file"):
        RlPlanner(qd.chemistry.parameters, seed=0, targets=qd.chemistry.targets, policy=str(bad))
    assert not marker.exists()


def test_a_policy_class_that_is_not_a_policy_is_refused(tmp_path):
    """A class from an allowed package is not enough: it must be a policy, a buffer, a space or an activation."""
    from agents.rl_scheduler import RlScheduler

    def change(data):
        data["policy_class"][":serialized:"] = base64.b64encode(pickle.dumps(zipfile.ZipFile)).decode()
    bad = _rewritten(POLICIES / "jobshop_scheduler.zip", tmp_path / "bad.zip", change)
    with pytest.raises(PluginError, match=r"'policy_class' asks for zipfile.ZipFile"):
        RlScheduler(load_scenario(ROOT / "scenarios" / "jobshop.yaml"), policy=str(bad))


def test_every_shipped_policy_still_loads_and_decides_as_before():
    """The restricted reading gives what SB3's own unpickling gives, for every policy shipped."""
    from stable_baselines3.common.save_util import json_to_data

    from twin.learning.policy_file import safe_objects

    for path in sorted(POLICIES.glob("*.zip")):
        ours = safe_objects(path)
        theirs = json_to_data(zipfile.ZipFile(path).read("data").decode())
        assert ours and sorted(ours) == sorted(k for k, v in json.loads(zipfile.ZipFile(path).read("data")).items()
                                               if isinstance(v, dict) and ":serialized:" in v)
        for key, value in ours.items():
            assert repr(value) == repr(theirs[key]), (path.name, key)


@pytest.mark.parametrize("damage", ["not a zip", "no data", "garbled pickle", "description not an object",
                                    "description nested too deep", "data nested too deep"])
def test_a_damaged_policy_file_is_a_clear_error(tmp_path, damage):
    from agents.rl_scheduler import RlScheduler

    src, bad = POLICIES / "jobshop_scheduler.zip", tmp_path / "bad.zip"
    shutil.copy(src.with_suffix(".json"), bad.with_suffix(".json"))
    if damage == "not a zip":
        bad.write_text("weights")
    elif damage == "no data":
        with zipfile.ZipFile(src) as zin, zipfile.ZipFile(bad, "w") as zout:
            for item in zin.infolist():
                if item.filename != "data":
                    zout.writestr(item, zin.read(item.filename))
    elif damage == "garbled pickle":
        _rewritten(src, bad, lambda d: d["action_space"].update({":serialized:": "gASV////"}))
    elif damage == "data nested too deep":  # json.loads raises RecursionError, not ValueError
        with zipfile.ZipFile(src) as zin, zipfile.ZipFile(bad, "w") as zout:
            for item in zin.infolist():
                zout.writestr(item, b"[" * 100_000 if item.filename == "data" else zin.read(item.filename))
    else:
        shutil.copy(src, bad)
        bad.with_suffix(".json").write_text("[" * 100_000 if damage == "description nested too deep" else "[1, 2]")
    with pytest.raises(PluginError, match=r"bad\.(zip|json): not an SB3 policy file|bad.json: not a policy "
                                          r"description|bad.zip: its 'action_space' cannot be read"):
        RlScheduler(load_scenario(ROOT / "scenarios" / "jobshop.yaml"), policy=str(bad))


def test_weights_that_would_run_a_command_are_refused_without_torchs_advice_to_trust_them(tmp_path):
    """The weights (policy.pth, itself a zip around a pickle) are read as weights only; torch's error for a pickle
    of more than tensors advises loading it unchecked, which the message leaves out."""
    from agents.rl_scheduler import RlScheduler

    marker, src, bad = tmp_path / "ran", POLICIES / "jobshop_scheduler.zip", tmp_path / "bad.zip"
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(bad, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "policy.pth":
                weights = io.BytesIO()
                with zipfile.ZipFile(io.BytesIO(data)) as win, zipfile.ZipFile(weights, "w") as wout:
                    for w in win.infolist():
                        wout.writestr(w, pickle.dumps(_Runs(f"touch {marker}"), protocol=2) if w.filename.endswith("data.pkl")
                                      else win.read(w.filename))
                data = weights.getvalue()
            zout.writestr(item, data)
    shutil.copy(src.with_suffix(".json"), bad.with_suffix(".json"))
    with pytest.raises(PluginError) as refused:
        RlScheduler(load_scenario(ROOT / "scenarios" / "jobshop.yaml"), policy=str(bad))
    said = str(refused.value)
    assert "bad.zip: the policy's weights are damaged or hold more than tensors" in said
    assert "system" in said and "weights_only" not in said and "trusted source" not in said
    assert not marker.exists()


def test_twin_run_with_a_hostile_policy_says_why_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    bad = _hostile(POLICIES / "jobshop_scheduler.zip", tmp_path / "bad.zip", "observation_space", marker)
    res = twin_cli("run", "scenarios/jobshop.yaml", "--scheduler", f"rl:{bad}", "--journal", tmp_path / "j.db")
    assert res.exit_code == 2, res.stderr
    assert "does not run code from a policy file" in " ".join(res.stderr.split())
    assert not marker.exists()


# a fresh interpreter, which has imported nothing yet
def test_a_policy_loaded_to_decide_leaves_torchs_compiler_unimported_and_its_optimizer_still_steps():
    """Loading builds the policy's optimizer; torch's first optimizer call imports torch._dynamo (seconds), which
    a policy that only decides does not need. Its optimizer still works: ``--init`` trains from a loaded policy."""
    code = """
import sys, torch
from twin import load_scenario
from agents.rl_scheduler import RlScheduler
model = RlScheduler(load_scenario('scenarios/jobshop.yaml'), policy='agents/policies/jobshop_scheduler.zip').model
print('torch._dynamo' in sys.modules)
before = [p.detach().clone() for p in model.policy.parameters()]
sum(p.square().sum() for p in model.policy.parameters()).backward()
model.policy.optimizer.step()
print(any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters())))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.stdout.split() == ["False", "True"], res.stderr


def test_a_policy_file_that_would_unpack_to_gigabytes_is_refused_before_it_is_read(tmp_path):
    from agents.rl_scheduler import RlScheduler
    from twin.learning import policy_file

    src, bomb = POLICIES / "jobshop_scheduler.zip", tmp_path / "bomb.zip"
    shutil.copy(src.with_suffix(".json"), bomb.with_suffix(".json"))
    zeros = bytes(2**20)
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zout:
        for item in zin.infolist():
            if item.filename != "policy.pth":
                zout.writestr(item.filename, zin.read(item.filename))
        with zout.open("policy.pth", "w", force_zip64=True) as big:  # a few hundred kB on disk
            for _ in range(policy_file.MAX_UNPACKED_BYTES // len(zeros) + 1):
                big.write(zeros)
    assert bomb.stat().st_size < 2**20
    with pytest.raises(PluginError, match=r"bomb\.zip: would unpack to 513 MB, more than a policy file does"):
        RlScheduler(load_scenario(ROOT / "scenarios" / "jobshop.yaml"), policy=str(bomb))


def test_a_policy_description_of_gigabytes_is_refused_unread(tmp_path, monkeypatch):
    from agents.rl_scheduler import RlScheduler
    from twin.learning import policies

    src, bad = POLICIES / "jobshop_scheduler.zip", tmp_path / "bad.zip"
    shutil.copy(src, bad)
    shutil.copy(src.with_suffix(".json"), bad.with_suffix(".json"))
    monkeypatch.setattr(policies, "MAX_DESCRIPTION_BYTES", 100)  # as a 16 MB limit meets a 17 MB file
    with pytest.raises(PluginError, match=r"bad\.json: not a policy description \([\d,]+ bytes, more than a "
                                          r"description has"):
        RlScheduler(load_scenario(ROOT / "scenarios" / "jobshop.yaml"), policy=str(bad))


@pytest.mark.parametrize("piped", ["zip", "json"])
def test_a_named_pipe_for_a_policy_is_refused_not_waited_on(tmp_path, piped):
    """A named pipe nobody writes to, as a policy or its description: `twin run --scheduler rl:P.zip` blocked in
    open() until killed."""
    from agents.rl_scheduler import RlScheduler

    src, policy = POLICIES / "jobshop_scheduler.zip", tmp_path / "p.zip"
    for suffix in (".zip", ".json"):
        if suffix == f".{piped}":
            os.mkfifo(policy.with_suffix(suffix))
        else:
            shutil.copy(src.with_suffix(suffix), policy.with_suffix(suffix))
    with pytest.raises(PluginError, match=rf"p\.{piped} is a named pipe, not a file; policies are saved by"):
        RlScheduler(load_scenario(ROOT / "scenarios" / "jobshop.yaml"), policy=str(policy))


def test_a_named_pipe_for_a_stock_a_template_table_or_a_route_prior_is_refused(tmp_path):
    from agents.routes import stock, templates
    from agents.routes.policy import load_prior

    pipe = tmp_path / "pipe.csv"
    os.mkfifo(pipe)
    with pytest.raises(stock.StockError, match="pipe.csv is a named pipe, not a file; a stock file is CSV"):
        stock.load(pipe)
    with pytest.raises(templates.TemplateError, match="pipe.csv is a named pipe, not a file; give a template file"):
        templates.load(pipe)
    prior = tmp_path / "prior.pt"
    os.mkfifo(prior)
    prior.with_suffix(".json").write_text("{}")
    with pytest.raises(ValueError, match=r"prior\.pt is a named pipe, not a file; a route prior is a \.pt file"):
        load_prior(prior, templates.load())


class _KilledWhileSaving:
    """A model whose save is cut short half-way, as a training killed (or a full disk) while it saves would be."""

    def __init__(self, model) -> None:
        self.model = model

    def save(self, path) -> None:
        self.model.save(path)
        Path(path).write_bytes(Path(path).read_bytes()[:100])
        raise KeyboardInterrupt


def test_a_policy_save_cut_short_leaves_the_policy_saved_before_whole(tmp_path):
    from agents.rl_scheduler import RlScheduler
    from twin import read_meta, save_policy

    s = load_scenario(ROOT / "scenarios" / "jobshop.yaml")
    shipped = POLICIES / "jobshop_scheduler.zip"
    meta = read_meta(shipped)
    model = RlScheduler(s, policy=str(shipped)).model
    best = save_policy(model, tmp_path / "best.zip", "scheduler", s, meta["signature"], round=1)
    before = best.read_bytes(), best.with_suffix(".json").read_text()
    with pytest.raises(KeyboardInterrupt):
        save_policy(_KilledWhileSaving(model), best, "scheduler", s, meta["signature"], round=2)
    assert (best.read_bytes(), best.with_suffix(".json").read_text()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["best.json", "best.zip"]  # nothing half-written left
    RlScheduler(s, policy=str(best))  # and it loads


def test_a_policy_not_found_names_the_one_beside_it_likely_meant(monkeypatch):
    monkeypatch.chdir(ROOT)
    res = twin_cli("validate", "scenarios/flaky_lab.yaml", "--set", "campaign.scheduler=rl:agents/policies/flaky.zip")
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and ("policy agents/policies/flaky.zip does not exist (did you mean "
                                   "agents/policies/flaky_scheduler.zip?); train one") in said, said
