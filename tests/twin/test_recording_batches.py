"""The fast runtime hands a recording what happens in batches (``twin.runtime.draw_later``): whatever their size, the
recording is the one drawn call by call, row for row, each entity's rows logged in the same order."""

from pathlib import Path

from tests.rrd import read_rrd
from tests.twin.shared_labs import LAB, SMALL, recorded_lab
from twin.runtime.draw_later import DrawLater
from twin.runtime.lab import prepare, run
from twin.view.watch import RecordOptions

ROOT = Path(__file__).resolve().parents[2]


def as_logged(rrd: dict[str, list[dict]]) -> dict[str, list[dict]]:
    """Each entity's rows in the order they were logged (their row ids), the ids left out."""
    return {path: [{k: v for k, v in r.items() if k != "row_id"} for r in sorted(rows, key=lambda r: r["row_id"])]
            for path, rows in rrd.items() if path != "__properties"}


def test_a_campaign_drawn_in_batches_is_the_recording_drawn_call_by_call(tmp_path, monkeypatch):
    drawn = {}
    for limit in (1, 7):  # 1: each call made as it comes
        monkeypatch.setattr(DrawLater, "LIMIT", limit)
        run(ROOT / "scenarios" / "flaky_lab.yaml", journal=tmp_path / f"{limit}.db", seed=5, bus="memory",
            runtime="fast", overrides={"campaign.budget": 16}, record=RecordOptions(save=tmp_path / f"{limit}.rrd"))
        drawn[limit] = as_logged(read_rrd(tmp_path / f"{limit}.rrd", row_ids=True))
    assert sum(len(rows) for rows in drawn[1].values()) > 50 * 7  # many batches, the last one part-full
    assert drawn[7] == drawn[1]


def test_a_shared_lab_drawn_in_batches_is_the_recording_drawn_call_by_call(tmp_path, monkeypatch):
    drawn = {}
    for limit in (1, 5):
        monkeypatch.setattr(DrawLater, "LIMIT", limit)
        (tmp_path / str(limit)).mkdir()
        _, rrd = recorded_lab(prepare(LAB, overrides=SMALL), tmp_path / str(limit))
        drawn[limit] = as_logged(rrd)
    assert any(path.startswith("campaigns/") for path in drawn[1])
    assert drawn[5] == drawn[1]


def test_an_observer_that_raises_when_its_calls_are_made_leaves_the_journal_whole(tmp_path):
    """The calls kept for an observer are made as the campaign ends: one that raises then (an observer of the
    caller's own; the shipped one draws what it can and logs the rest) is raised after the summary is written."""
    import pytest

    from twin.campaign.journal_read import read_run
    from twin.view.log_canvas import LogCanvas
    from twin.view.observer import LabObserver

    class Raising(LabObserver):
        def on_note(self, note):
            if note.kind != "campaign.summary":
                raise RuntimeError("observer failed")

    with pytest.raises(RuntimeError, match="observer failed"):
        run(ROOT / "scenarios" / "flaky_lab.yaml", journal=tmp_path / "j.db", bus="memory", runtime="fast",
            overrides={"campaign.budget": 3}, observer=Raising(LogCanvas(lambda line: None)))
    assert read_run(tmp_path / "j.db")["summary"]["done"] == 3
