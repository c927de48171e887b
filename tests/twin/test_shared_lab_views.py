"""A lab of several campaigns recorded, watched from another process, replayed from its journals."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from twin.campaign.journal_read import read_events
from twin.runtime.lab import prepare

from tests.twin.shared_labs import (LAB, ROOT, SMALL, busy_spells, kill_all, lines_until, recorded_lab, states)


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
    # every reading the campaigns took, live or from the histories, once (a watcher holds each until it is named)
    readings = sum(len(json.loads(e["detail"])["body"]["readings"]) for db in (tmp_path / "runs").glob("*.db")
                   for e in read_events(db, "msg.telemetry"))
    assert sum(len(rows) for path, rows in drawn.items() if path.startswith("telemetry/")) == readings > 0


@pytest.mark.parametrize("seed, overrides, runtime", [(1, {}, "auto"), (3, {"campaigns.1.start_h": 1.5}, "auto"),
                                                      (4, {"campaigns.1.after": "dots"}, "auto"), (1, {}, "asyncio")])
def test_twin_replay_of_a_labs_journals_equals_its_live_recording_as_rerun_compares_them(tmp_path, seed, overrides,
                                                                                        runtime):
    """On either runtime: the asyncio one flushed the recording every quarter lab-second of a virtual clock, in
    hundreds of chunks that Rerun's comparison could not match with the replay's."""
    import subprocess
    import sys

    from twin.view.watch import RecordOptions, replay

    s = prepare(LAB, seed=seed, overrides={**SMALL, **overrides})
    recorded_lab(s, tmp_path, runtime)
    replay(tmp_path / "runs", RecordOptions(save=tmp_path / "replay.rrd"))

    def compare(a, b):
        return subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "compare", "--unordered", str(a),
                               str(b)], capture_output=True, text=True, timeout=120)

    same = compare(tmp_path / "lab.rrd", tmp_path / "replay.rrd")
    assert same.returncode == 0, same.stdout[-2000:] + same.stderr[-2000:]
    other = prepare(LAB, seed=seed + 1, overrides={**SMALL, **overrides})
    recorded_lab(other, tmp_path / "other")
    assert compare(tmp_path / "lab.rrd", tmp_path / "other" / "lab.rrd").returncode != 0



def _watcher(tmp_path: Path, port: int, *more: str) -> subprocess.Popen:
    """`twin watch` of the shared lab at ``port``, recording to w.rrd."""
    return subprocess.Popen([sys.executable, "-m", "twin", "watch", "--lab", "shared", "--connect",
                             f"tcp/127.0.0.1:{port}", "--save", str(tmp_path / "w.rrd"), "--wait", "60", *more],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)


def _small_lab_run(tmp_path: Path, port: int, journal: str, output=subprocess.DEVNULL) -> subprocess.Popen:
    """The shared lab with 3 and 2 random experiments, run on a scaled clock, listening at ``port``."""
    raw = yaml.safe_load(LAB.read_text())
    for c, budget in zip(raw["campaigns"], (3, 2)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    return subprocess.Popen([sys.executable, "-m", "twin", "run", str(tmp_path / "lab.yaml"), "--clock", "scaled",
                             "--speed", "2000", "--listen", f"tcp/127.0.0.1:{port}", "--journal",
                             str(tmp_path / journal), "--quiet"], stdout=output, stderr=output, cwd=ROOT, text=True)


@pytest.mark.process
def test_twin_watch_without_follow_ends_by_itself_when_every_campaign_has_ended(tmp_path):
    from tests.rrd import read_rrd
    from tests.twin.test_device_process import free_port

    port = free_port()
    # the watcher first: it waits for the lab's endpoint to come up (--wait), however long the lab takes to start
    watcher = _watcher(tmp_path, port)
    lab = _small_lab_run(tmp_path, port, "runs", subprocess.PIPE)
    try:
        lab.communicate(timeout=120)
        out, err = watcher.communicate(timeout=60)  # it ends without being told to
    finally:
        kill_all(lab, watcher)
    assert lab.returncode == 0 and watcher.returncode == 0, err[-2000:]
    assert "campaign catalyst ended: 2 experiments" in out and "campaign dots ended: 3 experiments" in out, out
    assert "recorded" in err
    drawn = read_rrd(tmp_path / "w.rrd")
    for name in ("dots", "catalyst"):
        assert len(drawn[f"campaigns/{name}/summary"]) == 1, name


@pytest.mark.process
def test_a_following_watch_of_a_shared_lab_ends_when_the_lab_comes_back_with_another_run(tmp_path):
    """`twin watch --follow` on a lab of several campaigns took the lab's next run (the same file, `twin run`
    again) for a resume and drew its campaigns into the same recording; each campaign's history names its run,
    and the watch now ends there, saying so, with the first run recorded."""
    from tests.rrd import read_rrd
    from tests.twin.test_device_process import free_port

    port = free_port()
    watcher = _watcher(tmp_path, port, "--follow")
    first = second = None
    try:
        first = _small_lab_run(tmp_path, port, "first")
        said = lines_until(watcher.stdout, {"is on the bus"}, 120)  # the watch has the first run
        assert "lab 'shared' is on the bus" in said[-1], said
        assert first.wait(timeout=120) == 0
        second = _small_lab_run(tmp_path, port, "second")
        assert second.wait(timeout=120) == 0
        watcher.wait(timeout=60)  # it ends without being told to
        err = watcher.stderr.read()
    finally:
        kill_all(watcher, first, second)
    assert watcher.returncode == 0, err[-2000:]
    said = " ".join(err.split())
    assert "lab 'shared' came back with another run of campaign" in said and "start another `twin watch`" in said, err
    drawn = read_rrd(tmp_path / "w.rrd")
    for name in ("dots", "catalyst"):  # the first run's, and nothing of the second's
        assert len(drawn[f"campaigns/{name}/summary"]) == 1, name
