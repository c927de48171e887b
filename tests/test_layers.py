"""The layers hold: the kernel's layers, its public API, and what may import zenoh and rerun."""

import shutil
import subprocess
import sys
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_import_contracts_hold():
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    res = subprocess.run([exe, "--no-cache"], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "6 kept, 0 broken" in res.stdout


def test_no_import_cycle_anywhere_in_the_kernel():
    graph = grimp.build_graph("twin", cache_dir=None)
    cycles = []
    for module in sorted(graph.modules):
        for imported in graph.find_modules_directly_imported_by(module):
            if imported != module and graph.chain_exists(imported=module, importer=imported):
                cycles.append(f"{module} -> {imported} -> ... -> {module}")
    # a package's __init__ importing its own submodules is not a cycle of two modules
    real = [c for c in cycles if not c.split(" -> ")[1].startswith(c.split(" -> ")[0] + ".")]
    assert real == [], "\n".join(real[:10])


def test_a_command_line_or_a_driver_imports_only_what_it_uses_and_every_public_name_resolves():
    """`twin router`, `twin ctl` or `twin --help` imported the whole kernel (the runtime, the campaign core, the
    scenario model, numpy) before parsing a word: ~0.9 s a start. The CLI's modules import those when a command
    runs, and ``twin`` and ``twin.campaign`` import each name when first asked for."""
    probe = ("import sys, twin.cli\n"
             "heavy = sorted(m for m in ('twin.runtime', 'twin.campaign.core', 'twin.scenario.model', 'numpy',"
             " 'twin.view') if m in sys.modules)\n"
             "from twin import Driver, StepResult\n"
             "driver = sorted(m for m in ('twin.runtime', 'twin.campaign.core') if m in sys.modules)\n"
             "import twin\n"
             "missing = [name for name in twin.__all__ if getattr(twin, name, None) is None]\n"
             "print(heavy, driver, missing)\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["[]", "[]", "[]"], out.stdout
    # the type checker reads the imports under TYPE_CHECKING, the interpreter _WHERE: the same names, from the same
    # modules
    import ast

    import twin

    tree = ast.parse(Path(twin.__file__).read_text())
    guarded = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING")
    imported = {alias.asname or alias.name: (node.module, alias.name) for node in guarded.body
                for alias in node.names}
    assert imported == twin._WHERE


@pytest.mark.parametrize("lab, planner", [("quantum_dots", "gp-bo"), ("bandgap", "mf-gp-bo")])
def test_checking_a_lab_that_plans_by_a_gp_leaves_scipy_and_sklearn_unimported(lab, planner):
    """`twin validate` of quantum_dots took ~3 s, two of them importing scipy.stats and scikit-learn for a planner
    made only to be checked: the GP planners import them when they first design or fit."""
    probe = ("import sys\n"
             "from twin.runtime.checks import validate_file\n"
             f"s = validate_file('scenarios/{lab}.yaml')\n"
             "print(s.campaign.planner, sorted(m for m in ('scipy.stats', 'sklearn') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [planner, "[]"], out.stdout
