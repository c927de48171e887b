"""A driver's, scheduler's or planner's call that never returns holds the whole lab: the log says so while it still
does, naming who and its line, and Ctrl-C (or SIGTERM) ends the call and stops the lab cleanly, on both runtimes."""

import json
import logging
import os
import random
import signal
import threading

import pytest

from tests.conftest import qd_lab
from twin.campaign.journal_read import read_events
from twin.core import held
from twin.campaign.decisions import Assignment, Proposal
from twin.device.driver import StepResult
from twin.runtime.lab import run
from twin.scenario import parse

RELEASE = threading.Event()


class HoldsTheLab:
    """Its first step blocks in a synchronous call (a vendor SDK reading a socket with no timeout) until the test
    releases it, or 60 s have passed."""

    capabilities = frozenset({"measure"})

    def __init__(self, setup):
        self.n = 0

    async def run(self, step, params, sample, ctx):
        self.n += 1
        if self.n == 1:
            RELEASE.wait(60)  # the line the warning names
        await ctx.clock.sleep(30)
        return StepResult({"peak_nm": 600.0}, sample)

    async def safe_state(self):
        pass


class HoldsTheLabRetrying(HoldsTheLab):
    """As HoldsTheLab, inside an SDK's retry loop that swallows every error (``except Exception``)."""

    swallowed = 0

    async def run(self, step, params, sample, ctx):
        self.n += 1
        for _ in range(2 if self.n == 1 else 0):
            try:
                RELEASE.wait(5)  # the line the warning names
            except Exception:
                HoldsTheLabRetrying.swallowed += 1
        await ctx.clock.sleep(30)
        return StepResult({"peak_nm": 600.0}, sample)


class HoldsTheLabDeciding:
    """A scheduler whose third decision blocks (a search with no time limit) until the test releases it."""

    def __init__(self):
        self.n = 0

    def decide(self, view):
        self.n += 1
        if self.n == 3:
            RELEASE.wait(60)  # the line the warning names
        free = list(view.free)
        out = []
        for r in view.ready:
            fit = next((f for f in free if f.device_type == r.device_type), None)
            if fit is not None:
                free.remove(fit)
                out.append(Assignment(r.task, fit.name))
        return out


class HoldsTheLabProposing:
    """A planner whose second proposal blocks (a fit with no time limit) until the test releases it."""

    def __init__(self, parameters, seed=0):
        self.box, self.n, self.rng = parameters, 0, random.Random(seed)

    def propose(self, n, history, pending):
        self.n += 1
        if self.n == 2:
            RELEASE.wait(60)  # the line the warning names
        return [Proposal({k: self.rng.uniform(p.low, p.high) for k, p in self.box.items()}) for _ in range(n)]


class _OnWarning(logging.Handler):
    """Does ``then`` when the warning comes: it must come while the call still blocks."""

    def __init__(self, then):
        super().__init__()
        self.said, self.then = [], then

    def emit(self, record):
        if "has held the lab" in record.getMessage():
            self.said.append(record.getMessage())
            self.then()


def _run(tmp_path, runtime, monkeypatch, then, holder="driver"):
    monkeypatch.setattr(held, "HELD_S", 0.5)
    RELEASE.clear()
    handler = _OnWarning(then)
    logging.getLogger(held.__name__).addHandler(handler)
    try:
        changes = {"driver": {"devices.spectrometer.driver": "tests.twin.test_held_lab:HoldsTheLab"},
                   "retrying driver": {"devices.spectrometer.driver": "tests.twin.test_held_lab:HoldsTheLabRetrying"},
                   "scheduler": {"campaign.scheduler": "tests.twin.test_held_lab:HoldsTheLabDeciding"},
                   "planner": {"campaign.planner": "tests.twin.test_held_lab:HoldsTheLabProposing",
                               "campaign.max_in_flight": 1}}[holder]  # a proposal asked for each experiment
        lab = qd_lab(**{"devices.spectrometer.instances": 1, "campaign.budget": 2,
                        "orchestrator.timeout_slack_s": 600, **changes})
        summary = run(parse(lab), journal=tmp_path / "j.db", runtime=runtime)
    finally:
        logging.getLogger(held.__name__).removeHandler(handler)
    assert len(handler.said) == 1, handler.said  # said once
    said = handler.said[0]
    who, line, advice = {"driver": ("spectrometer's driver", "in run", "asyncio.to_thread"),
                         "retrying driver": ("spectrometer's driver", "in run", "asyncio.to_thread"),
                         "scheduler": ("scheduler 'tests.twin.test_held_lab:HoldsTheLabDeciding'", "in decide",
                                       "twin scheduler serve"),
                         "planner": ("planner 'tests.twin.test_held_lab:HoldsTheLabProposing'", "in propose",
                                     "campaign.planner_deadline_s")}[holder]
    assert said.startswith(f"{who} has held the lab for"), said
    assert "test_held_lab.py:" in said and line in said and advice in said and "Ctrl-C" in said
    return summary


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
@pytest.mark.parametrize("holder", ["driver", "scheduler", "planner"])
def test_a_call_holding_the_lab_is_said_while_it_holds_it(tmp_path, runtime, holder, monkeypatch):
    summary = _run(tmp_path, runtime, monkeypatch, RELEASE.set, holder)
    assert RELEASE.is_set()  # the warning released the call: it came while the call blocked
    assert summary.done == summary.proposed == 2  # the lab went on once the call returned


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_ends_a_drivers_call_that_holds_the_lab_and_stops_it_cleanly(tmp_path, runtime, sig, monkeypatch):
    summary = _run(tmp_path, runtime, monkeypatch, lambda: os.kill(os.getpid(), sig))
    assert not RELEASE.is_set()
    assert summary.stopped == f"interrupted ({sig.name})"
    assert summary.done + summary.abandoned + summary.pending == summary.proposed >= 1  # kept for a resume
    failed = [json.loads(e["detail"]) for e in read_events(tmp_path / "j.db") if e["kind"] == "attempt.failed"]
    assert [f["code"] for f in failed] == ["driver_error"]
    assert f"interrupted ({sig.name}) while spectrometer's driver held the lab" in failed[0]["reason"]


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_ctrl_c_is_not_swallowed_by_a_drivers_except_exception(tmp_path, runtime, monkeypatch):
    HoldsTheLabRetrying.swallowed = 0
    summary = _run(tmp_path, runtime, monkeypatch, lambda: os.kill(os.getpid(), signal.SIGINT), "retrying driver")
    assert HoldsTheLabRetrying.swallowed == 0  # it would have waited again, and Ctrl-C would never end the call
    assert summary.stopped == "interrupted (SIGINT)" and summary.done == 0
    failed = [json.loads(e["detail"]) for e in read_events(tmp_path / "j.db") if e["kind"] == "attempt.failed"]
    assert [f["code"] for f in failed] == ["driver_error"]
    assert "interrupted (SIGINT) while spectrometer's driver held the lab" in failed[0]["reason"]


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_ctrl_c_ends_a_decision_that_holds_the_lab_and_the_fallback_rule_makes_it(tmp_path, runtime, monkeypatch):
    summary = _run(tmp_path, runtime, monkeypatch, lambda: os.kill(os.getpid(), signal.SIGINT), "scheduler")
    assert not RELEASE.is_set()
    assert summary.stopped == "interrupted (SIGINT)" and summary.scheduler_fallbacks >= 1
    assert summary.done + summary.abandoned + summary.pending == summary.proposed >= 1
    fallback = [json.loads(e["detail"]) for e in read_events(tmp_path / "j.db") if e["kind"] == "scheduler.fallback"]
    assert "interrupted (SIGINT) while scheduler" in str(fallback[0]), fallback


class HoldsTheLabStopping(HoldsTheLab):
    """Its first step never ends; told to cancel it, its safe_state blocks (an instrument's synchronous stop)."""

    async def run(self, step, params, sample, ctx):
        self.n += 1
        if self.n == 1:
            await ctx.clock.sleep(10**6)
        await ctx.clock.sleep(30)
        return StepResult({"peak_nm": 600.0}, sample)

    async def safe_state(self):
        if not RELEASE.is_set():
            RELEASE.wait(60)  # the line the warning names


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_a_safe_state_holding_the_lab_is_said_while_it_holds_it(tmp_path, runtime, monkeypatch):
    monkeypatch.setattr(held, "HELD_S", 0.5)
    RELEASE.clear()
    handler = _OnWarning(RELEASE.set)
    logging.getLogger(held.__name__).addHandler(handler)
    try:
        lab = qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_held_lab:HoldsTheLabStopping",
                        "devices.spectrometer.instances": 1, "campaign.budget": 2})
        summary = run(parse(lab), journal=tmp_path / "j.db", runtime=runtime)
    finally:
        logging.getLogger(held.__name__).removeHandler(handler)
    assert RELEASE.is_set() and len(handler.said) == 1, handler.said
    assert handler.said[0].startswith("spectrometer's driver has held the lab") and "in safe_state" in handler.said[0]
    assert summary.done == summary.proposed == 2 and summary.timed_out == 1


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_ctrl_c_ends_a_proposal_that_holds_the_lab(tmp_path, runtime, monkeypatch):
    summary = _run(tmp_path, runtime, monkeypatch, lambda: os.kill(os.getpid(), signal.SIGINT), "planner")
    assert not RELEASE.is_set()
    assert summary.stopped == "interrupted (SIGINT)"
    assert summary.proposed == 1 and summary.done + summary.abandoned + summary.pending == 1  # the second never came


class InterruptedWhileProposing(HoldsTheLabProposing):
    """A planner whose second proposal is a short computation (a GP fit) during which Ctrl-C comes."""

    def propose(self, n, history, pending):
        if self.n == 1:
            os.kill(os.getpid(), signal.SIGINT)  # the handler runs here, inside the call
        self.n += 1
        return [Proposal({k: self.rng.uniform(p.low, p.high) for k, p in self.box.items()}) for _ in range(n)]


@pytest.mark.parametrize("runtime", ["fast", "asyncio"])
def test_ctrl_c_during_a_short_call_lets_it_finish_and_stops_the_lab_after(tmp_path, runtime, caplog):
    """Ctrl-C ends only a call that has held the lab for a while (held.INTERRUPT_AFTER_S): one that landed in a GP
    fit of a few ms had the planner declared failed ("raised Interrupted ... held the lab for 0 s")."""
    lab = qd_lab(**{"devices.spectrometer.instances": 1, "campaign.budget": 4, "campaign.max_in_flight": 1,
                    "campaign.planner": "tests.twin.test_held_lab:InterruptedWhileProposing"})
    summary = run(parse(lab), journal=tmp_path / "j.db", runtime=runtime)
    assert summary.stopped == "interrupted (SIGINT)" and summary.resumable
    events = read_events(tmp_path / "j.db")
    assert not [e for e in events if e["kind"] == "planner.failed" or "Interrupted" in (e["detail"] or "")]
    assert "Interrupted" not in caplog.text  # not "planner raised Interrupted: proposes nothing more"
