"""Fixtures the agents' tests share."""

from pathlib import Path

import pytest

from twin.runtime.lab import prepare

ROOT = Path(__file__).resolve().parents[2]
SHIPPED_JOBSHOP = ROOT / "agents" / "policies" / "jobshop_scheduler.zip"


@pytest.fixture(scope="module")
def ft06():
    """Fisher and Thompson's 6×6 shop as the scenario ships it (its training section included)."""
    return prepare(ROOT / "scenarios" / "jobshop.yaml")


@pytest.fixture(scope="module")
def state(ft06):
    """The shipped job-shop policy's action network, as a training starts from it (an earlier encoding widened)."""
    from agents.train_scheduler import initial_state

    return initial_state(SHIPPED_JOBSHOP, ft06, "candidates", part="action_net")


@pytest.fixture
def rollouts_in_process(monkeypatch):
    """A training's rollouts in the test's own process, as on a machine of one core: what is learnt is the same
    (agents.training_workers), without two spawned workers' seconds of imports. For the tests not about the pool."""
    from agents import training_workers

    monkeypatch.setattr(training_workers.os, "cpu_count", lambda: 1)
