"""A lab that several campaigns share: ``twin run`` of a lab file with ``campaigns:``, ``twin lab serve`` and
``twin submit``."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer
from rich.markup import escape

from twin.core.printable import shell_word
from twin.cli.common import _fail, app, check_lab_name, console, err, keep_serving, lab_app, speed_heeded
from twin.cli.stopping import exit_if_interrupted
from twin.cli.printable import log_to_stderr
from twin.core.counts import counted
from twin.core.errors import TwinError

if TYPE_CHECKING:  # the commands import the runtime and the viewer when they run: twin submit needs neither
    from twin.scenario import Scenario
    from twin.view.watch import RecordOptions


def shared_lab(s: Scenario, journal: Path | None, record: RecordOptions, quiet: bool, json_out: bool,
               external: list[str] | None, resuming: Path | None = None, runtime: str = "auto",
               path: str | Path = "") -> None:
    """``twin run LAB.yaml`` (read from ``path``; or, with ``resuming``, ``twin resume`` of its journals'
    directory)."""
    from twin.runtime.checks import checked
    from twin.runtime.lab import recording_id
    from twin.runtime.resume_lab import resume_lab
    from twin.runtime.shared_run import run_shared
    from twin.view.watch import open_lab_observer

    log_to_stderr(logging.WARNING)
    recording = None

    def reopen():
        """A recording of the lab from its start (again, when the lab runs again on another runtime)."""
        nonlocal recording
        if recording is not None:
            recording.close()
            recording.stop_serving()
        devices = {name: dtype for dtype in s.devices for name in s.instance_names(dtype)}
        observer, recording = open_lab_observer(record, recording_id(s), [c.name for c in s.campaigns], devices)
        for message in recording.messages:
            err.print(message, highlight=False)
        return observer

    try:
        if s.campaigns or resuming is None:  # a served lab resumed may have had none yet
            checked(s, resuming or path or s.name, external or ())
        observer = reopen() if record.wanted else None
        if not quiet and not json_out:
            how = (f"{s.name}: {len(s.campaigns)} campaigns sharing the lab" if resuming is None else
                   f"resuming {resuming}: the lab re-runs and each campaign's recorded events are checked"
                   if s.clock.mode == "virtual" else f"resuming {resuming}: the lab is rebuilt from the inputs it "
                   "journalled, and the devices are asked about the steps it had in the lab")
            names = ", ".join(c.name for c in s.campaigns) or "no campaign of its file"
            err.print(f"{how} ({names}), {s.clock.mode} clock …", highlight=False)
        if resuming is not None:
            summary = resume_lab(resuming, observer=observer, on_start=_resumed, runtime=runtime, reopen=reopen)
        else:
            summary = run_shared(s, journal, external_devices=set(external or ()), observer=observer,
                                 runtime=runtime, reopen=reopen)
    except TwinError as exc:
        if recording is not None:
            recording.stop_serving()
        _fail(exc)
    _show(summary, json_out)
    if recording is not None:
        recording.close()
        if record.save:
            err.print(f"recording saved: {record.save}  (open it with: rerun {shell_word(record.save)})",
                      highlight=False)
        keep_serving(recording, " ".join(c.stopped for c in summary.campaigns.values()))
    exit_if_interrupted(*(c.stopped for c in summary.campaigns.values()))


def _resumed(live) -> None:
    """A live lab taken over again: said once it runs (a served lab goes on serving until Ctrl-C or SIGTERM)."""
    what = "serving again; `twin submit` adds campaigns, Ctrl-C stops" if live.shared.serving else "running again"
    err.print(f"resumed lab {live.lab.lab} at {live.clock.now() / 3600:.2f} lab-h: {what}", highlight=False)


def _show(summary, json_out: bool) -> None:
    if json_out:
        print(json.dumps(summary.to_dict(), indent=2))
    else:
        from twin.view.report import render_lab_summary

        render_lab_summary(summary, console)


@lab_app.command("serve")
def lab_serve(
    lab_file: Annotated[Path, typer.Argument(help="the lab: its devices, and any campaigns to start with")],
    listen: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT", help="Zenoh endpoint to listen on, e.g. "
                                                             "tcp/127.0.0.1:7447")] = None,
    connect: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT",
                                                         help="the lab's router, e.g. tls/127.0.0.1:7447")] = None,
    security: Annotated[Optional[Path], typer.Option(
        help="the lab's security directory (twin security init): join the router with the orchestrator's "
             "certificate")] = None,
    insecure: Annotated[bool, typer.Option(help="allow --listen beyond loopback without security")] = False,
    clock: Annotated[str, typer.Option(help="scaled | wall")] = "scaled",
    speed: Annotated[Optional[float], typer.Option(help="lab seconds per wall second (scaled clock)")] = None,
    journal: Annotated[Optional[Path], typer.Option(help="the directory of the campaigns' journals")] = None,
    external: Annotated[Optional[list[str]], typer.Option(metavar="DEVICE",
                                                          help="a device served by another process")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="at the end, print the summary as JSON")] = False,
    trust_modules: Annotated[bool, typer.Option(help="let a submitted campaign name 'package.module:Class' "
                                                     "planners and schedulers, which the lab imports, and files "
                                                     "outside the folder it serves from, which it opens (default: "
                                                     "installed ones, files in that folder, and those the lab file "
                                                     "names)")] = False,
) -> None:
    """Serve a lab that several campaigns share, until Ctrl-C or SIGTERM: its devices, the campaigns of its file,
    and those submitted with `twin submit`; then print each campaign's summary."""
    from twin.runtime import lab
    from twin.runtime.checks import checked
    from twin.runtime.shared_run import serve_lab
    from twin.runtime.trial import warn_before_live

    log_to_stderr(logging.WARNING)
    overrides: dict = {}
    if listen:
        overrides["bus.listen"] = list(listen)
    if connect:
        overrides["bus.connect"] = list(connect)
    if security:
        overrides["bus.security"] = str(security.resolve())
    if insecure:
        overrides["bus.insecure"] = True
    try:
        s = lab.prepare(lab_file, clock=clock, speed=speed, bus="zenoh", overrides=overrides, lab_only=True)
        speed_heeded(speed, s.clock.mode)
        if s.campaigns:
            checked(s, lab_file, external or ())
            warn_before_live(s, lab_file)

        def started(live) -> None:
            where = [*s.bus.connect, *live.bus.listening][:1] or ["..."]
            secured = f" --security {shell_word(s.bus.security)}" if s.bus.security else ""
            err.print(f"serving lab {s.lab} ({s.clock.mode} clock"
                      f"{f', {s.clock.speed:g}x' if s.clock.mode == 'scaled' else ''}) with "
                      f"{counted(len(s.campaigns), 'campaign', 'campaigns')}; `twin submit CAMPAIGN.yaml --lab {s.lab} "
                      f"--connect {where[0]}{secured}` adds one, Ctrl-C stops", highlight=False)
        summary = serve_lab(s, journal, set(external or ()), on_start=started, trust_modules=trust_modules)
    except TwinError as exc:
        _fail(exc)
    _show(summary, json_out)


@app.command()
def submit(
    campaign_file: Annotated[Path, typer.Argument(help="a campaign: name, and any of owner, priority, share, "
                                                       "chemistry, workflow, campaign")],
    lab_name: Annotated[str, typer.Option("--lab", callback=check_lab_name, help="the lab (its file's `lab` field)")],
    connect: Annotated[list[str], typer.Option(metavar="ENDPOINT",
                                               help="a Zenoh endpoint of the lab, e.g. tcp/127.0.0.1:7447")],
    security: Annotated[Optional[Path], typer.Option(help="the lab's security directory: submit as its "
                                                          "operator")] = None,
    who: Annotated[Optional[str], typer.Option("--as", help="the name the journal records")] = None,
    wait: Annotated[bool, typer.Option(help="wait until the campaign has ended, saying how it goes, then print "
                                            "its counts (for scripts: exit 0 when it ends)")] = False,
) -> None:
    """Add a campaign to a lab served with `twin lab serve`; it starts at once, sharing the lab's devices."""
    from twin.cli.control import _who
    from twin.scenario.files import parse_yaml, read_text
    from twin.scenario.sharing import parse_campaign
    from twin.runtime.trial import SUBMITTED_WAIT_S
    from twin.tools.control import request

    try:
        text = read_text(campaign_file)  # once: `-` is standard input
        entry = parse_campaign(parse_yaml(text, str(campaign_file)), str(campaign_file))  # a bad file named here
        answer = request(lab_name, "submit", {"file": text, "who": _who(who)}, list(connect),
                         str(security) if security else None, wait_s=SUBMITTED_WAIT_S + 10)
    except TwinError as exc:
        _fail(exc)
    if not answer.get("ok"):
        err.print(f"[bold red]refused:[/] {escape(str(answer.get('error')))}", highlight=False, markup=True)
        raise typer.Exit(1)
    console.print(f"campaign {entry.name} started on lab {lab_name} at lab {answer['lab_hours']:.2f} h; its journal: "
                  f"{answer['journal']}", highlight=False, markup=False)
    for warning in answer.get("warnings") or ():
        err.print(f"[yellow]![/] campaign {escape(entry.name)}: warning: {escape(str(warning))}", highlight=False,
                  soft_wrap=True, markup=True)
    if wait:
        from twin.cli.control import until_ended

        until_ended(lab_name, list(connect), str(security) if security else None, entry.name, answer["journal"])

