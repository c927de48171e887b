"""The summary table, as ``twin run`` and ``twin report`` print it."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from twin.campaign.summary import LabSummary, Summary, busy_rows, cost_text, losses_text, quarantines_text
from twin.core.counts import counted, quantity
from twin.core.printable import printable, shell_word


def lab_span(seconds: float, digits: int = 2, prefix: str = "") -> str:
    """A lab's time as a person reads it: seconds for a lab of under an hour (a job shop), else hours
    (``prefix="lab-"``: ``732 lab-s``, ``6.00 lab-h``)."""
    return f"{seconds:,.0f} {prefix}s" if seconds < 3600 else f"{seconds / 3600:.{digits}f} {prefix}h"


def degraded(s: Summary) -> str:
    """How many samples degraded, and the steps they waited for past ``chemistry.stability_s`` (most first)."""
    if not s.degraded_samples or not s.degraded_before:
        return str(s.degraded_samples)
    steps = ", ".join(f"{escape(step)} {n}" for step, n in sorted(s.degraded_before.items(), key=lambda kv: -kv[1]))
    return f"{s.degraded_samples} [dim]— waited longer than chemistry.stability_s before {steps}[/]"


class _Marked(Table):
    """A table whose text cells are rich markup (their names and reasons escaped where they are made), read as
    such on any console: the command line's prints everything else as it is."""

    def add_row(self, *cells: Any, **options: Any) -> None:
        super().add_row(*(Text.from_markup(printable(c)) if isinstance(c, str) else c for c in cells), **options)


def render_summary(s: Summary, console: Console, resume_with: Any = None) -> None:
    """``resume_with``: what ``twin resume`` takes to continue it, if not its journal (a lab's directory)."""
    t = _Marked(title=f"{s.scenario} — seed {s.seed}", show_header=False, title_justify="left")
    t.add_column(style="bold")
    t.add_column()
    t.add_row("experiments", f"{s.done} done, {s.abandoned} abandoned, {s.pending} pending (of {s.proposed} proposed)")
    not_now = f", {s.refused_now} answered 'not now' (sent again later, no attempt used)" if s.refused_now else ""
    t.add_row("attempts", f"{s.attempts} ({s.failed_attempts} failed, {s.retried} retried, {s.timed_out} timed out"
                          f"{not_now})")
    for reason, n in sorted(s.abandoned_reasons.items()):
        example = s.abandoned_examples.get(reason, "")
        t.add_row("  abandoned", f"{n} × {escape(reason)}" + (f" [dim]— e.g. {escape(example)}[/]"
                                                                 if example and example != reason else ""))
    timed_out = sorted(r.split(":")[0] for r in s.abandoned_reasons if r.endswith(": timed_out"))
    if timed_out:
        t.add_row("  why?", f"timed_out: the last attempt at {', '.join(timed_out)} ran past its deadline. If the "
                            "step is slower than the scenario says, raise its device type's duration (or plus_param "
                            "for a time parameter): a deadline is the expected duration × "
                            "orchestrator.timeout_factor + orchestrator.timeout_slack_s")
    t.add_row("faults", f"{losses_text(s.devices_lost, s.steps_lost)}, {quarantines_text(s.quarantines, s.stuck)}, "
                        f"{counted(s.invalid_messages, 'invalid message', 'invalid messages')}, "
                        f"{counted(s.late_results, 'late result', 'late results')}")
    if s.rejected_messages or s.presence_flaps:
        flaps = counted(s.presence_flaps, "presence flap", "presence flaps")
        t.add_row("refused", f"{counted(s.rejected_messages, 'message', 'messages')} without the attempt's "
                             f"provenance (message.rejected), {flaps}")
    t.add_row("samples degraded", degraded(s))
    if s.decisions:
        ms = s.decision_ms
        fallback = f"; {s.scheduler_fallbacks} made by the fallback rule" if s.scheduler_fallbacks else ""
        t.add_row("scheduling", f"{counted(s.decisions, 'decision', 'decisions')}, {ms.get('p50', 0):.2f} / "
                                f"{ms.get('p99', 0):.2f} ms (p50 / p99 wall){fallback}")
    if s.cost:
        t.add_row("cost", cost_text(s.cost, s.hours_cost))
    hours = f"{s.lab_hours:.3f} h; " if s.lab_hours < 1 else ""
    t.add_row("lab time", f"{lab_span(s.lab_hours * 3600)} ({hours}{s.wall_s:.2f} s wall, {s.events} journal events)")
    for name, u in busy_rows(s.utilisation, s.device_types):
        t.add_row(f"  {escape(name)}", u)
    for name, c in s.consumables.items():
        short = " [red](short: work waits for a refill)[/]" if c.get("short") else ""
        out = f", out {lab_span(c['out_h'] * 3600)}" if c.get("out_h") else ""
        t.add_row(f"  {escape(name)}", f"{escape(quantity(c['left'], c['unit']))} left, {c['used']:g} used{out}{short}")
    for name, b in s.best.items():
        shown = ", ".join(f"{escape(k)}={_measured(v)}" for k, v in b["outputs"].items())
        met = s.targets_met_h.get(name)
        status = f"[green]met at {met:.2f} lab-h[/]" if met is not None else f"best score {b['score']:.3g}"
        t.add_row(f"target {escape(name)}", f"{status} — experiment {b['experiment']}: {shown}")
    if s.stopped:
        t.add_row("stopped", escape(s.stopped))
    elif s.ended:
        t.add_row("ended", escape(s.ended))
    console.print(t)
    more = f"; continue it with twin resume {shell_word(resume_with or s.journal)}" if s.resumable else ""
    console.print(f"journal: {s.journal}  (twin report {shell_word(s.journal)}{more})", soft_wrap=True, highlight=False,
                  markup=False)


def _measured(value: float) -> str:
    """An output as the summary shows it: a yes/no one as true or false (not 1 or 0)."""
    return str(value).lower() if isinstance(value, bool) else f"{value:.4g}"


def render_lab_summary(s: LabSummary, console: Console) -> None:
    """A lab that served several campaigns: one row per campaign (times are lab hours from the lab's start),
    then the lab's devices."""
    campaigns = counted(len(s.campaigns), "campaign", "campaigns")
    t = _Marked(title=f"{s.lab} — seed {s.seed}: {campaigns} sharing the lab", title_justify="left",
                caption="times in lab hours from the lab's start; targets: when met", caption_justify="left")
    for header in ("campaign", "prio", "from", "to", "done", "aband.", "pend.", "targets met"):
        t.add_column(header, overflow="fold", justify="right" if header not in ("campaign", "targets met") else "left")
    for name, c in s.campaigns.items():
        start = s.submitted_h.get(name, 0.0)
        met = ", ".join(f"{escape(k)} {start + h:.2f}"
                        for k, h in sorted(c.targets_met_h.items(), key=lambda kv: kv[1]))
        owner = f" ({escape(s.owner[name])})" if s.owner.get(name) else ""
        t.add_row(f"{escape(name)}{owner}", str(s.priority.get(name, 0)), f"{start:.2f}",
                  f"{s.ended_h.get(name, 0.0):.2f}", str(c.done), str(c.abandoned), str(c.pending), met or "—")
    for name, why in s.not_started.items():
        t.add_row(escape(name), str(s.priority.get(name, 0)), "—", "—", "", "", "", f"not started: {escape(why)}")
    console.print(t)
    busy = ", ".join(f"{d} {100 * u:.0f} %" for d, u in s.utilisation.items())
    console.print(f"lab time {s.lab_hours:.2f} h ({s.wall_s:.2f} s wall); devices busy: {busy}", highlight=False,
                  soft_wrap=True, markup=False)
    resumable = any(c.resumable for c in s.campaigns.values())
    more = f"; continue it with twin resume {shell_word(s.journals)}" if resumable else ""
    console.print(f"journals: {s.journals}/<campaign>.db  (twin report {shell_word(s.journals)}{more})",
                  highlight=False, soft_wrap=True, markup=False)
