"""Faults are handled where the design says: timeouts, retries elsewhere, quarantine, late results."""

import json

from twin.core import keys
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run
from twin.core.messages import Kind, pack


def attempts_of(db, task):
    rows = read_events(db, "attempt.%")
    return [(r["kind"], r["device"], json.loads(r["detail"]) if r["detail"] else None) for r in rows if r["task"] == task]


def test_timeout_then_retry_on_another_instance(scenario_of, tmp_path):
    # no quarantine here: with only the failed instance usable, a retry rightly goes back to it
    s = scenario_of(**{"devices.spectrometer.faults": {"hang_p": 0.5}, "campaign.budget": 10,
                       "orchestrator.quarantine_after": 50})
    db = tmp_path / "j.db"
    summary = run(s, journal=db)
    timed_out = [r for r in read_events(db, "attempt.failed") if json.loads(r["detail"])["code"] == "timed_out"]
    assert timed_out, "with hang_p=0.5 some measurement must hang"
    moved = 0
    for r in timed_out:
        later = [a for a in attempts_of(db, r["task"]) if a[0] == "attempt.dispatched"]
        devices = [d for _, d, _ in later]
        idx = devices.index(r["device"])
        if idx + 1 < len(devices):
            assert devices[idx + 1] != r["device"], "the retry must prefer the other instance"
            moved += 1
    assert moved >= 1
    assert summary.done + summary.abandoned == summary.proposed


def test_a_device_failing_k_times_in_a_row_is_quarantined_then_probed(scenario_of, tmp_path):
    s = scenario_of(**{
        "devices.synthesiser.faults": {"fail_p": 1.0},
        "orchestrator.quarantine_after": 2,
        "orchestrator.probe_after_s": 5000,
        "orchestrator.retry": {"max_attempts": 3, "backoff_s": 10},
        "campaign.budget": 3,
    })
    db = tmp_path / "j.db"
    summary = run(s, journal=db)
    assert summary.done == 0 and summary.abandoned == 3
    events = read_events(db)
    q = [e for e in events if e["kind"] == "device.quarantined"]
    probe = [e for e in events if e["kind"] == "device.probe"]
    assert q and probe
    first_q = q[0]["t_lab"]
    first_probe = probe[0]["t_lab"]
    assert first_probe - first_q == 5000
    dispatched_in_quarantine = [
        e for e in events if e["kind"] == "attempt.dispatched" and first_q < e["t_lab"] < first_probe
    ]
    assert dispatched_in_quarantine == []
    assert all("failed" in r for r in summary.abandoned_reasons)


def test_a_step_retried_for_longer_than_max_delay_is_abandoned_and_the_reason_names_the_field(scenario_of, tmp_path):
    """Attempts left, but retried for longer than retry.max_delay_s: abandoned, saying so. The clock starts at the
    step's first failure: time it spent queued before its first attempt is not retrying (it was counted, and in a
    large lab whose queue held steps for days an experiment was abandoned at its first failure, reading only
    "failed 1 time(s)" while max_attempts was 4)."""
    s = scenario_of(**{"devices.synthesiser.faults": {"fail_p": 1.0}, "devices.synthesiser.instances": 1,
                       "orchestrator.quarantine_after": 50, "campaign.max_in_flight": 3,
                       "orchestrator.retry": {"max_attempts": 4, "backoff_s": 10, "max_delay_s": 1},
                       "campaign.budget": 3})
    summary = run(s, journal=tmp_path / "j.db")
    # every step is retried once, the queued ones too (first ready long before their first failure), then not
    assert summary.abandoned == 3 and summary.attempts == 6
    (kind, n), = summary.abandoned_reasons.items()
    assert n == 3 and kind.endswith(": failed (retried past max_delay_s)")
    reason = summary.abandoned_examples[kind]
    assert "failed 2 time(s) and is not retried: it has been retried for" in reason
    assert "orchestrator.retry.max_delay_s (1 s; raise it" in reason


def test_a_step_whose_attempts_are_used_up_says_only_how_often_it_failed(scenario_of, tmp_path):
    s = scenario_of(**{"devices.synthesiser.faults": {"fail_p": 1.0}, "orchestrator.quarantine_after": 50,
                       "orchestrator.retry": {"max_attempts": 2, "backoff_s": 10}, "campaign.budget": 1})
    summary = run(s, journal=tmp_path / "j.db")
    (kind, n), = summary.abandoned_reasons.items()
    assert kind.endswith(": failed") and "failed 2 time(s); last: failed on" in summary.abandoned_examples[kind]


async def _duplicating_device(bus, clock, lab, name):
    """A misbehaving device: answers every command with its result twice, plus one for a stranger."""
    ids = iter(range(1, 10**6))

    def on_cmd(key, payload):
        env = json.loads(payload)
        if env["kind"] != "command":
            return
        for kind, body, attempt in [
            (Kind.ACCEPTED, {}, env["attempt"]),
            (Kind.RESULT, {"outputs": {"x": 1}, "sample": {"kind": "raw", "t_made": clock.now()}}, env["attempt"]),
            (Kind.RESULT, {"outputs": {"x": 2}, "sample": None}, env["attempt"]),
            (Kind.RESULT, {"outputs": {"x": 3}}, env["attempt"] + 7),
        ]:
            bus.publish(keys.evt(lab, name), pack(kind, body, id=f"{name}:{next(ids)}", sender=name,
                                                   t_lab=clock.now(), task=env["task"], attempt=attempt,
                                                   token=env["token"]))

    bus.subscribe(keys.cmd(lab, name), on_cmd)
    return bus.declare_token(keys.alive(lab, name))


def test_duplicate_and_late_results_are_recorded_never_double_counted(scenario_of, tmp_path):

    from twin.core.bus import MemoryHub, MemoryBus
    from twin.core.clock import LabClock
    from twin.campaign.journal import Journal
    from twin.runtime import LiveCampaign
    from twin.runtime.lab import make_planner, make_scheduler

    s = scenario_of(**{"devices": {"dup": {"driver": "machine", "steps": ["op"], "duration": {"mean_s": 1}}},
                       "workflow": [{"step": "op", "device": "dup"}], "campaign.budget": 5})
    clock = LabClock("virtual")
    db = tmp_path / "j.db"

    async def main():
        bus = MemoryBus(MemoryHub())
        await bus.start()
        token = await _duplicating_device(bus, clock, s.lab, "dup")
        journal = Journal(db)
        camp = LiveCampaign(s, bus, clock, journal, make_planner(s), make_scheduler(s))
        await camp.run()
        token.close()
        journal.close()
        return camp.core

    core = clock.run(main())
    assert [e.status for e in core.experiments] == ["done"] * 5
    assert all(e.outputs == {"x": 1} for e in core.experiments)
    assert core.counts.late == 5  # one duplicate per experiment
    assert core.counts.rejected == 5  # and one about an attempt never dispatched
    assert len(read_events(db, "experiment.done")) == 5
    assert len(read_events(db, "result.late")) == 5
    assert len(read_events(db, "message.rejected")) == 5


def test_the_summary_names_the_step_degraded_samples_waited_for(scenario_of, tmp_path):
    """A lab whose one spectrometer is the bottleneck: every degraded sample waited too long for 'measure', and the
    summary says so with the count, as `twin report` prints it."""
    import io

    from rich.console import Console

    from twin.view.report import render_summary

    s = scenario_of(**{"devices.synthesiser.instances": 4, "devices.spectrometer.duration": {"mean_s": 3000},
                       "chemistry.stability_s": 3600, "campaign.max_in_flight": 12, "campaign.budget": 24,
                       "campaign.stop_on_target": False})
    db = tmp_path / "j.db"
    summary = run(s, journal=db)
    assert summary.degraded_samples > 0
    assert summary.degraded_before == {"measure": summary.degraded_samples}
    made = {}
    for r in read_events(db, "attempt.done"):
        if r["task"].endswith("s0"):
            made[r["experiment"]] = r["t_lab"]
    late = {r["experiment"] for r in read_events(db, "attempt.dispatched")
            if r["task"].endswith("s1") and r["t_lab"] - made[r["experiment"]] > 3600}
    done = {r["experiment"] for r in read_events(db, "experiment.done")}
    assert len(late & done) == summary.degraded_samples
    out = io.StringIO()
    render_summary(summary, Console(file=out, width=200))
    assert (f"{summary.degraded_samples} — waited longer than chemistry.stability_s before measure "
            f"{summary.degraded_samples}") in out.getvalue()


def test_a_type_of_many_instances_is_one_row_of_the_summary(scenario_of, tmp_path):
    import io

    from rich.console import Console

    from twin.view.report import render_summary

    s = scenario_of(**{"devices.synthesiser.instances": 9, "campaign.budget": 12, "campaign.max_in_flight": 9,
                       "campaign.stop_on_target": False})
    summary = run(s, journal=tmp_path / "j.db")
    out = io.StringIO()
    render_summary(summary, Console(file=out, width=200))
    text = out.getvalue()
    busy = [100 * summary.utilisation[f"synthesiser-{i}"] for i in range(1, 10)]
    assert f"synthesiser ×9 │ {sum(busy) / 9:5.1f} % busy on average ({min(busy):.1f}–{max(busy):.1f} % per " \
           "instance)" in text
    assert "synthesiser-1 " not in text and "spectrometer-1 " in text  # one instance: its own row
    markdown = summary._repr_markdown_()  # a notebook's view, and the viewer's summary panel: folded alike
    assert f"| synthesiser ×9 | {sum(busy) / 9:.1f} % busy on average" in markdown
    assert "| synthesiser-1 |" not in markdown and "| spectrometer-1 |" in markdown
