"""A campaign run under a progress bar (and a recording, if asked), then its summary: what `twin run` and `twin
resume` share."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from rich.markup import escape

from twin.core.printable import shell_word
from twin.cli.common import _fail, bar_progress, console, err, keep_serving
from twin.cli.stopping import exit_if_interrupted
from twin.core.errors import TwinError
from twin.runtime import lab
from twin.runtime.live import lab_elapsed
from twin.view.report import lab_span, render_summary
from twin.view.watch import RecordOptions, open_observer


def waiting_for(device_types: list[str], paused_by: str = "", stocks: Sequence[str] = ()) -> str:
    """The progress line's word on an operator's pause, on device types that work waits for with no usable
    instance, and on stocks that steps wait to be refilled."""
    words = [f"[yellow]paused by {escape(paused_by)} (twin ctl resume)[/]"] if paused_by else []
    if device_types:
        words.append(f"[red]waiting: no usable {', '.join(device_types)}[/]")
    if stocks:
        words.append(f"[red]waiting for a refill of {escape(', '.join(stocks))} (twin ctl refill)[/]")
    return "  ".join(words)


def resumed_from(journal: Path, s) -> tuple[int, float]:
    """Where a resumed campaign's progress starts: experiments finished and lab seconds run. A live campaign goes
    on from where its journal got to; a virtual-time one re-runs from its start."""
    if s.clock.mode == "virtual":
        return 0, 0.0
    from twin.runtime.resume import interrupted

    got = interrupted(journal)
    return sum(n for status, n in got["experiments"].items() if status in ("done", "abandoned")), \
        got["lab_hours"] * 3600


def run_campaign(s, record: RecordOptions, quiet: bool, json_out: bool, call,
                 start: tuple[int, float] = (0, 0.0)) -> None:
    """Run ``call(on_progress, observer)`` under a progress bar and a recording, and print its summary. ``start``:
    experiments finished and lab seconds run already (a live campaign resumed)."""
    recording = None
    try:
        observer = None
        if record.wanted:
            observer, recording = open_observer(record, lab.recording_id(s))
            for message in recording.messages:
                err.print(message, highlight=False)
        progress = bar_progress(fields=("lab {task.fields[lab]}", "{task.fields[status]}"), disable=quiet or json_out,
                                remaining=False)  # a campaign may end at its targets, long before its budget
        with progress:
            bar = progress.add_task(f"{s.name} ({s.clock.mode} clock, {s.bus.kind} bus)",
                                    total=s.campaign.budget, completed=start[0], lab=lab_span(start[1], 1), status="")

            def on_progress(core) -> None:
                progress.update(bar, completed=core.finished_count, lab=lab_span(lab_elapsed(core), 1),
                                status=waiting_for(core.unavailable, core.paused_by, core.short_of))

            summary = call(on_progress, observer)
    except TwinError as exc:
        if recording is not None:
            recording.stop_serving()
        _fail(exc)
    if json_out:
        print(json.dumps(summary.to_dict(), indent=2))
    else:
        render_summary(summary, console)
    if recording is not None:
        try:
            recording.close()
        except TwinError as exc:
            recording.stop_serving()
            _fail(TwinError(f"{exc} (twin replay {shell_word(summary.journal)} --save FILE)"))
        if record.save:
            err.print(f"recording saved: {record.save}  (open it with: rerun {shell_word(record.save)})",
                      highlight=False)
        keep_serving(recording, summary.stopped)
    exit_if_interrupted(summary.stopped)
