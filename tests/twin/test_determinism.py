"""The same scenario and seed in virtual time give identical journals, on either bus."""

import sqlite3
from pathlib import Path

import pytest

from twin.runtime.lab import run

ROOT = Path(__file__).resolve().parents[2]


def journal_rows(db):
    with sqlite3.connect(db) as c:
        return (
            c.execute("SELECT * FROM events ORDER BY seq").fetchall(),
            c.execute("SELECT * FROM experiments ORDER BY id").fetchall(),
        )


@pytest.mark.parametrize("bus", ["memory", "zenoh"])
def test_same_seed_same_journal(tmp_path, bus):
    scenario = ROOT / "scenarios" / "flaky_lab.yaml"
    a = run(scenario, journal=tmp_path / "a.db", seed=3, bus=bus, overrides={"campaign.budget": 25})
    run(scenario, journal=tmp_path / "b.db", seed=3, bus=bus, overrides={"campaign.budget": 25})
    events_a, exps_a = journal_rows(tmp_path / "a.db")
    events_b, exps_b = journal_rows(tmp_path / "b.db")
    assert len(events_a) > 200
    assert a.failed_attempts > 0, "the flaky lab must exercise faults for this to mean anything"
    assert events_a == events_b
    assert exps_a == exps_b


def test_another_seed_gives_another_journal(tmp_path):
    scenario = ROOT / "scenarios" / "flaky_lab.yaml"
    run(scenario, journal=tmp_path / "a.db", seed=3, bus="memory", overrides={"campaign.budget": 10})
    run(scenario, journal=tmp_path / "b.db", seed=4, bus="memory", overrides={"campaign.budget": 10})
    assert journal_rows(tmp_path / "a.db") != journal_rows(tmp_path / "b.db")
