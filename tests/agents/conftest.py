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
