"""Several campaigns sharing one lab (scenario ``campaigns:``): holds, turns, priorities, one scheduler."""

import json
import sqlite3

import pytest

from tests.conftest import twin_cli
from twin.runtime.lab import prepare
from twin.runtime.shared_run import run_shared
from twin.scenario import load
from twin.core.errors import ScenarioError
from tests.twin.shared_labs import (LAB, NO_FAULTS, ROOT, SMALL, assert_accounted, assert_one_step_at_a_time,
                                    device_jobs, events)


def test_two_campaigns_share_the_lab_each_with_its_own_ledger(tmp_path):
    s = prepare(LAB, seed=1)
    out = run_shared(s, tmp_path, handle_signals=False)
    assert set(out.campaigns) == {"dots", "catalyst"} and not out.not_started
    assert_accounted(out)
    assert_one_step_at_a_time(tmp_path)
    # each journal holds its own campaign: its own scenario, and samples named by the campaign
    for name in ("dots", "catalyst"):
        con = sqlite3.connect(tmp_path / f"{name}.db")
        scenario = json.loads(con.execute("SELECT value FROM run WHERE key='scenario'").fetchone()[0])
        routes = {r[0] for r in con.execute("SELECT route FROM experiments")}
        con.close()
        assert scenario["campaigns"] == [] and scenario["chemistry"]["model"] == ("quantum_dots" if name == "dots"
                                                                                   else "catalyst")
        assert all(("prepare" in r) == (name == "catalyst") for r in routes)
    # both used the shared devices; the lab's busy shares add up both campaigns' steps
    assert out.campaigns["dots"].utilisation["spectrometer"] > 0 < out.campaigns["catalyst"].utilisation["spectrometer"]
    assert out.lab_hours == pytest.approx(max(out.ended_h.values()))


@pytest.mark.parametrize("lab_scheduler", [None, "mwkr", "rl:agents/policies/flaky_scheduler.zip"])
def test_the_higher_priority_campaign_picks_free_devices_first(tmp_path, lab_scheduler):
    s = prepare(LAB, seed=2, overrides={**NO_FAULTS, "orchestrator.lab_scheduler": lab_scheduler})
    run_shared(s, tmp_path, handle_signals=False)
    high, low = tmp_path / "catalyst.db", tmp_path / "dots.db"
    device_of = {"prepare": "synthesiser", "react": "reactor", "measure": "spectrometer", "synthesise": "synthesiser"}
    # when each of the high-priority campaign's steps waited: ready -> dispatched
    waiting: list[tuple[float, float, str]] = []
    ready: dict[str, tuple[float, str]] = {}
    for t, kind, _, task, _, _, detail, _ in events(high, "task.ready", "attempt.dispatched"):
        if kind == "task.ready":
            ready[task] = (t, device_of[json.loads(detail)["step"]])
        elif task in ready:
            t0, dtype = ready.pop(task)
            waiting.append((t0, t, dtype))
    taken = [(t, device.rsplit("-", 1)[0] if device[-1].isdigit() else device)
             for t, _, _, _, _, device, _, _ in events(low, "attempt.dispatched")]
    assert waiting and taken
    overtaken = [(t, dtype, w) for t, dtype in taken for w in waiting if w[2] == dtype and w[0] <= t < w[1]]
    assert not overtaken, f"the low-priority campaign took a device a higher-priority step waited for: {overtaken[:3]}"


def test_fair_share_gives_device_time_in_proportion(tmp_path):
    # two campaigns of the same chemistry and priority, one spectrometer for both; shares 3 : 1
    dots = load(LAB).campaigns[0].model_dump(exclude_none=True)
    dots["campaign"].update(budget=40, stop_on_target=False, planner="random")
    s = prepare(LAB, seed=3, overrides={
        **NO_FAULTS, "campaigns": [{**dots, "share": 3}, {**dots, "name": "twin", "share": 1}],
        "devices.spectrometer.duration.mean_s": 1500})
    out = run_shared(s, tmp_path, handle_signals=False)
    spec = {n: c.utilisation["spectrometer"] * c.lab_hours for n, c in out.campaigns.items()}
    both = min(out.ended_h.values())  # while both campaigns ran
    assert both > 5
    used = {n: sum(min(e, both * 3600) - s0 for s0, e, c in device_jobs(tmp_path)["spectrometer"] if c == n and s0 <
                   both * 3600) for n in out.campaigns}
    assert used["dots"] > 2 * used["twin"], (used, spec)


def test_one_after_the_other_starts_the_second_when_the_first_ends(tmp_path):
    s = prepare(LAB, seed=1, overrides={"campaigns.1.after": "dots"})
    out = run_shared(s, tmp_path, handle_signals=False)
    assert out.submitted_h["catalyst"] == pytest.approx(out.ended_h["dots"])
    first = min(t for t, *_ in events(tmp_path / "catalyst.db", "attempt.dispatched"))
    assert first >= out.ended_h["dots"] * 3600
    assert_accounted(out)


def test_a_campaign_submitted_later_starts_at_its_hour(tmp_path):
    s = prepare(LAB, seed=1, overrides={"campaigns.0.start_h": 5.0})
    out = run_shared(s, tmp_path, handle_signals=False)
    assert out.submitted_h["dots"] == 5.0
    assert min(t for t, *_ in events(tmp_path / "dots.db", "attempt.dispatched")) >= 5 * 3600
    assert_one_step_at_a_time(tmp_path)


@pytest.mark.parametrize("change, named", [
    ({"campaigns.1.after": "nobody"}, "campaigns.1.after: 'nobody' is not another campaign"),
    ({"campaigns.1.name": "dots"}, "campaigns.1.name: 'dots' is the name of campaigns.0 too"),
    ({"campaigns.0.after": "catalyst", "campaigns.1.after": "dots"}, "waits for itself"),
    ({"campaigns.0.workflow": [{"step": "synthesise", "device": "robot"}]}, "campaigns.0 (dots)"),
])
def test_a_bad_lab_file_names_the_campaign_and_field(change, named):
    with pytest.raises(ScenarioError) as err:
        s = load(LAB, change)
        run_shared(s, "/nonexistent", handle_signals=False)
    assert named in str(err.value)


def test_whatif_compares_both_at_once_with_one_after_the_other():
    from twin.tools.whatif import summarise, variants, whatif

    s = prepare(LAB, overrides={"campaigns.0.campaign.budget": 12, "campaigns.1.campaign.budget": 8,
                                "campaigns.0.campaign.stop_on_target": False,
                                "campaigns.1.campaign.stop_on_target": False})
    chosen = variants(s, [("campaigns.1.after", [None, "dots"])])
    assert [v.label for v in chosen] == ["as written", "campaigns.1.after=dots"]
    runs = whatif(s, chosen, seeds=2, workers=1)
    rows = {row["variant"]: row for row in summarise(runs, chosen)}
    together, serial = rows["as written"], rows["campaigns.1.after=dots"]
    assert together["experiments"] == serial["experiments"] == 20  # the same work either way
    assert serial["lab_hours_change"][2] > 0  # one after the other takes longer on every seed
    assert together["utilisation"]["spectrometer"] > serial["utilisation"]["spectrometer"]


def test_a_campaign_journal_is_a_journal_like_any_other(tmp_path):
    run_shared(prepare(LAB, seed=4, overrides={"campaigns.0.campaign.budget": 6, "campaigns.1.campaign.budget": 4}),
               tmp_path, handle_signals=False)
    report = twin_cli("report", str(tmp_path / "catalyst.db"), columns=100)
    assert report.exit_code == 0, report.output
    assert "4 done" in report.output or "abandoned" in report.output
    out = twin_cli("export", str(tmp_path / "dots.db"), "--format", "jsonl", "--what", "experiments",
                   "--out", str(tmp_path / "x"), columns=80)
    assert out.exit_code == 0, out.output
    rows = [json.loads(line) for line in (tmp_path / "x" / "experiments.jsonl").read_text().splitlines()]
    assert len(rows) == 6 and all("param.concentration_mm" in r and "param.temperature_k" not in r for r in rows)
    # the lab's directory, as `twin report DIR` takes it: each campaign's tables in a directory of its own
    whole = twin_cli("export", str(tmp_path), "--what", "experiments", "--out", str(tmp_path / "all"), columns=80)
    assert whole.exit_code == 0, whole.output
    for name, n in (("dots", 6), ("catalyst", 4)):
        assert len((tmp_path / "all" / name / "experiments.csv").read_text().splitlines()) == n + 1  # + header
        assert (tmp_path / "all" / name / "provenance.json").is_file()


@pytest.mark.process
@pytest.mark.parametrize("one", [None, "agents/policies/lab_scheduler.zip"])
def test_two_campaigns_on_a_scaled_clock_over_zenoh_with_a_device_in_another_process(tmp_path, one):
    """``one``: the lab's one scheduler, the RL policy that sees whose step each candidate is."""
    import socket
    import subprocess
    import sys

    import yaml

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    raw = yaml.safe_load(LAB.read_text())
    raw["clock"] = {"mode": "scaled", "speed": 3000}
    # the device is started first and waits for the lab, which loads torch for the policy before it listens
    raw["bus"] = {"kind": "zenoh", "listen": [f"tcp/127.0.0.1:{port}"], "connect_timeout_ms": 60_000}
    raw["orchestrator"]["startup_s"] = 3000
    for c, budget in zip(raw["campaigns"], (5, 3)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    raw["campaigns"][1]["chemistry"]["parameters"]["time_s"] = {"low": 600, "high": 900, "unit": "s"}
    if one:
        raw["orchestrator"]["lab_scheduler"] = f"rl:{ROOT / one}"
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    device = subprocess.Popen([sys.executable, "-m", "twin", "device", "serve", str(path), "--id", "spectrometer",
                               "--connect", f"tcp/127.0.0.1:{port}", "--clock", "scaled", "--speed", "3000"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT)
    try:
        out = run_shared(load(path), tmp_path / "runs", handle_signals=False, external_devices={"spectrometer"})
    finally:
        device.terminate()
        _, err = device.communicate(timeout=30)
    assert out.campaigns["dots"].done + out.campaigns["dots"].abandoned == 5, err.decode()[-2000:]
    assert out.campaigns["catalyst"].done + out.campaigns["catalyst"].abandoned == 3
    assert_accounted(out)
    assert_one_step_at_a_time(tmp_path / "runs")
    # the spectrometer in the other process measured both campaigns' samples, each with its own chemistry
    for name, output in (("dots", "output.peak_nm"), ("catalyst", "output.yield")):
        con = sqlite3.connect(tmp_path / "runs" / f"{name}.db")
        results = con.execute("SELECT detail FROM events WHERE kind='msg.result' AND device='spectrometer'").fetchall()
        con.close()
        assert results and all(json.loads(r[0])["campaign"] == name for r in results)
        assert all(output.split(".")[1] in json.loads(r[0])["body"]["outputs"] for r in results)


def test_a_device_one_campaign_quarantined_is_kept_from_the_others_until_its_probe(tmp_path):
    s = prepare(LAB, seed=5, overrides={
        **NO_FAULTS, "devices.spectrometer.instances": 2, "devices.spectrometer.faults": {"fail_p": 0.5},
        "orchestrator.quarantine_after": 2, "orchestrator.probe_after_s": 7200,
        "campaigns.0.campaign.planner": "random", "campaigns.1.campaign.planner": "random"})
    run_shared(s, tmp_path, handle_signals=False)
    dbs = {db.stem: db for db in tmp_path.glob("*.db")}
    spells = []  # (campaign, device, from, to): quarantined by that campaign until its probe
    for name, db in dbs.items():
        opened = {}
        for t, kind, _, _, _, device, _, _ in events(db, "device.quarantined", "device.probe"):
            if kind == "device.quarantined":
                opened[device] = t
            elif device in opened:
                spells.append((name, device, opened.pop(device), t))
        con = sqlite3.connect(db)
        ended = con.execute("SELECT max(t_lab) FROM events WHERE kind != 'campaign.summary'").fetchone()[0]
        con.close()
        spells += [(name, d, t0, ended) for d, t0 in opened.items()]  # a campaign that ended holds nothing
    assert spells, "no device was quarantined: the test needs a flakier spectrometer"
    for name, device, t0, t1 in spells:
        for other, db in dbs.items():
            if other == name:
                continue
            inside = [r[0] for r in events(db, "attempt.dispatched") if r[5] == device and t0 <= r[0] < t1]
            assert not inside, f"{other} sent {device} work at {inside[:3]} while {name} had it quarantined"


@pytest.mark.parametrize("spec", ["mwkr", "rl:agents/policies/flaky_scheduler.zip"])
def test_one_scheduler_for_the_lab_chooses_among_every_campaigns_steps(tmp_path, monkeypatch, spec):
    """orchestrator.lab_scheduler: the rule or policy is asked once per pass with the ready steps of every
    campaign that asked (named campaign/task), and what it picks is dispatched by the campaign it belongs to."""
    from twin.runtime import shared_run

    views: list = []
    made = shared_run._lab_scheduler

    def spied(s):
        chosen = made(s)
        decide = chosen.decide

        def watching(view):
            views.append(view)
            return decide(view)
        chosen.decide = watching
        return chosen

    monkeypatch.setattr(shared_run, "_lab_scheduler", spied)
    s = prepare(LAB, seed=1, overrides={**SMALL, "campaigns.1.start_h": 0.0, "orchestrator.lab_scheduler": spec})
    out = run_shared(s, tmp_path, handle_signals=False)
    assert_accounted(out)
    assert_one_step_at_a_time(tmp_path)
    owners = [{r.task.split("/")[0] for r in v.ready} for v in views]
    assert any(o == {"dots", "catalyst"} for o in owners), "never saw both campaigns' steps at once"
    for db in tmp_path.glob("*.db"):
        assert events(db, "attempt.dispatched") and not events(db, "scheduler.invalid"), db.stem


def test_one_scheduler_for_the_lab_on_a_live_clock_answers_every_campaign_and_is_journalled(tmp_path):
    """On a scaled clock the lab's one scheduler (the RL policy) is asked in-process with every campaign's steps;
    its answers are the lab's inputs, journalled before anything they dispatch (`twin resume` replays them)."""
    from twin.campaign.journal_read import read_inputs
    from twin.campaign.replay import decode_input
    from twin.campaign.events import Decided

    s = prepare(LAB, seed=1, clock="scaled", speed=50_000, bus="memory",
                overrides={**SMALL, "campaigns.1.start_h": 0.0,
                           "orchestrator.lab_scheduler": "rl:agents/policies/lab_scheduler.zip"})
    out = run_shared(s, tmp_path, handle_signals=False)
    assert_accounted(out)
    assert_one_step_at_a_time(tmp_path)
    answers = [decode_input(item[1]) for _, batch in read_inputs(tmp_path / "lab.inputs")
               for item in batch.get("items", []) if item[0] == "lab"]
    given = {a.task.split("/")[0] for d in answers if type(d) is Decided for a in d.assignments}
    assert given == {"dots", "catalyst"}, "the lab's scheduler did not answer both campaigns"
    for db in tmp_path.glob("*.db"):
        assert events(db, "attempt.dispatched") and not events(db, "scheduler.invalid"), db.stem


def test_an_override_keeps_each_campaigns_seed_the_labs_plus_its_place():
    """`twin whatif --vary` on a lab: each variant is prepared with overrides, then given the run's seed; a
    campaign that has no seed of its own must still run on the lab's seed plus its place (a full re-dump once
    pinned every variant's campaigns to seed 0)."""
    from twin.scenario.sharing import campaign_scenarios

    for overrides in ({"orchestrator.lab_scheduler": "mwkr"}, {"campaigns.1.after": "dots"},
                      {"devices.spectrometer.instances": 2}):
        lab = prepare(prepare(load(LAB), overrides=overrides), seed=3)
        assert {n: c.campaign.seed for n, c in campaign_scenarios(lab, lab.name).items()} == {"dots": 3,
                                                                                             "catalyst": 4}
    pinned = prepare(prepare(load(LAB), overrides={"campaigns.1.campaign.seed": 9}), seed=3)
    assert campaign_scenarios(pinned, pinned.name)["catalyst"].campaign.seed == 9


def test_a_target_named_with_brackets_is_printed_as_named(tmp_path):
    """The lab's summary read its targets' names as rich markup: "[red]R" lost its bracket (and coloured the rest)."""
    res = twin_cli("run", LAB, "--journal", tmp_path, "--set", 'campaigns.0.chemistry.targets.0.name="[red]R"',
                   "--set", "campaigns.0.campaign.budget=8", "--set", "campaigns.1.campaign.budget=2", columns=200)
    assert res.exit_code == 0, res.output
    row = next(line for line in res.output.splitlines() if line.startswith("│ dots"))
    assert "[red]R " in row, row


@pytest.mark.parametrize("command", [["run", "FILE", "--quiet"],
                                     ["lab", "serve", "FILE", "--listen", "tcp/127.0.0.1:0"]])
def test_what_the_checks_refuse_in_a_lab_file_names_the_file(tmp_path, command):
    """`twin run LAB.yaml` and `twin lab serve` named the lab's scenario (`error: shared_lab: 1 problem`) where a
    lone campaign's file is named; `twin validate` named the file."""
    import yaml

    raw = yaml.safe_load(LAB.read_text())
    raw["campaigns"][1]["campaign"] = {"budget": 2, "planner": "fixed", "planner_options": {"proposals": [
        {"params": {"temperature_k": 1000, "time_s": 1000}}]}}
    path = tmp_path / "plates.yaml"
    path.write_text(yaml.safe_dump(raw))
    res = twin_cli(*[path if a == "FILE" else a for a in command], "--journal", tmp_path / "runs")
    said = " ".join(res.stderr.split())
    assert res.exit_code == 2 and f"{path}: 1 problem" in said, said
    assert "campaigns.1 (catalyst): campaign.planner_options.proposals.0: temperature_k = 1000 is outside" in said
