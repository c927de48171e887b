"""A job shop run as a lab: FIFO gives a valid schedule no shorter than the optimum."""

import json
from collections import defaultdict
from pathlib import Path

import pytest

from twin.scenario.jobshop import read
from twin.campaign.journal import read_events
from twin.runtime.lab import run

ROOT = Path(__file__).resolve().parents[2]


def schedule(db):
    start, end = {}, {}
    for e in read_events(db, "msg.%"):
        if e["kind"] == "msg.accepted":
            start[e["task"]] = (e["t_lab"], e["device"])
        elif e["kind"] == "msg.result":
            end[e["task"]] = e["t_lab"]
    return {t: (s, end[t], d) for t, (s, d) in start.items()}


@pytest.mark.parametrize("bus", ["memory", "zenoh"])
def test_fifo_on_ft06_is_a_valid_schedule(tmp_path, bus):
    db = tmp_path / "j.db"
    summary = run(ROOT / "scenarios" / "jobshop.yaml", journal=db, bus=bus)
    inst = read(ROOT / "scenarios" / "jobshop" / "ft06.txt")
    ops = schedule(db)
    assert summary.done == len(inst.jobs) == 6
    assert len(ops) == sum(len(j) for j in inst.jobs)
    for j, job in enumerate(inst.jobs):
        prev_end = 0.0
        for k, (machine, duration) in enumerate(job):
            s, e, dev = ops[f"e{j}s{k}"]
            assert dev == f"m{machine}"
            assert e - s == pytest.approx(duration)
            assert s >= prev_end - 1e-9, f"job {j} op {k} starts before its predecessor ends"
            prev_end = e
    by_machine = defaultdict(list)
    for s, e, dev in ops.values():
        by_machine[dev].append((s, e))
    for dev, spans in by_machine.items():
        spans.sort()
        for (s1, e1), (s2, _) in zip(spans, spans[1:]):
            assert s2 >= e1 - 1e-9, f"{dev} runs two operations at once"
    makespan = max(e for _, e, _ in ops.values()) - min(s for s, _, _ in ops.values())
    assert makespan >= 55
    assert json.loads(json.dumps(summary.utilisation))  # every machine reported
    assert set(summary.utilisation) == {f"m{m}" for m in range(6)}


def test_a_malformed_instance_is_a_scenario_error(tmp_path):
    from twin.core.errors import ScenarioError

    bad = tmp_path / "bad.txt"
    bad.write_text("2 2\n0 3 1\n")
    with pytest.raises(ScenarioError, match="bad.txt"):
        read(bad)
