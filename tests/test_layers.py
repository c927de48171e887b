"""The layers hold: the kernel's layers, its public API, and what may import zenoh and rerun."""

import shutil
import subprocess
import sys
from pathlib import Path

import grimp

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
