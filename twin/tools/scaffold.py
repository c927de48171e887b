"""`twin driver new NAME`: a pip-installable driver package with a test, ready to edit."""

from __future__ import annotations

import importlib.util
import keyword
import re
from pathlib import Path

from twin.core.errors import TwinError

DRIVER = '''"""{title}: a labtwin device driver (see labtwin's docs/drivers.md)."""

from __future__ import annotations

from typing import Any

from twin import DriverSetup, Refused, StepContext, StepResult


class {cls}:
    labtwin_api = 1
    capabilities = frozenset({{"measure"}})
    option_names = frozenset({{"noise_nm"}})  # a misspelt option in a scenario is refused, naming the field
    needs_sample = frozenset({{"measure"}})  # a workflow that measures before a step makes one is refused
    makes_sample: frozenset[str] = frozenset()  # it passes on the sample it measured

    def __init__(self, setup: DriverSetup) -> None:
        self.name = setup.name
        self.noise_nm = float(setup.options.get("noise_nm", 0.5))

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        if not sample or "peak_nm" not in sample:  # the workflow's doing, not a fault: refused, not retried
            raise Refused(f"{{self.name}}: nothing to measure in {{sample!r:.80}}", infeasible=True)
        await ctx.clock.sleep(ctx.draw_duration(params))  # replace with talking to the instrument
        peak = sample["peak_nm"] + float(ctx.rng.normal(0.0, self.noise_nm))
        return StepResult({{"peak_nm": round(peak, 3)}}, sample)

    async def safe_state(self) -> None:
        """Leave the instrument safe after a cancelled or failed step."""
'''

TEST = '''"""The driver alone, then in a whole campaign."""

from pathlib import Path

import pytest

from twin import Refused, driver_setup, run_scenario, run_step
from {module}.driver import {cls}

HERE = Path(__file__).resolve().parents[1]


def test_it_measures_a_sample():
    result, took = run_step({cls}(driver_setup("{name}-1")), "measure", {{}}, {{"peak_nm": 520.0}})
    assert abs(result.outputs["peak_nm"] - 520.0) < 5 and took > 0


def test_it_refuses_a_missing_sample():
    with pytest.raises(Refused, match="nothing to measure"):
        run_step({cls}(driver_setup("{name}-1")), "measure", {{}}, None)


def test_a_campaign_runs_with_it():
    summary = run_scenario(HERE / "scenario.yaml")
    assert summary.done == 4 and summary.failed_attempts == 0
'''

SCENARIO = '''# A small lab in which {name} measures what the simulated synthesiser makes.
name: {module}_demo
lab: {module}
devices:
  synthesiser: {{driver: synthesiser, steps: [synthesise], duration: {{mean_s: 600, cv: 0.1}}}}
  reader: {{driver: {name}, steps: [measure], duration: {{mean_s: 120, cv: 0.1}}}}
chemistry:
  model: quantum_dots
  parameters:
    concentration_mm: {{low: 1, high: 50}}
    temperature_c: {{low: 220, high: 320}}
    time_s: {{low: 10, high: 600}}
workflow:
  - {{step: synthesise, device: synthesiser}}
  - {{step: measure, device: reader}}
campaign: {{budget: 4, planner: random, stop_on_target: false}}
'''

PYPROJECT = '''[build-system]
requires = ["setuptools>=68"]
build-backend = "setuptools.build_meta"

[project]
name = "{name}"
version = "0.1.0"
description = "{title}: a labtwin device driver"
requires-python = ">=3.11"
dependencies = ["labtwin"]

[project.entry-points."labtwin.devices"]
{name} = "{module}.driver:{cls}"

[tool.setuptools.packages.find]
include = ["{module}*"]

[tool.pytest.ini_options]
# labtwin's test tools include pytest-asyncio, which warns at every run while this is unset
asyncio_default_fixture_loop_scope = "function"
'''

README = '''# {name}

A labtwin device driver. `pip install -e .` makes it known to labtwin
(`twin devices` lists it); use it in a scenario as `driver: {name}`.
`python -m pytest` runs its tests (`scenario.yaml` is a whole campaign with it).
'''


def _taken(name: str, module: str) -> str:
    """Why installing the package for ``name`` would clash with what is here ('' if it would not): its module
    would shadow (or be shadowed by) an importable one, its distribution would replace an installed one, or its
    entry point would be a driver name that is installed or reserved."""
    from importlib.metadata import PackageNotFoundError, distribution

    from twin.core import plugins

    if name == "operator":
        return "`driver: operator` means people in a scenario, not a driver"
    if name in plugins.installed("devices"):
        return "an installed driver is called so (`twin devices` lists it)"
    try:
        installed = distribution(name)
    except PackageNotFoundError:
        pass
    else:
        return f"the package {installed.metadata['Name']} {installed.version} is installed here, and `pip install` " \
               "of this one would replace it"
    spec = importlib.util.find_spec(module)
    if spec is not None:
        return f"its Python module would be {module}, which is importable here already ({spec.origin or 'a folder'})"
    return ""


def scaffold(name: str, where: Path) -> Path:
    """Write the package for driver ``name`` under ``where``; returns its directory."""
    if not re.fullmatch(r"[a-z][a-z0-9-]*[a-z0-9]", name):
        raise TwinError(f"driver name {name!r}: use lower-case letters, digits and dashes, e.g. acme-hplc")
    module = name.replace("-", "_")
    if keyword.iskeyword(module):
        raise TwinError(f"driver name {name!r} is a Python keyword; choose another")
    taken = _taken(name, module)
    if taken:
        raise TwinError(f"driver name {name!r} is taken: {taken}; choose another, e.g. acme-{name}")
    cls = "".join(part.capitalize() for part in name.split("-"))
    root = where / name
    if root.exists():
        raise TwinError(f"{root} already exists; choose another name or directory (--dir)")
    values = {"name": name, "module": module, "cls": cls, "title": name.replace("-", " ").title()}
    files = {"pyproject.toml": PYPROJECT, "README.md": README, "scenario.yaml": SCENARIO,
             f"{module}/__init__.py": "", f"{module}/driver.py": DRIVER, "tests/test_driver.py": TEST}
    for rel, template in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(template.format(**values))
    return root
