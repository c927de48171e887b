"""Several campaigns sharing one lab (scenario ``campaigns:``), in virtual time on the fast runtime."""

import json
import sqlite3
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from twin.campaign.journal import read_run
from twin.core.errors import ScenarioError
from twin.runtime.lab import prepare
from twin.runtime.shared_run import run_shared
from twin.scenario import load

ROOT = Path(__file__).resolve().parents[2]
LAB = ROOT / "scenarios" / "shared_lab.yaml"
NO_FAULTS = {f"devices.{d}.faults": {} for d in ("synthesiser", "reactor", "spectrometer")}


def events(db: Path, *kinds: str) -> list[tuple]:
    con = sqlite3.connect(db)
    try:
        marks = ",".join("?" * len(kinds))
        return con.execute(f"SELECT t_lab, kind, experiment, task, attempt, device, detail, seq FROM events "
                           f"WHERE kind IN ({marks}) ORDER BY seq", kinds).fetchall()
    finally:
        con.close()


def device_jobs(journals: Path) -> dict[str, list[tuple[float, float, str]]]:
    """Per device, (accepted at, ended at, campaign) of every step it ran, from every campaign's journal: a step
    ends with its result or fault, when its device leaves the bus, or when its campaign cancels it (at the end,
    or at its deadline: an in-process device stops at once, and a campaign that ends then journals no answer)."""
    jobs: dict[str, list[tuple[float, float, str]]] = {}
    for db in journals.glob("*.db"):
        started: dict[tuple, tuple[float, str]] = {}
        for t, kind, _, task, attempt, device, detail, _ in events(
                db, "msg.accepted", "msg.result", "msg.fault", "device.lost", "attempt.cancelled", "attempt.failed"):
            if kind == "attempt.failed" and "timed_out" not in detail:
                continue
            if kind == "msg.accepted":
                started[(task, attempt)] = (t, device)
            elif kind == "device.lost":
                for key in [k for k, (_, d) in started.items() if d == device]:
                    jobs.setdefault(device, []).append((started.pop(key)[0], t, db.stem))
            elif (task, attempt) in started:
                jobs.setdefault(device, []).append((started.pop((task, attempt))[0], t, db.stem))
        assert not started, f"{db.stem}: steps accepted and never ended: {started}"
    return jobs


def assert_one_step_at_a_time(journals: Path) -> None:
    for device, runs in device_jobs(journals).items():
        runs.sort()
        for (s0, e0, c0), (s1, e1, c1) in zip(runs, runs[1:]):
            assert s1 >= e0 - 1e-9, f"{device} ran {c0}'s step [{s0}, {e0}] and {c1}'s [{s1}, {e1}] at once"


def assert_accounted(summary) -> None:
    for name, c in summary.campaigns.items():
        assert c.done + c.abandoned + c.pending == c.proposed, name
        assert c.proposed > 0, f"{name} proposed nothing"
        if not c.stopped:
            assert c.pending == 0, name


def wait_until_ended(status, campaigns: int, seconds: float = 90) -> dict:
    """Poll ``status()`` (a lab's `twin ctl status --json`) until ``campaigns`` campaigns have all ended."""
    import time

    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        now = status()
        if len(now["campaigns"]) == campaigns and all(c["state"] == "ended" for c in now["campaigns"]):
            return now
        time.sleep(0.5)
    pytest.fail(f"the campaigns did not end: {now}")


def kill_all(*procs) -> None:
    for proc in procs:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.communicate()


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


lab_shapes = st.fixed_dictionaries({
    "spectrometers": st.integers(1, 2), "synthesisers": st.integers(1, 3),
    "fail_p": st.sampled_from([0.0, 0.1, 0.3]), "hang_p": st.sampled_from([0.0, 0.05]),
    "mtbc_h": st.sampled_from([0, 3]),
    "priorities": st.lists(st.integers(-1, 1), min_size=2, max_size=3),
    "budgets": st.lists(st.integers(2, 8), min_size=3, max_size=3),
    "seed": st.integers(0, 1000),
    "lab_scheduler": st.sampled_from([None, "mwkr", "spt"]),  # None: each campaign's own, in turns
})


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(shape=lab_shapes)
def test_any_shared_lab_runs_one_step_per_device_and_accounts_for_everything(tmp_path_factory, shape):
    """Random labs, faults, crashes and priorities, the campaigns in turns or one scheduler for the lab: every
    campaign ends with its accounting invariant, no device ever runs two steps at once."""
    n = len(shape["priorities"])
    base = load(LAB)
    campaigns = []
    for i in range(n):
        c = base.campaigns[i % 2].model_dump(exclude_none=True)
        c.update(name=f"c{i}", priority=shape["priorities"][i])
        c["campaign"] = {**c["campaign"], "budget": shape["budgets"][i], "planner": "random"}
        campaigns.append(c)
    faults = {"fail_p": shape["fail_p"], "hang_p": shape["hang_p"], "mtbc_h": shape["mtbc_h"], "restart_s": 600}
    s = prepare(base, seed=shape["seed"], overrides={
        "campaigns": campaigns, "devices.spectrometer.instances": shape["spectrometers"],
        "devices.synthesiser.instances": shape["synthesisers"], "orchestrator.lab_scheduler": shape["lab_scheduler"],
        **{f"devices.{d}.faults": faults for d in ("synthesiser", "reactor", "spectrometer")}})
    where = tmp_path_factory.mktemp("lab")
    out = run_shared(s, where, handle_signals=False)
    assert len(out.campaigns) == n
    assert_accounted(out)
    assert_one_step_at_a_time(where)
    busy = [r for db in where.glob("*.db") for r in events(db, "msg.rejected") if "busy" in (r[6] or "")]
    assert not busy, f"a device was sent a step while it ran another: {busy[:2]}"


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
    from typer.testing import CliRunner

    from twin.cli import app

    run_shared(prepare(LAB, seed=4, overrides={"campaigns.0.campaign.budget": 6, "campaigns.1.campaign.budget": 4}),
               tmp_path, handle_signals=False)
    runner = CliRunner()
    report = runner.invoke(app, ["report", str(tmp_path / "catalyst.db")], env={"COLUMNS": "100"})
    assert report.exit_code == 0, report.output
    assert "4 done" in report.output or "abandoned" in report.output
    out = runner.invoke(app, ["export", str(tmp_path / "dots.db"), "--format", "jsonl", "--what", "experiments",
                              "--out", str(tmp_path / "x")])
    assert out.exit_code == 0, out.output
    rows = [json.loads(line) for line in (tmp_path / "x" / "experiments.jsonl").read_text().splitlines()]
    assert len(rows) == 6 and all("param.concentration_mm" in r and "param.temperature_k" not in r for r in rows)


@pytest.mark.process
def test_two_campaigns_on_a_scaled_clock_over_zenoh_with_a_device_in_another_process(tmp_path):
    import socket
    import subprocess
    import sys

    import yaml

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    raw = yaml.safe_load(LAB.read_text())
    raw["clock"] = {"mode": "scaled", "speed": 3000}
    raw["bus"] = {"kind": "zenoh", "listen": [f"tcp/127.0.0.1:{port}"]}
    raw["orchestrator"]["startup_s"] = 3000
    for c, budget in zip(raw["campaigns"], (5, 3)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    raw["campaigns"][1]["chemistry"]["parameters"]["time_s"] = {"low": 600, "high": 900, "unit": "s"}
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


@pytest.mark.process
def test_twin_lab_serve_takes_campaigns_from_twin_submit_and_lists_them(tmp_path):
    """A served lab starts empty; two campaigns are submitted over Zenoh, `twin ctl status` lists them, one is
    paused by name; SIGTERM ends the lab with each campaign's summary and journal."""
    import signal
    import socket
    import subprocess
    import sys
    import time

    import yaml
    from typer.testing import CliRunner

    from tests.rrd import read_rrd
    from twin.campaign.journal import read_run
    from twin.cli import app

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    raw = yaml.safe_load(LAB.read_text())
    campaigns = raw.pop("campaigns")
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    for c, budget in zip(campaigns, (4, 3)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
        (tmp_path / f"{c['name']}.yaml").write_text(yaml.safe_dump(c))
    lab = subprocess.Popen([sys.executable, "-m", "twin", "lab", "serve", str(tmp_path / "lab.yaml"), "--listen",
                            f"tcp/127.0.0.1:{port}", "--speed", "3000", "--journal", str(tmp_path / "runs")],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
    runner, connect = CliRunner(), ["--lab", "shared", "--connect", f"tcp/127.0.0.1:{port}"]
    watcher = None

    def ctl(*args):
        return runner.invoke(app, [*args, *connect], env={"COLUMNS": "100"})

    try:
        line = lab.stderr.readline()
        assert "serving lab shared" in line, line + lab.stderr.read() if lab.poll() is not None else line
        assert ctl("submit", str(tmp_path / "dots.yaml"), "--as", "qd-group").exit_code == 0
        watcher = subprocess.Popen([sys.executable, "-m", "twin", "watch", "--lab", "shared", "--connect",
                                    f"tcp/127.0.0.1:{port}", "--save", str(tmp_path / "w.rrd"), "--follow"],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
        assert "watching lab" in watcher.stdout.readline()
        sub = ctl("submit", str(tmp_path / "catalyst.yaml"))
        assert sub.exit_code == 0 and "campaign catalyst started on lab shared" in sub.output, sub.output
        again = ctl("submit", str(tmp_path / "dots.yaml"))
        assert again.exit_code == 1 and "has a campaign 'dots' already" in again.output
        listed = ctl("ctl", "status")
        assert listed.exit_code == 0 and "dots" in listed.output and "catalyst" in listed.output, listed.output
        both = ctl("ctl", "pause")
        assert both.exit_code == 1 and "name one with --campaign" in both.output
        paused = ctl("ctl", "pause", "--campaign", "catalyst", "--as", "alice")
        assert paused.exit_code == 0 and "paused" in paused.output, paused.output
        assert ctl("ctl", "resume", "--campaign", "catalyst").exit_code == 0
        wait_until_ended(lambda: json.loads(ctl("ctl", "status", "--json").output), 2)
        lab.send_signal(signal.SIGTERM)
        out, err = lab.communicate(timeout=60)
        time.sleep(1.0)  # the campaigns' summaries reach the watcher
        watcher.send_signal(signal.SIGTERM)
        _, watch_err = watcher.communicate(timeout=60)
    finally:
        kill_all(lab, watcher)
    assert lab.returncode == 0, err[-2000:]
    assert watcher.returncode == 0, watch_err[-2000:]
    drawn = read_rrd(tmp_path / "w.rrd")  # a campaign submitted after the watcher joined has its tab too
    for name, budget in (("dots", 4), ("catalyst", 3)):
        assert drawn[f"campaigns/{name}/campaign/finished"][-1]["Scalars:scalars"][0] == budget, name
        assert len(drawn[f"campaigns/{name}/summary"]) == 1, name
    assert {p.split("/")[1] for p in drawn if p.startswith("devices/")} == {
        "synthesiser-1", "synthesiser-2", "reactor", "spectrometer"}
    assert "dots (quantum-dot" in out and "catalyst" in out
    runs = tmp_path / "runs"
    for name, budget in (("dots", 4), ("catalyst", 3)):
        summary = read_run(runs / f"{name}.db")["summary"]
        assert summary["done"] + summary["abandoned"] == budget == summary["proposed"]
    events_ = [e[1] for e in events(runs / "catalyst.db", "operator.pause", "operator.resume", "campaign.submitted")]
    assert events_[0] == "campaign.submitted" and "operator.pause" in events_ and "operator.resume" in events_
    assert_one_step_at_a_time(runs)


def test_hostile_submissions_are_refused_with_the_reason_and_the_lab_goes_on(tmp_path):
    """What `twin submit` could be sent by anyone with the operator's key: every bad one is answered with why,
    and the lab keeps serving the campaign it has."""
    import asyncio

    from twin.runtime.shared_run import serve_lab

    s = prepare(LAB, clock="scaled", speed=50_000, bus="memory",
                overrides={"campaigns.0.campaign.budget": 2, "campaigns.0.campaign.planner": "random",
                           "campaigns": [load(LAB).campaigns[0].model_dump(exclude_none=True)]}, lab_only=True)
    bomb = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{k}: &{k} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
        for p, k in zip("abcdefg", "bcdefgh"))
    hostile = {
        b"not json": "not JSON",
        b"[1, 2]": "not a JSON object",
        json.dumps({"file": 42}).encode(): "give the text of a campaign file",
        json.dumps({"file": "name: [unclosed"}).encode(): "not valid YAML",
        json.dumps({"file": bomb}).encode(): "values",
        json.dumps({"file": "name: x\nbudget: 3\n"}).encode(): "budget: unknown field",
        json.dumps({"file": "name: dots\n"}).encode(): "has a campaign 'dots' already",
        json.dumps({"file": "name: y\nafter: dots\n"}).encode(): "after / start_h",
        json.dumps({"file": "name: z\nworkflow: [{step: melt, device: furnace}]\n"}).encode(): "furnace",
        b"{" + b" " * (1 << 21) + b"}": "bytes; at most",
    }
    answers: dict = {}

    def started(lab) -> None:
        async def ask() -> None:
            for payload in hostile:
                answers[payload] = json.loads(await lab.desk.serve("labtwin/shared/control/submit", payload))
            lab.stop("test over")
        asyncio.ensure_future(ask())

    out = serve_lab(s, tmp_path, handle_signals=False, on_start=started)
    for payload, words in hostile.items():
        answer = answers[payload]
        assert answer["ok"] is False and words in answer["error"], (payload[:60], answer)
    assert list(out.campaigns) == ["dots"] and sorted(p.stem for p in tmp_path.glob("*.db")) == ["dots"]


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


def recorded_lab(s, where: Path):
    """Run ``s`` with its recording saved, and read the recording back."""
    from tests.rrd import read_rrd
    from twin.view.watch import RecordOptions, open_lab_observer

    devices = {name: dtype for dtype in s.devices for name in s.instance_names(dtype)}
    observer, recording = open_lab_observer(RecordOptions(save=where / "lab.rrd"), "t",
                                            [c.name for c in s.campaigns], devices)
    try:
        out = run_shared(s, where / "runs", handle_signals=False, observer=observer)
    finally:
        recording.close()
    return out, read_rrd(where / "lab.rrd", row_ids=True)


def states(rows: list[dict]) -> list[tuple[float, str]]:
    """A device's (lab time, state) changes in the order they were drawn."""
    changes = [r for r in rows if "StateChange:state" in r]
    return [(r["lab_time"], r["StateChange:state"][0]) for r in sorted(changes, key=lambda r: (r["lab_time"],
                                                                                               r["row_id"]))]


def busy_spells(rows: list[dict]) -> list[tuple[float, float]]:
    """(from, to) of each busy spell of a device's state rows; a second 'busy' before the first ended fails."""
    spells, since = [], None
    for t, state in states(rows):
        if state == "busy":
            assert since is None, f"busy again at {t} while busy since {since}: two steps at once"
            since = t
        elif since is not None:
            spells.append((since, t))
            since = None
    return spells


def test_a_shared_lab_is_recorded_with_its_devices_once_and_a_panel_per_campaign(tmp_path):
    """`twin run LAB.yaml --save`: the devices' states at the top come from every campaign's steps (each step
    once, never two at a time, adding up to the lab's utilisation); each campaign's objective, log and summary
    are under campaigns/<name>/. The second campaign comes while the first has steps in the lab."""
    s = prepare(LAB, seed=2, overrides={"campaigns.1.start_h": 1.5})
    out, rrd = recorded_lab(s, tmp_path)
    lab_s = out.lab_hours * 3600
    for device, share in out.utilisation.items():
        lab_spells = busy_spells(rrd[f"devices/{device}"])
        mine = [sp for c in out.campaigns for sp in busy_spells(rrd.get(f"campaigns/{c}/devices/{device}", []))]
        assert sorted(lab_spells) == sorted(mine), device  # the lab's row is the campaigns' steps, each once
        assert sum(b - a for a, b in lab_spells) / lab_s == pytest.approx(share, abs=0.01), device
    for name, c in out.campaigns.items():
        finished = rrd[f"campaigns/{name}/campaign/finished"]
        assert finished[-1]["Scalars:scalars"][0] == c.done + c.abandoned, name
        assert len(rrd[f"campaigns/{name}/summary"]) == 1 and len(rrd[f"campaigns/{name}/log"]) > 5
        assert any(p.startswith(f"campaigns/{name}/objective/") for p in rrd)
    assert "log" not in rrd and "objective/score" not in rrd  # nothing of a campaign's drawn at the lab's level
    for device in out.utilisation:  # the campaign that came later found the devices there, not offline
        at_start = [state for t, state in states(rrd[f"campaigns/catalyst/devices/{device}"]) if t == 5400.0]
        assert at_start[-1] != "offline", (device, at_start)
    assert any(p.startswith("telemetry/") for p in rrd)


def test_a_shared_lab_on_a_scaled_clock_is_recorded_too(tmp_path):
    s = prepare(LAB, clock="scaled", speed=50_000, bus="memory", seed=3,
                overrides={"campaigns.0.campaign.budget": 4, "campaigns.1.campaign.budget": 3})
    out, rrd = recorded_lab(s, tmp_path)
    for name, c in out.campaigns.items():
        assert rrd[f"campaigns/{name}/campaign/finished"][-1]["Scalars:scalars"][0] == c.done + c.abandoned
        assert rrd[f"campaigns/{name}/spectra/measurement"], name  # results reach their campaign's panel
    for device in out.utilisation:
        busy_spells(rrd[f"devices/{device}"])


def test_twin_watch_of_a_served_lab_draws_each_campaign_even_one_submitted_after_it_joined(tmp_path):
    """A watcher joins a served lab late (it reads each campaign's history), and a campaign submitted after it
    joined gets its own tab; what it draws agrees with the campaigns' summaries and never shows a device
    running two steps."""
    import asyncio

    import yaml

    from tests.rrd import read_rrd
    from twin.runtime.shared_run import serve_lab
    from twin.view.watch import RecordOptions, watch_async

    raw = yaml.safe_load(LAB.read_text())
    late = {**raw["campaigns"][0], "name": "late"}
    late["campaign"] = {**late["campaign"], "budget": 2, "planner": "random", "stop_on_target": False}
    s = prepare(LAB, clock="scaled", speed=50_000, bus="memory", seed=6, overrides={
        "campaigns.0.campaign.budget": 4, "campaigns.1.campaign.budget": 3,
        "campaigns.0.campaign.planner": "random", "campaigns.1.campaign.planner": "random"})
    rrd = tmp_path / "watch.rrd"
    watched: dict = {}

    def started(lab) -> None:
        async def go() -> None:
            try:
                await watch_and_submit()
            finally:
                lab.stop("test over")

        async def watch_and_submit() -> None:
            await lab.clock.sleep(2 * 3600)  # join late: the campaigns' first steps come from their histories
            stop = asyncio.Event()
            watcher = asyncio.ensure_future(watch_async(lab.bus, lab.clock, "shared", RecordOptions(save=rrd),
                                                        follow=True, stop=stop))
            await lab.clock.sleep(1800)
            answer = json.loads(await lab.desk.serve("labtwin/shared/control/submit",
                                                     json.dumps({"file": yaml.safe_dump(late)}).encode()))
            assert answer["ok"], answer
            while not all(c.finished for c in lab.shared.cores.values()):
                await lab.clock.sleep(600)
            await lab.clock.sleep(1200)
            stop.set()
            watched["observer"] = await watcher
        watched["task"] = asyncio.ensure_future(go())

    out = serve_lab(s, tmp_path / "runs", handle_signals=False, on_start=started)
    assert watched["task"].exception() is None
    assert set(out.campaigns) == {"dots", "catalyst", "late"}
    drawn = read_rrd(rrd, row_ids=True)
    for name, c in out.campaigns.items():
        finished = drawn[f"campaigns/{name}/campaign/finished"]
        assert finished[-1]["Scalars:scalars"][0] == c.done + c.abandoned, name
        assert drawn[f"campaigns/{name}/log"] and drawn[f"campaigns/{name}/objective/score"], name
    for device in out.utilisation:
        lab_spells = busy_spells(drawn[f"devices/{device}"])
        mine = [sp for c in out.campaigns for sp in busy_spells(drawn.get(f"campaigns/{c}/devices/{device}", []))]
        assert sorted(lab_spells) == sorted(mine), device
    assert set(watched["observer"].campaigns) == {"dots", "catalyst", "late"}


SMALL = {"campaigns.0.campaign.budget": 6, "campaigns.1.campaign.budget": 4, "campaigns.1.start_h": 1.0}


def journal_tables(journals: Path) -> dict[str, tuple]:
    out = {}
    for db in sorted(journals.glob("*.db")):
        with sqlite3.connect(db) as c:
            out[db.stem] = (c.execute("SELECT * FROM events ORDER BY seq").fetchall(),
                            c.execute("SELECT * FROM experiments ORDER BY id").fetchall())
    return out


def _lab_killed_at(s, where: Path, row: int) -> None:
    """In a child process: run the lab and SIGKILL itself when its campaigns have written ``row`` events."""
    import os
    import signal

    from twin.campaign.journal import Journal

    written = [0]
    append = Journal._append

    def dying(self, *r):
        written[0] += 1
        if written[0] == row:
            os.kill(os.getpid(), signal.SIGKILL)
        append(self, *r)

    Journal._append = dying
    run_shared(s, where, handle_signals=False)


@pytest.mark.parametrize("at", [0.1, 0.5, 0.9])
def test_a_lab_killed_anywhere_and_resumed_ends_with_the_journals_of_the_unkilled_one(tmp_path, at):
    import multiprocessing
    import signal

    from twin.runtime.resume_lab import resume_lab

    s = prepare(LAB, seed=3, overrides=SMALL)
    run_shared(s, tmp_path / "whole", handle_signals=False)
    whole = journal_tables(tmp_path / "whole")
    row = max(1, int(at * sum(len(t[0]) for t in whole.values())))
    child = multiprocessing.get_context("fork").Process(target=_lab_killed_at, args=(s, tmp_path / "killed", row))
    child.start()
    child.join(60)
    assert child.exitcode == -signal.SIGKILL
    assert any("summary" not in read_run(db) for db in (tmp_path / "killed").glob("*.db"))
    from typer.testing import CliRunner

    from twin.cli import app

    told = CliRunner().invoke(app, ["report", str(tmp_path / "killed")], env={"COLUMNS": "300"})
    assert told.exit_code == 0 and f"Continue it with: twin resume {tmp_path / 'killed'}" in told.output
    out = resume_lab(tmp_path / "killed", handle_signals=False)
    assert journal_tables(tmp_path / "killed") == whole
    assert out.journals == str(tmp_path / "killed") and set(out.campaigns) == {"dots", "catalyst"}
    assert not (tmp_path / "killed.resuming").exists()


def test_twin_resume_of_a_lab_that_diverges_names_the_campaign_and_event_and_keeps_the_journals(tmp_path):
    from typer.testing import CliRunner

    from twin.cli import app

    run_shared(prepare(LAB, seed=3, overrides=SMALL), tmp_path, handle_signals=False)
    for db in tmp_path.glob("*.db"):
        with sqlite3.connect(db) as c:
            c.execute("DELETE FROM run WHERE key='summary'")
    with sqlite3.connect(tmp_path / "catalyst.db") as c:
        c.execute("UPDATE events SET kind='device.lost' WHERE seq=12")
    before = journal_tables(tmp_path)
    result = CliRunner().invoke(app, ["resume", str(tmp_path)], env={"COLUMNS": "200"})
    assert result.exit_code == 2
    assert "catalyst.db: event 12 differs from the journal: it recorded 'device.lost'" in " ".join(result.output.split())
    assert journal_tables(tmp_path) == before


def test_twin_resume_of_a_finished_lab_says_so(tmp_path):
    from typer.testing import CliRunner

    from twin.cli import app

    run_shared(prepare(LAB, seed=3, overrides=SMALL), tmp_path, handle_signals=False)
    result = CliRunner().invoke(app, ["resume", str(tmp_path)], env={"COLUMNS": "200"})
    assert result.exit_code == 2 and "every campaign of the lab finished" in " ".join(result.output.split())


@pytest.mark.process
@pytest.mark.parametrize("kills", [1, 2])
def test_a_live_lab_sigkilled_and_resumed_finishes_every_campaign_and_keeps_what_its_journals_held(tmp_path, kills):
    """A lab on a scaled clock, SIGKILLed once experiments have finished (and, the second time, its resumed
    process SIGKILLed too), is rebuilt by `twin resume` from the inputs it journalled: every campaign's journal
    keeps what it held, the steps it had in the lab are asked after (here its in-process devices died with it:
    the steps are retried), and every campaign ends with its accounting invariant and no device running two
    steps."""
    import signal
    import subprocess
    import sys
    import time

    import yaml
    from typer.testing import CliRunner

    from twin.cli import app

    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (4, 3)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    where = tmp_path / "j"
    lab = subprocess.Popen([sys.executable, "-m", "twin", "run", str(tmp_path / "lab.yaml"), "--clock", "scaled",
                            "--speed", "4000", "--bus", "memory", "--journal", str(where), "--quiet"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)

    def finished() -> int:
        n = 0
        for db in where.glob("*.db"):
            try:
                with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
                    n += con.execute("SELECT COUNT(*) FROM experiments WHERE status='done'").fetchone()[0]
            except sqlite3.Error:
                pass
        return n

    try:
        for kill in range(kills):
            if kill:  # the resumed lab dies too, once it finished more
                lab = subprocess.Popen([sys.executable, "-m", "twin", "resume", str(where), "--quiet"],
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
            deadline, wanted = time.monotonic() + 60, 2 + 2 * kill
            while finished() < wanted and time.monotonic() < deadline and lab.poll() is None:
                time.sleep(0.05)
            assert lab.poll() is None, "the lab ended before it could be killed: " + lab.stderr.read()[-1000:]
            lab.send_signal(signal.SIGKILL)
            lab.communicate(timeout=30)
    finally:
        kill_all(lab)
    held = journal_tables(where)
    assert all("summary" not in read_run(db) for db in where.glob("*.db"))
    result = CliRunner().invoke(app, ["resume", str(where), "--json"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    out = json.loads(result.output[result.output.index("{"):])
    for name, budget in (("dots", 4), ("catalyst", 3)):
        c = out["campaigns"][name]
        assert c["done"] + c["abandoned"] == budget == c["proposed"] and c["pending"] == 0, (name, c)
        events_now = journal_tables(where)[name][0]
        assert events_now[:len(held[name][0])] == held[name][0], name  # what the journal held is kept
        assert len([e for e in events_now if e[2] == "campaign.resumed"]) == kills, name
    assert_one_step_at_a_time(where)


@pytest.mark.process
def test_a_shared_lab_killed_with_a_step_on_a_device_of_another_process_adopts_its_result_once(tmp_path):
    """Over Zenoh, a router and the spectrometer in other processes: the lab is SIGKILLed while the spectrometer
    measures one campaign's sample; the measurement finishes while nobody listens; `twin resume` asks the device
    and takes that result, once, for the campaign it was for."""
    import os
    import signal
    import subprocess
    import sys
    import time

    import yaml

    from twin.campaign.journal import read_events
    from tests.twin.test_device_process import free_port
    from tests.twin.test_distributed_lab import start

    router, speed = f"tcp/127.0.0.1:{free_port()}", 1000.0
    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (3, 2)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    raw["devices"]["spectrometer"]["duration"] = {"mean_s": 1500, "cv": 0.0}
    raw["devices"]["synthesiser"]["duration"] = {"mean_s": 200, "cv": 0.0}
    for d in raw["devices"].values():
        d["faults"] = {}
    raw.update(clock={"mode": "scaled", "speed": speed},
               bus={"kind": "zenoh", "listen": [], "connect": [router], "lease_ms": 1000},
               orchestrator={**raw["orchestrator"], "startup_s": 40000, "orphan_grace_s": 10 ** 6,
                             "timeout_slack_s": 40000})
    path, where = tmp_path / "lab.yaml", tmp_path / "j"
    path.write_text(yaml.safe_dump(raw))
    procs = {"router": start(["router", "--listen", router], "router")}
    procs["spec"] = start(["device", "serve", str(path), "--id", "spectrometer", "--connect", router, "--clock",
                           "scaled", "--speed", str(speed)], "ready spectrometer")
    # what is dispatched is on disk before the command leaves (write-ahead); a measurement takes 1.5 s of wall time
    running = ("SELECT COUNT(*) FROM events d WHERE d.kind='attempt.dispatched' AND d.device='spectrometer' AND NOT "
               "EXISTS (SELECT 1 FROM events e WHERE e.task=d.task AND e.attempt=d.attempt AND e.seq>d.seq)")
    try:
        lab = subprocess.Popen([sys.executable, "-m", "twin", "run", str(path), "--journal", str(where), "--quiet",
                                "--external", "spectrometer"], cwd=ROOT, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE)
        deadline, on_spec = time.monotonic() + 90, []
        while lab.poll() is None and time.monotonic() < deadline and not on_spec:
            for db in where.glob("*.db"):
                try:
                    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
                        if con.execute(running).fetchone()[0]:
                            on_spec.append(db.stem)
                except sqlite3.Error:
                    pass
            time.sleep(0.01)
        time.sleep(0.4)  # the spectrometer has the command and measures
        os.kill(lab.pid, signal.SIGKILL)  # the lab dies with a measurement running on the remote spectrometer
        lab.wait()
        assert on_spec, "no measurement ran before the deadline: " + lab.stderr.read().decode()[-1000:]
        campaign = on_spec[0]
        killed = next(e["task"] for e in reversed(read_events(where / f"{campaign}.db"))
                      if e["kind"] == "attempt.dispatched" and e["device"] == "spectrometer")
        time.sleep(2.0)  # the measurement (1.5 s of wall time) finishes while nobody listens
        resumed = subprocess.run([sys.executable, "-m", "twin", "resume", str(where), "--json"], cwd=ROOT,
                                 capture_output=True, text=True, timeout=180)
        assert resumed.returncode == 0, resumed.stderr[-3000:]
    finally:
        for p in procs.values():
            p.kill()
            p.wait()
    out = json.loads(resumed.stdout)
    events_ = read_events(where / f"{campaign}.db")
    done = [e for e in events_ if e["kind"] == "attempt.done" and e["task"] == killed]
    assert len(done) == 1 and done[0]["device"] == "spectrometer", "the finished result is adopted, once"
    assert done[0]["t_lab"] >= next(e["t_lab"] for e in events_ if e["kind"] == "campaign.resumed")
    assert not [e for e in events_ if e["kind"] == "attempt.failed" and e["task"] == killed]
    for name, budget in (("dots", 3), ("catalyst", 2)):
        c = out["campaigns"][name]
        assert c["done"] + c["abandoned"] == budget == c["proposed"] and c["pending"] == 0, (name, c)
    assert_one_step_at_a_time(where)


@pytest.mark.process
@pytest.mark.parametrize("with_campaigns", [True, False])
def test_a_served_lab_sigkilled_and_resumed_goes_on_serving_and_takes_submissions(tmp_path, with_campaigns):
    """A served lab killed with campaigns under way (or before any came) is resumed by `twin resume` of its
    journals' directory, serves again, and takes a submission; SIGTERM ends it with every campaign accounted."""
    import signal
    import subprocess
    import sys
    import time

    import yaml
    from typer.testing import CliRunner

    from twin.cli import app
    from tests.twin.test_device_process import free_port

    port = free_port()
    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (3, 2)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    late = {**raw["campaigns"][0], "name": "late"}
    late["campaign"] = {**late["campaign"], "budget": 2}
    budgets = {"dots": 3, "catalyst": 2, "late": 2} if with_campaigns else {"late": 2}
    if not with_campaigns:
        del raw["campaigns"]
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    (tmp_path / "late.yaml").write_text(yaml.safe_dump(late))
    where = tmp_path / "runs"
    serve = [sys.executable, "-m", "twin", "lab", "serve", str(tmp_path / "lab.yaml"), "--listen",
             f"tcp/127.0.0.1:{port}", "--speed", "3000", "--journal", str(where)]
    runner, connect = CliRunner(), ["--lab", "shared", "--connect", f"tcp/127.0.0.1:{port}"]
    first = subprocess.Popen(serve, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
    again = None
    try:
        assert "serving lab shared" in first.stderr.readline()
        if with_campaigns:  # a campaign paused by an operator is still paused after the lab is resumed
            paused = runner.invoke(app, ["ctl", "pause", "--campaign", "catalyst", "--as", "alice", *connect])
            assert paused.exit_code == 0, paused.output
        deadline = time.monotonic() + 60
        what = ((where / "dots.db", "SELECT COUNT(*) FROM experiments WHERE status='done'") if with_campaigns else
                (where / "lab.inputs", "SELECT COUNT(*) FROM inputs"))  # killed once it did something
        while time.monotonic() < deadline:
            try:
                with sqlite3.connect(f"file:{what[0]}?mode=ro", uri=True) as con:
                    if con.execute(what[1]).fetchone()[0]:
                        break
            except sqlite3.Error:
                pass
            time.sleep(0.05)
        first.send_signal(signal.SIGKILL)
        first.communicate(timeout=30)
        again = subprocess.Popen([sys.executable, "-m", "twin", "resume", str(where), "--json"],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
        line = again.stderr.readline()
        while line and "resumed lab shared" not in line:
            line = again.stderr.readline()
        assert "serving again" in line, again.stderr.read()[-2000:] if again.poll() is not None else line
        if with_campaigns:
            states = {c["campaign"]: c["state"] for c in json.loads(
                runner.invoke(app, ["ctl", "status", "--json", *connect]).output)["campaigns"]}
            assert states["catalyst"] == "paused by alice", states
            assert runner.invoke(app, ["ctl", "resume", "--campaign", "catalyst", *connect]).exit_code == 0
        sub = runner.invoke(app, ["submit", str(tmp_path / "late.yaml"), *connect])
        assert sub.exit_code == 0 and "campaign late started" in sub.output, sub.output
        wait_until_ended(lambda: json.loads(runner.invoke(app, ["ctl", "status", "--json", *connect]).output),
                         len(budgets))
        again.send_signal(signal.SIGTERM)
        out, err = again.communicate(timeout=60)
    finally:
        kill_all(first, again)
    assert again.returncode == 0, err[-2000:]
    summary = json.loads(out)
    assert set(summary["campaigns"]) == set(budgets)
    for name, budget in budgets.items():
        c = summary["campaigns"][name]
        assert c["done"] + c["abandoned"] == budget == c["proposed"], (name, c)
    assert_one_step_at_a_time(where)


@pytest.mark.parametrize("batches, words", [
    ([], "do not begin with its start"),
    ([(0.0, {"start": True, "secrets": {}}), (5.0, {"items": [["bogus", 1]]})], "lab input batch 2 of 2"),
    ([(0.0, {"start": True, "secrets": {}}), (5.0, {"items": [["seat", "dots"]]})], "lab input batch 2 of 2"),
])
def test_damaged_lab_inputs_are_named(batches, words):
    from twin.campaign.journal import NullJournal
    from twin.campaign.lab_replay import rebuild_lab
    from twin.campaign.replay import ReplayError
    from twin.scenario.sharing import campaign_scenarios

    s = prepare(LAB, clock="scaled", bus="memory")
    with pytest.raises(ReplayError, match=words):
        rebuild_lab(s, campaign_scenarios(s, s.name), batches, lambda name, cs: NullJournal())


@pytest.mark.parametrize("seed, overrides", [(1, {}), (3, {"campaigns.1.start_h": 1.5}),
                                             (4, {"campaigns.1.after": "dots"})])
def test_twin_replay_of_a_labs_journals_equals_its_live_recording_as_rerun_compares_them(tmp_path, seed, overrides):
    import subprocess
    import sys

    from twin.view.watch import RecordOptions, replay

    s = prepare(LAB, seed=seed, overrides={**SMALL, **overrides})
    recorded_lab(s, tmp_path)
    replay(tmp_path / "runs", RecordOptions(save=tmp_path / "replay.rrd"))

    def compare(a, b):
        return subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "compare", "--unordered", str(a),
                               str(b)], capture_output=True, text=True, timeout=120)

    same = compare(tmp_path / "lab.rrd", tmp_path / "replay.rrd")
    assert same.returncode == 0, same.stdout[-2000:] + same.stderr[-2000:]
    other = prepare(LAB, seed=seed + 1, overrides={**SMALL, **overrides})
    recorded_lab(other, tmp_path / "other")
    assert compare(tmp_path / "lab.rrd", tmp_path / "other" / "lab.rrd").returncode != 0



@pytest.mark.process
def test_twin_watch_without_follow_ends_by_itself_when_every_campaign_has_ended(tmp_path):
    import subprocess
    import sys

    import yaml

    from tests.rrd import read_rrd
    from tests.twin.test_device_process import free_port

    port = free_port()
    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (3, 2)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    lab = subprocess.Popen([sys.executable, "-m", "twin", "run", str(tmp_path / "lab.yaml"), "--clock", "scaled",
                            "--speed", "2000", "--listen", f"tcp/127.0.0.1:{port}", "--journal",
                            str(tmp_path / "runs"), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           cwd=ROOT, text=True)
    watcher = subprocess.Popen([sys.executable, "-m", "twin", "watch", "--lab", "shared", "--connect",
                                f"tcp/127.0.0.1:{port}", "--save", str(tmp_path / "w.rrd")],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
    try:
        lab.communicate(timeout=120)
        _, err = watcher.communicate(timeout=60)  # it ends without being told to
    finally:
        kill_all(lab, watcher)
    assert lab.returncode == 0 and watcher.returncode == 0, err[-2000:]
    assert "recorded" in err
    drawn = read_rrd(tmp_path / "w.rrd")
    for name in ("dots", "catalyst"):
        assert len(drawn[f"campaigns/{name}/summary"]) == 1, name


@pytest.mark.parametrize("spec", ["mwkr", "rl:agents/policies/flaky_scheduler.zip"])
def test_one_scheduler_for_the_lab_chooses_among_every_campaigns_steps(tmp_path, monkeypatch, spec):
    """orchestrator.lab_scheduler: the rule or policy is asked once per pass with the ready steps of every
    campaign that asked (named campaign/task), and what it picks is dispatched by the campaign it belongs to."""
    from twin.runtime import shared_run

    views: list = []
    made = shared_run._lab_scheduler

    def spied(s, scenarios):
        chosen = made(s, scenarios)
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


def test_one_scheduler_for_the_lab_is_refused_on_a_live_clock_with_the_reason(tmp_path):
    from twin.core.errors import ClockError

    s = prepare(LAB, clock="scaled", bus="memory", overrides={"orchestrator.lab_scheduler": "mwkr"})
    with pytest.raises(ClockError, match="lab_scheduler runs in virtual time"):
        run_shared(s, tmp_path, handle_signals=False)
    assert not list(tmp_path.glob("*.db"))


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
