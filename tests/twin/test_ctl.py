"""`twin ctl` against a live campaign in another process, over Zenoh on loopback: a pause takes effect at once and
holds (no dispatch until resume), survives SIGKILL + `twin resume`, and hostile requests are refused by field."""

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab, twin_cli
from tests.twin.test_device_process import free_port
from twin.campaign.journal_read import read_events, read_run
from twin.core import keys
from twin.core.bus import NoReplyError, open_bus
from twin.core.clock import LabClock

ROOT = Path(__file__).resolve().parents[2]
TWIN = [sys.executable, "-m", "twin"]


def live_lab(tmp_path, endpoint, **changes):
    lab = qd_lab(**{"campaign.budget": 12, "campaign.max_in_flight": 3, "clock": {"mode": "scaled", "speed": 300},
                    "bus": {"kind": "zenoh", "listen": [endpoint]}, "devices.spectrometer.instances": 2,
                    "devices.synthesiser.duration": {"mean_s": 30, "cv": 0.0},
                    "devices.spectrometer.duration": {"mean_s": 60, "cv": 0.0}, **changes})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(lab))
    return path


class Operator:
    """One Zenoh client session of an operator, as `twin ctl` opens it."""

    def __init__(self, endpoint):
        self.endpoint = endpoint

    async def __aenter__(self):
        host, port = self.endpoint.split("/")[1].split(":")
        deadline = time.monotonic() + 60
        while True:  # the campaign's process is starting: wait until its session listens
            try:
                socket.create_connection((host, int(port)), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, f"nothing ever listened at {self.endpoint}"
                await asyncio.sleep(0.05)
        self.bus = open_bus("zenoh", LabClock("wall"), mode="client", listen=[], connect=[self.endpoint])
        await self.bus.start()
        return self

    async def __aexit__(self, *exc):
        await self.bus.close()

    async def ask(self, command, body=b"{}", wait=5.0):
        payload = body if isinstance(body, bytes) else json.dumps(body).encode()
        return json.loads(await self.bus.request(keys.control("t", command), payload, wait))

    async def until(self, predicate, seconds=60.0):
        """Poll the campaign's status until ``predicate(status)`` holds (the campaign may not be up yet)."""
        deadline, st = time.monotonic() + seconds, None
        while time.monotonic() < deadline:
            try:
                st = (await self.ask("status", wait=1.0))["status"]
                if predicate(st):
                    return st
            except NoReplyError:
                pass
            await asyncio.sleep(0.05)
        raise AssertionError(f"the campaign never got there: {st}")


def kinds_between(events, first, last=None):
    """Event kinds after the first ``first`` note and before the first ``last`` one after it."""
    i = next(n for n, e in enumerate(events) if e["kind"] == first)
    rest = events[i + 1:]
    j = next((n for n, e in enumerate(rest) if e["kind"] == last), len(rest)) if last else len(rest)
    return [e["kind"] for e in rest[:j]]


@pytest.mark.process
async def test_a_pause_takes_effect_at_once_and_holds_until_resume(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    db = tmp_path / "j.db"
    proc = subprocess.Popen(TWIN + ["run", str(live_lab(tmp_path, endpoint)), "--journal", str(db), "--quiet"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        async with Operator(endpoint) as op:
            await op.until(lambda st: st["experiments"]["done"] >= 1)
            t0 = time.perf_counter()
            answer = await op.ask("pause", {"who": "alice", "reason": "reagent rack"})
            took = time.perf_counter() - t0
            assert answer["ok"] and answer["done"] == "operator.pause" and answer["status"]["state"] == "paused"
            assert took < 0.1, f"the pause took {took * 1000:.0f} ms to take effect"
            refused = await op.ask("pause", {"who": "bob"})
            assert refused == {"ok": False, "error": "already paused by alice", "lab_hours": refused["lab_hours"]}
            # steps in the lab finish; nothing new starts (at 300x, 3 lab-minutes pass per 0.6 s)
            st = await op.until(lambda st: not st["in_lab"], seconds=30)
            await asyncio.sleep(0.6)
            later = (await op.ask("status"))["status"]
            assert later["state"] == "paused" and later["paused_by"] == "alice" and not later["in_lab"]
            assert later["experiments"] == st["experiments"] and later["ready"] == st["ready"]
            answer = await op.ask("resume", {"who": "bob"})
            assert answer["ok"] and answer["status"]["state"] == "running"
        assert proc.wait(timeout=60) == 0, proc.stderr.read().decode()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    events = read_events(db)
    paused = kinds_between(events, "operator.pause", "operator.resume")
    assert "attempt.dispatched" not in paused and "attempt.done" in paused
    pause = next(e for e in events if e["kind"] == "operator.pause")
    assert json.loads(pause["detail"]) == {"who": "alice", "ref": json.loads(pause["detail"])["ref"],
                                           "reason": "reagent rack"}
    assert read_run(db)["summary"]["done"] == 12


@pytest.mark.process
async def test_a_paused_campaign_stays_paused_after_sigkill_and_twin_resume(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    db = tmp_path / "j.db"
    path = live_lab(tmp_path, endpoint)
    proc = subprocess.Popen(TWIN + ["run", str(path), "--journal", str(db), "--quiet"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    resumed = None
    try:
        async with Operator(endpoint) as op:
            await op.until(lambda st: st["experiments"]["done"] >= 1)
            assert (await op.ask("pause", {"who": "alice", "now": True}))["ok"]
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        assert "summary" not in read_run(db)
        resumed = subprocess.Popen(TWIN + ["resume", str(db), "--quiet", "--json"], cwd=ROOT,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        async with Operator(endpoint) as op:  # the resumed campaign listens where the scenario says, as before
            st = await op.until(lambda st: st["state"] in ("paused", "running", "finished"))
            assert st["state"] == "paused" and st["paused_by"] == "alice"
            await asyncio.sleep(0.5)  # 2.5 lab-minutes: long enough for a step to be dispatched, were it allowed
            st = (await op.ask("status"))["status"]
            assert st["state"] == "paused" and not st["in_lab"]
            assert (await op.ask("resume", {"who": "alice"}))["ok"]
        out, errs = resumed.communicate(timeout=120)
        assert resumed.returncode == 0, errs.decode()[-2000:]
    finally:
        for p in (proc, resumed):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
    summary = json.loads(out)
    assert summary["done"] == 12 and summary["proposed"] == 12
    record = read_run(db)["provenance"]
    assert record["seed"] == 0 and len(record["resumed"]) == 1 and record["resumed"][0]["command"][1] == "resume"
    events = read_events(db)
    after = kinds_between(events, "campaign.resumed", "operator.resume")
    assert "attempt.dispatched" not in after


@pytest.mark.process
async def test_hostile_requests_are_refused_by_field_and_never_reach_the_journal(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    db = tmp_path / "j.db"
    proc = subprocess.Popen(TWIN + ["run", str(live_lab(tmp_path, endpoint, **{"campaign.budget": 4})),
                                    "--journal", str(db), "--quiet"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        async with Operator(endpoint) as op:
            await op.until(lambda st: st["state"] == "running")
            bad = {b"not json": "not JSON", b"[1, 2]": "JSON object", b'{"who": "x; rm -rf /"}': "who:",
                   b'{"who": "a", "experiment": true}': "experiment:", b'{"who": "a", "now": "yes"}': "now:",
                   b'{"who": "a", "sudo": 1}': "unknown field", b"{" + b" " * 5000 + b"}": "at most 4096",
                   b"[" * 4000: "not JSON (JSON nested too deep)",  # json.loads raises RecursionError
                   b'{"who": "a", "reason": "' + b"x" * 600 + b'"}': "reason:",
                   b'{"who": "a", "amount": 1e308}': "amount: '1e+308' is not a positive number below 1e15",
                   # past SQLite's 64 bits: the refusal's journal row failed, and every write after it
                   b'{"who": "a", "experiment": 1180591620717411303424}': "experiment:"}
            for payload, words in bad.items():
                answer = await op.ask("pause", payload)
                assert not answer["ok"] and words in answer["error"], (payload[:40], answer)
            answer = await op.ask("explode", {"who": "a"})
            assert not answer["ok"] and "unknown command 'explode'" in answer["error"]
            answer = await op.ask("abort", {"who": "a", "experiment": 999})
            assert not answer["ok"] and "there is no experiment 999" in answer["error"]
            assert (await op.ask("stop", {"who": "carol", "reason": "test over"}))["ok"]
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    events = read_events(db)
    ops = [(e["kind"], json.loads(e["detail"]).get("who")) for e in events if e["kind"].startswith("operator.")]
    assert ops == [("operator.refused", "a"), ("operator.stop", "carol")]  # the rest never got past the desk
    assert read_run(db)["summary"]["stopped"] == "stopped by carol: test over"
    # as Ctrl-C's, an operator's stop is undone by twin resume: the campaign goes on from before it
    resumed = subprocess.run(TWIN + ["resume", str(db), "--json"], cwd=ROOT, capture_output=True, text=True,
                             timeout=120)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert json.loads(resumed.stdout)["done"] == 4
    again = [json.loads(e["detail"]) for e in read_events(db) if e["kind"] == "campaign.resumed"]
    assert [r["after"] for r in again] == ["stopped by carol: test over"]


class Lab:
    """A live campaign in another process, driven by `twin ctl` in this one (in-process, through typer)."""

    def __init__(self, tmp_path, endpoint=None, **changes):
        self.endpoint = endpoint or f"tcp/127.0.0.1:{free_port()}"
        self.db = tmp_path / "j.db"
        path = live_lab(tmp_path, self.endpoint, **changes)
        self.proc = subprocess.Popen(TWIN + ["run", str(path), "--journal", str(self.db), "--quiet", "--json"],
                                     cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def until(self, predicate):
        async def wait():
            async with Operator(self.endpoint) as op:
                await op.until(predicate)

        asyncio.run(wait())

    def ctl(self, *args):
        command, rest = args[0], list(args[1:])
        return twin_cli("ctl", command, "--lab", "t", "--connect", self.endpoint, *rest)

    def finished(self) -> dict:
        out, errs = self.proc.communicate(timeout=60)
        self.log = errs.decode()
        assert self.proc.returncode == 0, self.log[-2000:]
        return json.loads(out)


@pytest.mark.process
def test_the_ctl_commands_say_what_they_did_and_a_refusal_exits_1(tmp_path):
    with Lab(tmp_path) as lab:
        lab.until(lambda st: st["state"] == "running")
        res = lab.ctl("pause", "--as", "alice", "--reason", "refill")
        assert res.exit_code == 0 and "operator.pause by alice at lab" in res.output and "paused" in res.output
        res = lab.ctl("status")
        assert res.exit_code == 0, res.output
        assert "test_lab (campaign c1, lab t): paused by alice" in res.output and "spectrometer-1" in res.output
        res = lab.ctl("abort", "999")
        assert res.exit_code == 1 and "refused: there is no experiment 999" in res.output
        # --campaign on a lab of one campaign: its own name is taken, another is refused naming it
        res = lab.ctl("resume", "--campaign", "other")
        said = " ".join(res.output.split())
        assert res.exit_code == 1 and "this lab runs one campaign, 'test_lab', not 'other': leave --campaign out" \
            in said, said
        assert lab.ctl("status", "--campaign", "test_lab").exit_code == 0
        # a lab name mistyped: the one that is there is named
        wrong = twin_cli("ctl", "status", "--lab", "tt", "--connect", lab.endpoint)
        assert wrong.exit_code == 2 and "no campaign of lab 'tt' answered" in wrong.output
        assert "(labs on it now: t)" in wrong.output, wrong.output
        assert json.loads(lab.ctl("status", "--json").output)["status"]["paused_by"] == "alice"
        waiting = subprocess.Popen(TWIN + ["ctl", "wait", "--lab", "t", "--connect", lab.endpoint], cwd=ROOT,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert "campaign test_lab: " in waiting.stderr.readline()  # it asked, and said how the campaign goes
            res = lab.ctl("stop", "--as", "alice")
            assert res.exit_code == 0 and "operator.stop by alice" in res.output, res.output
            out, _ = waiting.communicate(timeout=60)
        finally:
            waiting.kill()
        assert lab.finished()["stopped"] == "stopped by alice"
        # a campaign run on its own ends with its process
        assert waiting.returncode == 0 and "campaign test_lab of lab t has ended: its lab no longer answers" in \
            " ".join(out.split()), out


@pytest.mark.process
def test_an_operator_lists_the_pending_question_and_answers_it(tmp_path):
    with Lab(tmp_path, **{"campaign.budget": 2, "devices.synthesiser.faults": {"fail_p": 1.0},
                          "orchestrator.retry.max_attempts": 1,
                          "orchestrator.recovery": [{"device": "synthesiser", "options": ["retry", "abandon"],
                                                     "default": "abandon", "timeout_s": 100000}]}) as lab:
        lab.until(lambda st: st["questions"])
        res = lab.ctl("pending")
        assert res.exit_code == 0 and "q1: experiment" in res.output and "options: retry, abandon" in res.output
        assert "twin ctl answer q1 OPTION" in res.output
        res = lab.ctl("answer", "q1", "skip")
        assert res.exit_code == 1 and "'skip' is not an option of q1: choose one of retry, abandon" in res.output
        res = lab.ctl("answer", "q1", "abandon", "--as", "alice")
        assert res.exit_code == 0 and "operator.answer by alice" in res.output, res.output
        assert lab.ctl("stop", "--as", "alice").exit_code == 0
        lab.finished()
    said = " ".join(lab.log.split())  # and the person running the lab was told, with the command that answers
    assert "question.asked q1: synthesise of experiment 0 failed on synthesiser" in said, lab.log
    assert (f"what now? Options retry, abandon. Answer: twin ctl answer q1 OPTION --lab t --connect "
            f"{lab.endpoint}; unanswered within 100,000 lab-s (333 s of wall time) abandon applies") in said, lab.log
    events = read_events(lab.db)
    answered = [json.loads(e["detail"]) for e in events if e["kind"] == "question.answered"]
    assert answered[0] == {"id": "q1", "option": "abandon", "who": "alice"}
    gone = next(e for e in events if e["kind"] == "experiment.abandoned")
    assert json.loads(gone["detail"])["reason"].endswith("alice chose to abandon it")


@pytest.mark.process
@pytest.mark.parametrize("held_by", [None, "spectrometer"])
def test_a_short_consumable_waits_for_the_operators_refill(tmp_path, held_by):
    """A lab's stock of vials, or each of the two spectrometers' own: the third sample waits for a refill."""
    vials = {"unit": "vials", "level": 1, "reorder_at": 0.5, "used_by": {"measure": 1},
             **({"device": held_by} if held_by else {})}
    stocks = ["vials"] if held_by is None else ["vials@spectrometer-1", "vials@spectrometer-2"]
    with Lab(tmp_path, **{"campaign.budget": 3, "consumables": {"vials": vials}}) as lab:
        lab.until(lambda st: all(st["consumables"][k]["depleted"] for k in stocks))
        res = lab.ctl("pending")
        assert res.exit_code == 0 and all(f"{k} is short (0 vials left)" in res.output for k in stocks), res.output
        assert all(f"twin ctl refill {k}" in res.output for k in stocks)
        res = lab.ctl("status")  # the levels, and what waits for which
        rows = [line.split() for line in res.output.splitlines() if line.split()[:1] and line.split()[0] in stocks]
        assert sorted(r[0] for r in rows) == stocks and all(r[1:4] == ["0", "vials", "0.5"] for r in rows), res.output
        assert all("short" in r for r in rows) and sum(any(x.startswith("e") for x in r[5:]) for r in rows) >= 1
        res = lab.ctl("refill", "vials", "--amount", "5", "--as", "alice")
        assert res.exit_code == 0 and "operator.refill by alice" in res.output, res.output
        summary = lab.finished()
    assert summary["done"] == 3 and set(summary["consumables"]) == set(stocks)
    assert sum(c["left"] for c in summary["consumables"].values()) == len(stocks) * 6 - 3
    assert sum(c["used"] for c in summary["consumables"].values()) == 3
    assert not any(c["short"] for c in summary["consumables"].values())
    kinds = [e["kind"] for e in read_events(lab.db)]
    assert kinds.count("consumable.depleted") == len(stocks) and kinds.count("consumable.refilled") == len(stocks)
    said = " ".join(lab.log.split())  # and the person running the lab was told to reorder, with the command
    assert all(f"consumable.low {k}: 0 vials left, below its reorder point (0.5): reorder it; when it is refilled, "
               f"twin ctl refill {k} --lab t --connect {lab.endpoint}" in said for k in stocks), lab.log


@pytest.mark.process
def test_a_human_step_waits_for_twin_ctl_confirm(tmp_path):
    from tests.twin.test_human_steps import HUMAN

    with Lab(tmp_path, **{**HUMAN, "campaign.budget": 1}) as lab:
        lab.until(lambda st: st["human_steps"])
        res = lab.ctl("pending")
        assert res.exit_code == 0 and "e0s0: load_rack on operator — load the precursor rack into bay 2" in res.output
        res = lab.ctl("confirm", "e0s0", "--as", "alice")
        assert res.exit_code == 0 and "operator.confirm by alice" in res.output, res.output
        assert lab.finished()["done"] == 1
    confirmed = [json.loads(e["detail"]) for e in read_events(lab.db) if e["kind"] == "attempt.confirmed"]
    assert confirmed == [{"who": "alice"}]
    # and the person running the lab was told, with the command that reaches it
    said = " ".join(lab.log.split())
    assert ("operator.step e0s0: load_rack on operator waits for a person — load the precursor rack into bay 2. "
            f"Done: twin ctl confirm e0s0 --lab t --connect {lab.endpoint}; unconfirmed within ") in said, lab.log


def test_a_lab_listening_on_a_port_it_chose_names_that_port_to_its_operator(tmp_path):
    """Without --listen a lab listens on a free port (tcp/127.0.0.1:0), which Zenoh does not say: the line for its
    operator said `--connect ENDPOINT (a port the lab chose …)`, and nothing could reach it. The lab chooses the
    port itself now, and the line's command reaches it."""
    import queue
    import re
    import threading
    from tests.twin.test_human_steps import HUMAN

    with Lab(tmp_path, endpoint="tcp/127.0.0.1:0", **{**HUMAN, "campaign.budget": 1}) as lab:
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [lines.put(b.decode()) for b in lab.proc.stderr], daemon=True).start()
        deadline, said, before = time.monotonic() + 60, "", []
        while "operator.step" not in said:
            said = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            before.append(said)
        m = re.search(r"Done: twin ctl confirm e0s0 --lab t --connect (tcp/127\.0\.0\.1:(\d+));", said)
        assert m and m.group(2) != "0", said
        # and said once at the start, for a person to look at the lab
        assert [line for line in before if "is on the bus" in line] == [
            f"INFO twin.where: lab t is on the bus: twin ctl status --lab t --connect {m.group(1)}, twin watch "
            f"--lab t --connect {m.group(1)}\n"], before
        res = twin_cli("ctl", "confirm", "e0s0", "--lab", "t", "--connect", m.group(1), "--as", "alice")
        assert res.exit_code == 0 and "operator.confirm by alice" in res.output, res.output
        assert lab.proc.wait(timeout=60) == 0
        assert json.loads(lab.proc.stdout.read())["done"] == 1


def test_the_answers_being_written_get_their_wall_seconds_before_a_fast_campaign_closes_its_bus():
    """drain waited 2 lab-seconds for the operator's answers to go out: 2 µs at 10⁶×, so a `stop`'s own answer was
    cut off by the campaign's end."""
    from twin.core.clock import sleep_wall
    from twin.runtime.control import ControlDesk

    clock = LabClock("scaled", speed=1e6)
    desk = ControlDesk(None, clock, lambda event: None, lambda: None)

    async def answering(command, payload):
        await sleep_wall(0.05)  # the answer takes a moment of wall time to be written
        return {"ok": True}

    desk._answer = answering

    async def stop_then_drain():
        answer = asyncio.ensure_future(desk.serve("labtwin/t/control/stop", b"{}"))
        await asyncio.sleep(0)  # the answer is being written
        await desk.drain()
        return answer.done()

    assert clock.run(stop_then_drain())


@pytest.mark.parametrize("answer", [b"<html>a web server</html>", b"[" * 5000, b'{"status": "fine"}', b"[1, 2]"])
def test_twin_ctl_answered_by_what_is_no_campaign_says_so_not_a_traceback(answer):
    """Any program on an open bus can serve a lab's control key: `twin ctl` read its answer as JSON unchecked."""
    from tests.twin.zenoh_clients import open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(listen=endpoint)
    try:
        def impostor(query):
            with query:
                query.reply(query.key_expr, answer)
        queryable = session.declare_queryable("labtwin/imp/control/**", impostor)
        res = twin_cli("ctl", "status", "--lab", "imp", "--connect", endpoint)
        queryable.undeclare()
    finally:
        session.close()
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "what answered for lab 'imp'" in said and "is not a campaign's answer" in said, said
    assert "Traceback" not in said
