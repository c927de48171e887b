"""Run a lab that serves several campaigns (a scenario with ``campaigns:``) and summarise each and all."""

from __future__ import annotations

import time
from typing import Any
from pathlib import Path

from twin.campaign.summary import LabSummary
from twin.core.errors import ClockError, DriverError
from twin.runtime.fast_lab import FastLab
from twin.runtime.lab import (_stop_on_signals, finish, load_drivers, make_planner, make_scheduler, open_journal,
                              refuse_realtime)
from twin.scenario import Scenario
from twin.scenario.sharing import campaign_scenarios


def default_journals(s: Scenario) -> Path:
    return Path("runs") / f"{s.name}-seed{s.campaign.seed}-{time.strftime('%Y%m%d-%H%M%S')}"


def run_shared(s: Scenario, journals: str | Path | None = None, handle_signals: bool = True) -> LabSummary:
    """Every campaign of ``s`` on its shared lab, in virtual time; each writes ``<journals>/<campaign>.db``."""
    if s.clock.mode != "virtual":
        raise ClockError(f"{s.name}: a lab of several campaigns runs in virtual time (clock.mode: virtual, "
                         f"or --clock virtual); on a {s.clock.mode} clock, serve the lab with `twin lab serve`")
    wall0 = time.perf_counter()
    scenarios = campaign_scenarios(s, s.name)
    drivers = {name: _drivers(name, cs) for name, cs in scenarios.items()}
    where = Path(journals) if journals is not None else default_journals(s)
    where.mkdir(parents=True, exist_ok=True)
    parts = {name: (open_journal(cs, where / f"{name}.db"), make_planner(cs), make_scheduler(cs))
             for name, cs in scenarios.items()}
    lab = FastLab(s, scenarios, drivers, parts)
    with _stop_on_signals(lab.stop, handle_signals):
        try:
            lab.run()
        finally:
            summaries = {}
            for name, (journal, _, _) in parts.items():
                if name in lab.shared.started:
                    summaries[name] = finish(lab.shared.cores[name], journal, wall0, lab.now)
                else:
                    why = lab.shared.unsubmitted.get(name, "the lab ended first")
                    journal.event(lab.now, "campaign.not_started", detail=why)
                    journal.close()
    return _summary(s, lab, summaries, where, time.perf_counter() - wall0)


def _drivers(name: str, s: Scenario) -> list[tuple[str, str, Any]]:
    """Campaign ``name``'s drivers: those of its workflow's device types must simulate its chemistry; another
    type's driver that cannot is left out (the campaign sends it nothing)."""
    used = {w.device for w in s.workflow}
    out = []
    for dtype in s.devices:
        try:
            out += load_drivers(s, only=set(s.instance_names(dtype)))
        except DriverError as exc:
            if dtype in used:
                raise DriverError(f"campaigns.{name}: {exc}") from None
    refuse_realtime(out)
    return out


def _summary(s: Scenario, lab: FastLab, summaries: dict, where: Path, wall_s: float) -> LabSummary:
    shared = lab.shared
    ended = {n: shared.cores[n].now / 3600 for n in shared.started}
    hours = max(ended.values(), default=0.0)
    busy: dict[str, float] = {}
    for name in shared.started:
        for dev in shared.cores[name].devices.values():
            busy[dev.name] = busy.get(dev.name, 0.0) + dev.busy_s
    return LabSummary(
        lab=s.name, seed=s.campaign.seed, journals=str(where), lab_hours=hours, campaigns=summaries,
        submitted_h={n: t / 3600 for n, t in shared.submitted_at.items() if n in shared.started},
        ended_h=ended, priority={c.name: c.priority for c in s.campaigns},
        owner={c.name: c.owner for c in s.campaigns}, not_started=dict(shared.unsubmitted),
        utilisation={d: round(b / max(hours * 3600, 1e-9), 4) for d, b in busy.items()}, wall_s=wall_s)
