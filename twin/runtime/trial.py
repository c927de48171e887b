"""A few trial experiments on the twin before a file is trusted: a workflow that every experiment fails in (a
sample of a kind the next device cannot take, a driver that raises on every step) passes each field's check, and
would otherwise be found a whole campaign later — on a live lab, after its first experiment's last step."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import logging
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from twin.core.printable import shell_word
from twin.core import plugins
from twin.core.clock import wall_on_loop
from twin.core.counts import counted
from twin.core.held import log as held_log
from twin.scenario import Scenario

TRIALS = 3
SUBMITTED_WAIT_S = 60.0  # a child process importing the lab's plugins and running the trial: ~0.6 s here
HELD_LOGGER = held_log.name
log = logging.getLogger(__name__)


def warn_before_live(s: Scenario, path: str | Path) -> None:
    """A live lab's file is tried on the twin before the lab starts: a workflow no experiment gets through would
    otherwise be found an experiment's length of the lab's time later (a virtual run is itself the trial)."""
    if s.clock.mode != "virtual":
        for warning in trial_warnings(s, path):
            logging.getLogger("twin.run").warning(warning)


def trial_warnings(s: Scenario, path: str | Path) -> list[str]:
    """What a few trial experiments of each campaign of ``s`` (read from ``path``) warn of: none where one got
    through (see ``trial_warning``)."""
    if not s.campaigns:
        return [w for w in [trial_warning(s, path)] if w]
    from twin.scenario.sharing import campaign_scenarios
    each = campaign_scenarios(s, str(path))
    return [w for i, (name, c) in enumerate(each.items()) if (w := trial_warning(c, path, f"campaigns.{i} ({name}): "))]


def trial_warning(s: Scenario, path: str | Path, where: str = "", then: str | None = None) -> str:
    """'' if a trial experiment of ``s`` got through, or none was run (a job shop, a planner that may plan routes of
    its own, a driver that needs its instrument and has no twin); else what stopped all of them, as a warning about the file
    at ``path``. ``where``: the campaign's place in a shared lab ("campaigns.0 (dots): "); ``then``: what to do
    (by default, run the file on a virtual clock to see where)."""
    if s.jobshop is not None or not _runs_the_workflow(s.campaign.planner):
        return ""
    from twin.runtime.assembly import prepare
    from twin.runtime.lab import run

    faultless: dict[str, Any] = {f"devices.{dtype}.faults": {} for dtype in s.devices}
    try:
        trial = prepare(s, overrides={
            "campaign.budget": TRIALS, "campaign.max_in_flight": TRIALS, "campaign.stop_on_target": False,
            "campaign.planner": "random", "campaign.scheduler": "fifo", "clock.mode": "virtual", "bus.kind": "memory",
            **faultless})
        with tempfile.TemporaryDirectory(prefix="labtwin-trial-") as tmp, _quiet():
            summary = run(trial, journal=Path(tmp) / "trial.db", handle_signals=False, options_checked=True,
                          runtime="fast")
    except Exception as exc:  # the fast twin cannot run it (a real instrument, I/O in a driver): the checks and
        log.debug("no trial of %s: %s", s.name, exc)  # the run itself say what is wrong, not a trial
        return ""
    if not summary.proposed or summary.abandoned < summary.proposed:
        return ""
    example = next(iter(summary.abandoned_examples.values()), "")
    then = f"`twin run {shell_word(path)} --clock virtual` shows where" if then is None else then
    return (f"{where}workflow: {counted(summary.proposed, 'trial experiment', 'trial experiments')} on the twin "
            "(random parameters from the chemistry's ranges, faults off, virtual clock) "
            f"{'was' if summary.proposed == 1 else 'were all'} abandoned ({example}), so every experiment of the "
            f"campaign may be: {then}")


async def submitted_warning(s: Scenario, name: str, then: str) -> str:
    """``trial_warning`` of campaign ``name`` submitted to a served lab (``s``, what it runs), found in a child
    process: the trial quiets the process's logging and output, which a live lab's threads share, and the lab's loop
    goes on meanwhile. '' after ``SUBMITTED_WAIT_S``, or from a child that failed (said on the log)."""
    child = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "twin.runtime.trial_child", then, stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
    try:  # wall time: an OS process's, not the lab's
        out, _ = await asyncio.wait_for(child.communicate(s.model_dump_json().encode()),
                                        wall_on_loop(SUBMITTED_WAIT_S))
    except asyncio.TimeoutError:
        log.warning("campaign %s was not tried on the twin: its trial took more than %g s", name, SUBMITTED_WAIT_S)
        return ""
    finally:
        if child.returncode is None:  # timed out, or the lab stopped meanwhile
            with contextlib.suppress(ProcessLookupError):
                child.kill()
    try:
        said = json.loads(out)
    except ValueError:
        said = None
    if child.returncode != 0 or not isinstance(said, str):
        log.warning("campaign %s was not tried on the twin: its trial failed (exit %s)", name, child.returncode)
        return ""
    return said


def _runs_the_workflow(planner: str) -> bool:
    """Whether every experiment of ``planner`` runs the workflow as written (``plans_routes = False``, as the shipped
    random, lhs, gp-bo and rl say): random parameters then stand in for its own."""
    try:
        return getattr(plugins.load("planners", plugins.with_policy("planners", planner)[0]), "plans_routes",
                       None) is False
    except Exception:  # the checks name a planner that does not load
        return False


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """What the trial's run logs (a device refused, an experiment abandoned) is the trial's to sum up; only a driver
    or plugin that holds the lab (held.py: a call that does not return) is said as it happens. What a plugin
    prints is dropped: `twin validate --json`'s output is one JSON document."""
    def passes(record: logging.LogRecord) -> bool:
        return record.name == HELD_LOGGER

    handlers = logging.getLogger().handlers
    for handler in handlers:
        handler.addFilter(passes)
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            yield
    finally:
        for handler in handlers:
            handler.removeFilter(passes)
