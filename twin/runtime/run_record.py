"""A run's provenance: what it takes to know where its results came from and to run it again.

Written to the journal (``run.provenance``) when the run starts: the scenario's hash (of the whole scenario as
run, overrides included; the scenario itself is in ``run.scenario``), the seed, the versions of Python and the
packages that decide the results, the policy and data files the scenario names with their SHA-256, and the
command line. The operators' acts are events in the journal; ``twin export`` adds them to this record.
"""

from __future__ import annotations

import hashlib
import platform
import sys
import time
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from twin.scenario import Scenario

PACKAGES = ("labtwin", "numpy", "scipy", "scikit-learn", "torch", "stable-baselines3", "sb3-contrib", "gymnasium",
            "eclipse-zenoh", "rerun-sdk", "rdkit", "pydantic", "msgspec")
FILE_SUFFIXES = (".zip", ".pt", ".json", ".yaml", ".yml", ".csv", ".tsv", ".gz", ".txt")


def scenario_hash(s: Scenario) -> str:
    """SHA-256 of the scenario as run (every field, overrides included)."""
    return hashlib.sha256(s.model_dump_json().encode()).hexdigest()


@lru_cache(maxsize=1)
def _versions() -> tuple[tuple[str, str], ...]:
    out = {"python": platform.python_version()}
    for p in PACKAGES:
        try:
            out[p] = version(p)
        except PackageNotFoundError:
            pass
    return tuple(out.items())


def versions() -> dict[str, str]:
    """Python's and the packages' versions (looked up once per process: each lookup reads the installed
    metadata, and a what-if or a test suite starts thousands of runs)."""
    return dict(_versions())


@lru_cache(maxsize=256)
def _sha256(path: str, size: int, mtime_ns: int) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def named_files(s: Scenario) -> dict[str, str]:
    """Files the scenario names (policies, templates, stocks, job shops) that exist here, with their SHA-256."""
    found: dict[str, str] = {}

    def visit(value: Any) -> None:
        if isinstance(value, dict):
            for v in value.values():
                visit(v)
        elif isinstance(value, (list, tuple)):
            for v in value:
                visit(v)
        elif isinstance(value, str) and len(value) < 1024:
            path = value.split(":", 1)[1] if value.startswith(("rl:", "mcts:")) else value
            if path.lower().endswith(FILE_SUFFIXES) and path not in found:
                p = Path(path)
                candidates = [p, p.with_suffix(".zip")] if p.suffix == ".json" else [p]
                for c in candidates:
                    st = c.stat() if c.is_file() else None
                    if st is not None and st.st_size < 1 << 30:
                        found[str(c)] = _sha256(str(c), st.st_size, st.st_mtime_ns)

    visit(s.model_dump())
    return found


def provenance(s: Scenario) -> dict[str, Any]:
    return {"scenario": s.name, "scenario_sha256": scenario_hash(s), "seed": s.campaign.seed,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "versions": versions(),
            "files": named_files(s), "command": [Path(sys.argv[0]).name, *sys.argv[1:]]}
