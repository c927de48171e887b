"""A plugin's options read from its source: the typo check on planner options imports no planner to do it."""

import subprocess
import sys
from importlib.metadata import EntryPoint
from pathlib import Path

from twin.core import plugins

ROOT = Path(__file__).resolve().parents[2]

MODULE = '''
import a_module_that_is_not_installed  # never imported: the source is only read
from dataclasses import dataclass
from elsewhere import Imported


class Plain:
    def __init__(self, parameters, seed, alpha=1.0, *, beta=2, **_):
        pass


class Open:
    def __init__(self, parameters, seed, **options):
        pass


class Child(Plain):
    pass


@dataclass
class Fields:
    parameters: dict
    seed: int


def factory(parameters, seed, gamma=0):
    return Plain(parameters, seed)


class Made:
    def __new__(cls, parameters, seed, delta=0):
        return object.__new__(cls)

    def __init__(self, parameters, seed, delta=0):
        pass


class Wrapped:
    def __init__(self, parameters, seed):
        pass


Wrapped = factory


class Signed:
    __signature__ = None  # what inspect would read instead

    def __init__(self, parameters, seed):
        pass
'''


def test_a_constructors_names_are_read_from_its_source_or_left_to_an_import(tmp_path, monkeypatch):
    (tmp_path / "my_planners.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    names = ["Plain", "Open", "Child", "Fields", "factory", "Imported", "Missing", "Made", "Wrapped", "Signed"]
    eps = {n: EntryPoint(n, f"my_planners:{n}", "labtwin.planners") for n in names}
    monkeypatch.setattr(plugins, "installed", lambda kind: eps)
    read = {n: plugins.parameters_unimported("planners", n) for n in names}
    assert read == {"Plain": (["parameters", "seed", "alpha", "beta"], False), "Open": (["parameters", "seed"], True),
                    "Child": None, "Fields": None, "factory": (["parameters", "seed", "gamma"], False),
                    "Imported": None, "Missing": None, "Made": None, "Wrapped": None, "Signed": None}
    assert "a_module_that_is_not_installed" not in sys.modules


def test_each_shipped_planners_source_names_what_its_signature_does():
    from twin.runtime.assembly import PLANNER_ARGUMENTS, _options_not_taken

    for name in plugins.installed("planners"):
        named, takes_any = plugins.parameters_unimported("planners", name)
        _, loaded = _options_not_taken(plugins.load("planners", name), {}, PLANNER_ARGUMENTS)
        assert [n for n in named if n not in PLANNER_ARGUMENTS] == loaded and not takes_any, name


def test_a_scenarios_options_for_another_planner_import_none_of_the_planners():
    """quantum_dots' gp-bo options with `--planner random`: each installed planner was imported to see whether it
    takes n_init (scikit-learn, torch, RDKit: 2-3 s of a `twin run` that needs none of them)."""
    code = ("import sys\n"
            "from twin.runtime.lab import prepare\n"
            "from twin.runtime.assembly import make_planner\n"
            "s = prepare('scenarios/quantum_dots.yaml', overrides={'campaign.planner': 'random'})\n"
            "assert s.campaign.planner_options, s.campaign\n"
            "make_planner(s)\n"
            "print(sorted(m for m in ('sklearn', 'scipy.stats', 'torch', 'rdkit') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr
