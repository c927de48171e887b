"""Trained policies on disk: an SB3 ``.zip`` with a ``.json`` beside it saying what it was trained for."""

from __future__ import annotations

import functools
import hashlib
import json
import pickle
import time
from pathlib import Path
from typing import Any

from twin.core.printable import shell_word
from twin.core.errors import PluginError
from twin.core.whole_files import written_whole
from twin.learning.policy_file import safe_objects
from twin.runtime.run_record import versions
from twin.scenario import Scenario
from twin.scenario.files import nearest_file, not_a_file

MAX_DESCRIPTION_BYTES = 16 * 2**20  # a policy's .json: a few kB as `twin train` writes it


def scenario_hash(scenario: Scenario) -> str:
    return hashlib.sha256(scenario.model_dump_json().encode()).hexdigest()[:16]


def save_policy(model: Any, path: Path, kind: str, scenario: Scenario, signature: dict[str, Any], **extra: Any) -> Path:
    """Save ``model`` with what it was trained for; ``signature`` is what a user of it must match."""
    path = path.with_suffix(".zip")
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"kind": kind, "algorithm": type(model).__name__, "scenario": scenario.name,
            "scenario_hash": scenario_hash(scenario), "signature": signature,
            "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "versions": versions(), **extra}
    # each whole or not at all: a training killed while it saves, or a lab loading the policy meanwhile, never
    # meets half a file, and the best policy saved before stays
    with written_whole(path) as partial:
        model.save(partial)
    write_description(path, meta)
    return path


def write_description(policy: Path, meta: dict[str, Any]) -> None:
    """The ``.json`` beside ``policy``, written whole."""
    with written_whole(policy.with_suffix(".json")) as partial:
        partial.write_text(json.dumps(meta, indent=2) + "\n")


def read_meta(path: str | Path) -> dict[str, Any]:
    """The description ``twin train`` saved beside the policy at ``path`` (its ``.json``)."""
    path = Path(path)
    side = path.with_suffix(".json")
    if not side.exists():
        raise PluginError(f"{path}: no {side.name} beside it; policies are saved by `twin train`")
    if why := not_a_file(side):
        raise PluginError(f"{side} {why}; policies are saved by `twin train`")
    try:
        if side.stat().st_size > MAX_DESCRIPTION_BYTES:
            raise ValueError(f"{side.stat().st_size:,} bytes, more than a description has: `twin train` writes a "
                             f"few kB, and {MAX_DESCRIPTION_BYTES:,} is the most read")
        meta = json.loads(side.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:  # the last: JSON nested too deep
        raise PluginError(f"{side}: not a policy description ({exc}); policies are saved by `twin train`") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("signature", {}), dict):
        raise PluginError(f"{side}: not a policy description (not an object with a signature); "
                          "policies are saved by `twin train`")
    return meta


def load_policy(path: str | Path, kind: str, signature: dict[str, Any]) -> Any:
    """The policy at ``path``, checked to be a ``kind`` policy trained for a lab of this ``signature``."""
    path = Path(path)
    if not path.exists():
        meant = nearest_file(path)
        raise PluginError(f"policy {path} does not exist{f' ({meant})' if meant else ''}; train one with `twin train "
                          f"SCENARIO --agent {kind} --out {shell_word(path)}`")
    if why := not_a_file(path):
        raise PluginError(f"{path} {why}; policies are saved by `twin train`")
    meta = read_meta(path)
    if meta.get("kind") != kind:
        raise PluginError(f"{path} is a {meta.get('kind')} policy, not a {kind} policy")
    trained = meta.get("signature", {})
    wrong = [f"{k}: trained {trained.get(k)!r}, here {v!r}" for k, v in signature.items() if trained.get(k) != _plain(v)]
    if wrong:
        raise PluginError(f"{path} was trained on {meta.get('scenario')!r} for a different lab ({'; '.join(wrong)}). "
                          f"Train one for this scenario with `twin train SCENARIO --agent {kind}`.")
    from sb3_contrib import MaskablePPO
    from stable_baselines3 import PPO

    algorithm: Any = {"PPO": PPO, "MaskablePPO": MaskablePPO}.get(meta.get("algorithm", "PPO"))
    if algorithm is None:
        raise PluginError(f"{path}: unknown algorithm {meta.get('algorithm')!r}")
    objects = safe_objects(path)  # SB3 would unpickle these itself, running whatever they ask
    _optimizer_without_dynamo()
    try:
        return algorithm.load(path, device="cpu", custom_objects=objects)
    except pickle.UnpicklingError as exc:  # torch's own words would suggest weights_only=False: running the file
        raise PluginError(f"{path}: the policy's weights are damaged or hold more than tensors, and labtwin runs no "
                          f"code a policy file holds (read as weights only: {_unpickler_said(exc)}); save it again with "
                          "`twin train`") from exc
    except Exception as exc:
        raise PluginError(f"{path}: the policy cannot be loaded ({type(exc).__name__}: {exc}); "
                          "save it again with `twin train`") from exc


def _unpickler_said(exc: Exception) -> str:
    """What torch's weights-only reader found, without the advice around it (to load the file unchecked)."""
    text = str(exc).partition("Check the documentation")[0]
    said = text.partition("WeightsUnpickler error:")[2] or (text.split("\n", 1)[1] if "\n" in text else "")
    return " ".join(said.partition("Please use")[0].split())[:200] or "not a pickle of tensors"


@functools.cache  # once per process: the classes are torch's, the same for every policy loaded
def _optimizer_without_dynamo() -> None:
    """Loading a policy builds its optimizer, whose methods torch wraps to keep ``torch.compile`` out of them;
    the first call imports ``torch._dynamo`` to do that: 2 s of a `twin run --scheduler rl:…` start here, for
    a policy that only decides. Nothing in labtwin compiles, so there is nothing to keep out: each wrapper is
    handed, as its cached disabled method, the method itself. Training still imports the compiler (``step``
    asks for it)."""
    import torch.optim
    from torch._compile import _disable_dynamo

    wrapper = _disable_dynamo(_plain).__code__  # the code every so wrapped method shares (_plain: any function)
    classes = [torch.optim.Optimizer]
    while classes:
        cls = classes.pop()
        classes.extend(cls.__subclasses__())
        for attr in vars(cls).values():
            method = getattr(attr, "__wrapped__", None)
            if method is not None and getattr(attr, "__code__", None) is wrapper:
                method.__dynamo_disable = method


def _plain(value: Any) -> Any:
    """As the value reads back from JSON (tuples become lists)."""
    return json.loads(json.dumps(value))
