"""``twin run``, ``resume``, ``watch``, ``replay``, ``validate``, ``schema``, ``devices``."""

from __future__ import annotations

import contextlib
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer
from rich.markup import escape
from rich.text import Text

from twin.cli.common import (_fail, app, assignments, check_lab_name, console, err, machine_output, narrow_table,
                             recording_file, refuse_disagreeing, say_if_still_written, speed_heeded, writable)
from twin.cli.stopping import exit_status, sigterm_unwinds, stopped_by
from twin.cli.printable import log_to_stderr
from twin.core.printable import printable
from twin.core import plugins
from twin.core.whole_files import written_whole
from twin.core.warnings_said import warnings_said
from twin.core.counts import counted
from twin.core.errors import ScenarioError, TwinError

if TYPE_CHECKING:  # the commands import the runtime and the viewer when they run: twin ctl or router need neither
    from twin.view.watch import RecordOptions

# the output options `twin run` and `twin resume` share
SaveOpt = Annotated[Optional[Path], typer.Option(help="save a Rerun recording, e.g. run.rrd")]
ViewerOpt = Annotated[bool, typer.Option(help="open the Rerun viewer and stream live")]
ServeOpt = Annotated[bool, typer.Option(help="serve a web viewer on 127.0.0.1 (URL printed)")]
ServePortOpt = Annotated[int, typer.Option(min=0, max=65535, help="gRPC port for --serve (0: any free one)")]
WebPortOpt = Annotated[int, typer.Option(min=0, max=65535, help="web viewer port for --serve (0: any free one)")]
QuietOpt = Annotated[bool, typer.Option("--quiet/--no-quiet", "-q", help="no progress bar")]
JsonOpt = Annotated[bool, typer.Option("--json", help="print the summary as JSON")]


def _runtime(value: str) -> str:
    from twin.runtime import lab

    if value not in lab.RUNTIMES:
        raise typer.BadParameter(f"{value[:40]!r} is not a runtime: use one of {', '.join(lab.RUNTIMES)}")
    return value


RuntimeOpt = Annotated[str, typer.Option(callback=_runtime,
                                         help="fast | asyncio | auto (fast for a virtual clock on the memory bus)")]


@app.command()
def run(
    scenario: Annotated[Path, typer.Argument(help="a scenario file, e.g. scenarios/quantum_dots.yaml")],
    seed: Annotated[Optional[int], typer.Option(help="override campaign.seed")] = None,
    clock: Annotated[Optional[str], typer.Option(help="virtual | scaled | wall")] = None,
    speed: Annotated[Optional[float], typer.Option(help="lab seconds per wall second (a scaled clock, which "
                                                        "--speed alone asks for)")] = None,
    bus: Annotated[Optional[str], typer.Option(help="zenoh | memory")] = None,
    budget: Annotated[Optional[int], typer.Option(help="override campaign.budget")] = None,
    planner: Annotated[Optional[str], typer.Option(help="override campaign.planner (twin bench planners lists them)")] = None,
    scheduler: Annotated[Optional[str], typer.Option(help="override campaign.scheduler")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", metavar="FIELD=VALUE",
                                                      help="override any scenario field, e.g. "
                                                           "devices.spectrometer.instances=2; repeatable")] = None,
    journal: Annotated[Optional[Path], typer.Option(help="where to write the SQLite journal")] = None,
    external: Annotated[Optional[list[str]], typer.Option(metavar="DEVICE",
                                                          help="a device served by another process")] = None,
    listen: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT",
                                                        help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447")] = None,
    connect: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT",
                                                         help="the lab's router, e.g. tls/127.0.0.1:7447")] = None,
    security: Annotated[Optional[Path], typer.Option(help="the lab's security directory (twin security init): "
                                                          "join the router with the orchestrator's certificate")] = None,
    insecure: Annotated[bool, typer.Option(help="allow --listen beyond loopback without security")] = False,
    save: SaveOpt = None,
    viewer: ViewerOpt = False,
    serve: ServeOpt = False,
    serve_port: ServePortOpt = 0,
    web_port: WebPortOpt = 0,
    quiet: QuietOpt = False,
    json_out: JsonOpt = False,
    runtime: RuntimeOpt = "auto",
) -> None:
    """Run a campaign and print its summary."""
    from twin.cli.campaign_bar import run_campaign
    from twin.cli.sharing import shared_lab
    from twin.runtime import lab
    from twin.runtime.checks import checked
    from twin.runtime.trial import warn_before_live

    log_to_stderr(logging.WARNING)
    overrides: dict = assignments(set_ or [])
    if speed is not None and clock is None and "clock.mode" not in overrides:
        clock = "scaled"  # a pace asks for the clock that has one, as twin device serve takes it
    refuse_disagreeing(overrides, {
        "campaign.seed": ("--seed", seed), "clock.mode": ("--clock", clock), "clock.speed": ("--speed", speed),
        "bus.kind": ("--bus", bus), "campaign.budget": ("--budget", budget), "campaign.planner": ("--planner", planner),
        "campaign.scheduler": ("--scheduler", scheduler), "bus.listen": ("--listen", listen and list(listen)),
        "bus.connect": ("--connect", connect and list(connect))})
    overrides |= {f"campaign.{k}": v for k, v in (("budget", budget), ("planner", planner),
                                                   ("scheduler", scheduler)) if v is not None}
    if listen:
        overrides["bus.listen"] = list(listen)
    if connect:
        overrides["bus.connect"] = list(connect)
    if security:
        overrides["bus.security"] = str(security.resolve())
    if insecure:
        overrides["bus.insecure"] = True
    record = _record(save, viewer, serve, serve_port, web_port)
    recording_file("--save", save)
    try:
        s = lab.prepare(scenario, seed=seed, clock=clock, speed=speed, bus=bus, overrides=overrides)
        speed_heeded(speed, s.clock.mode)
        if (listen or connect) and s.bus.kind == "memory":
            given = " ".join(f"--{name} {' '.join(ends)}" for name, ends in (("listen", listen), ("connect", connect))
                             if ends)
            raise TwinError(f"{given}: the bus is memory (no sockets), so nothing would listen or connect and `twin "
                            "ctl`, `twin watch` and devices elsewhere could not reach the lab; add --bus zenoh")
    except TwinError as exc:
        _fail(exc)
    twins = [f"{d} by {spec.twin.driver}" for d, spec in s.devices.items() if spec.twin is not None]
    if twins and s.clock.mode == "virtual" and not (quiet or json_out):
        err.print(f"the clock is virtual, so twins stand in: {', '.join(twins)} (devices.*.twin; --clock scaled "
                  "runs the lab's own drivers)", highlight=False)
    if s.campaigns:
        warn_before_live(s, scenario)
        shared_lab(s, journal, record, quiet, json_out, external, runtime=runtime, path=scenario)
        return
    try:
        with sigterm_unwinds():  # the check makes the scheduler, which may plan the lab ahead for a while
            checked(s, scenario, external or ())
    except TwinError as exc:
        _fail(exc)
    except KeyboardInterrupt as stop:
        err.print(f"{stopped_by(stop)} while the lab was being checked"
                  f"{' and its scheduler planned it ahead' if s.campaign.plays_ahead else ''}: nothing ran, and no "
                  "journal was written", highlight=False)
        raise typer.Exit(exit_status(stop)) from None
    warn_before_live(s, scenario)
    run_campaign(s, record, quiet, json_out, lambda on_progress, observer: lab.run(
        s, journal=journal, external_devices=set(external or ()), on_progress=on_progress, observer=observer,
        runtime=runtime))


@app.command()
def resume(
    journal: Annotated[Path, typer.Argument(help="the journal of a killed or interrupted run, runs/<run>.db (or "
                                                 "the directory of a lab's journals, "
                                                 "runs/<lab>-seed<N>-<time>/)")],
    save: SaveOpt = None,
    viewer: ViewerOpt = False,
    serve: ServeOpt = False,
    serve_port: ServePortOpt = 0,
    web_port: WebPortOpt = 0,
    quiet: QuietOpt = False,
    json_out: JsonOpt = False,
    runtime: RuntimeOpt = "auto",
) -> None:
    """Continue a killed campaign, or one stopped by Ctrl-C, SIGTERM or twin ctl stop, from its journal (virtual
    time: re-run and checked; live: rebuilt)."""
    from twin.cli.campaign_bar import resumed_from, run_campaign
    from twin.cli.sharing import shared_lab
    from twin.runtime.resume import recorded
    from twin.runtime.resume import resume as resume_journal
    from twin.runtime.resume_lab import recorded_lab

    log_to_stderr(logging.WARNING)
    recording_file("--save", save)
    record = _record(save, viewer, serve, serve_port, web_port)
    if journal.is_dir():  # the journals of a lab several campaigns share
        try:
            s = recorded_lab(journal)[0]
        except TwinError as exc:
            _fail(exc)
        shared_lab(s, None, record, quiet, json_out, None,
                   resuming=journal, runtime=runtime)
        return
    try:
        s, prefix = recorded(journal)
    except TwinError as exc:
        _fail(exc)
    if not (quiet or json_out):
        how = ("its core is rebuilt from the inputs it journalled, and the devices are asked about the steps it "
               "had in the lab" if s.clock.mode != "virtual" else
               f"{len(prefix)} recorded events are checked as the campaign re-runs")
        err.print(f"resuming {journal}: {how}", highlight=False)
    run_campaign(s, record, quiet, json_out,
              lambda on_progress, observer: resume_journal(journal, on_progress=on_progress, observer=observer,
                                                       runtime=runtime), resumed_from(journal, s))


def _record(save: Path | None, viewer: bool, serve: bool, serve_port: int, web_port: int) -> RecordOptions:
    """What to record; a port of --serve's server given without --serve would be ignored, so it is refused."""
    from twin.view.watch import RecordOptions

    ports = [f"--{name} {port}" for name, port in (("serve-port", serve_port), ("web-port", web_port)) if port]
    if ports and not serve:
        _fail(TwinError(f"{' and '.join(ports)}: the port{'s' if len(ports) > 1 else ''} of --serve's server, and "
                        "nothing is served: add --serve"))
    return RecordOptions(save, viewer, serve, serve_port, web_port)


@app.command()
def watch(
    lab_name: Annotated[str, typer.Option("--lab", callback=check_lab_name,
                                          help="the lab to watch (the scenario's `lab` field)")],
    connect: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT",
                                                         help="Zenoh endpoint of the lab, e.g. tcp/127.0.0.1:7447")] = None,
    listen: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT",
                                                        help="listen instead, for a lab that connects to us")] = None,
    save: Annotated[Optional[Path], typer.Option(help="save the recording, e.g. watch.rrd")] = None,
    viewer: Annotated[bool, typer.Option(help="open the Rerun viewer")] = False,
    serve: Annotated[bool, typer.Option(help="serve a web viewer on 127.0.0.1")] = False,
    follow: Annotated[bool, typer.Option(help="keep watching after the campaign ends, or when its lab dies "
                                              "(for twin resume)")] = False,
    security: Annotated[Optional[Path], typer.Option(help="the lab's security directory: watch through its "
                                                          "router with the watcher's certificate")] = None,
    wait: Annotated[float, typer.Option(min=0.1, max=600, metavar="SECONDS",
                                        help="how long --connect may take to answer: a lab or router started "
                                             "after the watcher")] = 30.0,
    log: Annotated[bool, typer.Option("--log", help="print the decisions and faults on stdout, a line each as they "
                                                    "come (the viewer's log without each dispatch): for a terminal "
                                                    "with no display; with or without a recording")] = False,
) -> None:
    """Attach to a lab running in another process and record what it does (or print its log)."""
    from twin.view.watch import RecordOptions
    from twin.view.watch import watch as watch_lab

    recording_file("--save", save)
    if not (connect or listen):
        _fail(TwinError("give --connect ENDPOINT (where the lab listens: twin run --listen ...) or --listen ENDPOINT"))
    record = RecordOptions(save, viewer, serve, log=(lambda line: print(line, flush=True)) if log else None)
    if not record.wanted:
        _fail(TwinError("nothing to do: give --save FILE, --viewer, --serve or --log"))
    gone: list[bool] = []

    def lab_gone() -> None:
        gone.append(True)
        err.print(f"lab {lab_name!r} left the bus before its campaigns ended (its process killed, crashed or hung, "
                  "or its machine lost); " + ("still watching, for it to come back (twin resume)" if follow else
                                              "the recording ends here. Finish them with twin resume JOURNAL (a lab "
                                              "of several campaigns: their directory); twin replay JOURNAL then "
                                              "draws all of it"), highlight=False)

    def present(back: bool) -> None:  # on stderr when stdout is the log's
        print(f"lab {lab_name!r} is back on the bus: reading what it did meanwhile from its history" if back else
              f"lab {lab_name!r} is on the bus: {'watching' if log and not record.recorded else 'recording'} it",
              flush=True, file=sys.stderr if log else sys.stdout)

    def link(cut: bool) -> None:
        where = ", ".join(connect or listen or [])
        err.print(f"lost the connection to {where} (a router restarted, a network down): the lab may be running "
                  "still; waiting for the connection to come back (Ctrl-C ends the watch)" if cut else
                  f"connected to {where} again: what the lab did meanwhile is read from its history", highlight=False)
    try:
        observer = watch_lab(lab_name, record, list(connect or []), list(listen or []), follow,
                             str(security) if security else None, wait, lab_gone, link, present)
    except TwinError as exc:
        _fail(exc)
    except KeyboardInterrupt:  # once connected, Ctrl-C ends the watch and saves; this is before, while it waits
        err.print(f"interrupted while waiting for {', '.join(connect or listen or [])} to answer: nothing recorded",
                  highlight=False)
        raise typer.Exit(130) from None
    err.print(f"{'recorded' if record.recorded else 'watched'} {observer.spectra} spectra, {observer.finished} "
              "finished experiments" + (f" to {save}" if save else ""), highlight=False)
    if gone and not follow:
        raise typer.Exit(1)


@app.command()
def replay(
    journal: Annotated[Path, typer.Argument(help="a run's journal, runs/<run>.db (or a lab's directory of "
                                                 "journals: the lab's recording)")],
    save: Annotated[Optional[Path], typer.Option(help="save the rebuilt recording, e.g. replay.rrd")] = None,
    viewer: Annotated[bool, typer.Option(help="open the Rerun viewer")] = False,
    serve: Annotated[bool, typer.Option(help="serve a web viewer on 127.0.0.1")] = False,
) -> None:
    """Rebuild a run's Rerun recording from its journal alone."""
    from twin.view.watch import RecordOptions
    from twin.view.watch import replay as replay_journal

    recording_file("--save", save)
    if not (save or viewer or serve):
        _fail(TwinError("nothing to do: give --save FILE, --viewer or --serve"))
    # written whole or not at all: an interrupted replay leaves no recording that looks like the run's
    try:
        with written_whole(save) if save else contextlib.nullcontext() as partial:
            observer = replay_journal(journal, RecordOptions(partial, viewer, serve))
    except TwinError as exc:
        _fail(exc)
    except KeyboardInterrupt:
        err.print("interrupted: nothing saved" + (f" ({save} is as it was)" if save and save.exists() else ""),
                  highlight=False)
        raise typer.Exit(130) from None
    err.print(f"replayed {observer.spectra} spectra, {observer.finished} finished experiments"
              + (f" to {save}" if save else ""), highlight=False)
    say_if_still_written(journal, "the recording")


@app.command()
def validate(files: Annotated[list[Path], typer.Argument(metavar="FILE", help="scenario files")],
             set_: Annotated[Optional[list[str]], typer.Option("--set", metavar="FIELD=VALUE",
                                                               help="check the files with a field overridden, as "
                                                                    "`twin run --set` would run them; repeatable")]
             = None,
             serve: Annotated[bool, typer.Option("--serve", help="check them as `twin lab serve` reads a lab "
                                                 "file: its campaigns may come later (twin submit), so it needs no "
                                                 "workflow")] = False,
             strict: Annotated[bool, typer.Option("--strict", help="a file with warnings fails too (exit 2): for a "
                                                  "CI that keeps scenario files clean")] = False,
             json_out: Annotated[bool, typer.Option("--json", help="print each file's problems and warnings as one "
                                                    "JSON document")] = False) -> None:
    """Check scenario files; every problem names its file, field and value, and every warning its file."""
    from twin.runtime.checks import validate_file

    overrides = assignments(set_ or [])
    checked: list[dict] = []
    with warnings_said() as warned:
        for f in files:
            warned.said.clear()
            refusal = None
            try:  # what a plugin prints as it is made goes to stderr: --json's output is one JSON document
                with contextlib.redirect_stdout(sys.stderr) if json_out else contextlib.nullcontext():
                    validate_file(f, overrides, serve)
            except TwinError as exc:
                refusal = exc
            problems = [] if refusal is None else list(refusal.problems) if isinstance(refusal, ScenarioError) \
                else [str(refusal)]
            checked.append({"file": str(f), "ok": not problems and not (strict and warned.said),
                            "problems": problems, "warnings": list(warned.said)})
            if not json_out:
                _say_checked(f, refusal, checked[-1]["warnings"], strict)
    if json_out:
        console.print_json(json.dumps({"ok": all(c["ok"] for c in checked), "files": checked}))
    if not all(c["ok"] for c in checked):
        raise typer.Exit(2)


def _say_checked(f: Path, refusal: TwinError | None, warnings: list[str], strict: bool) -> None:
    if refusal is not None:
        err.print(f"[red]✗[/] {escape(str(refusal))}", highlight=False, markup=True)
    else:
        said = f" ({counted(len(warnings), 'warning', 'warnings')})" if warnings else ""
        failed = strict and warnings
        console.print(f"{'[red]✗[/]' if failed else '[green]✓[/]'} {escape(str(f))}{said}"
                      f"{': --strict fails it' if failed else ''}", highlight=False, soft_wrap=True, markup=True)
    for text in warnings:
        err.print(f"[yellow]![/] {escape(str(f))}: warning: {escape(text)}", highlight=False, soft_wrap=True,
                  markup=True)


@app.command()
def schema() -> None:
    """Print the JSON Schema of scenario files (for editors)."""
    from twin.scenario import json_schema

    print(json.dumps(json_schema(), indent=2))


@app.command()
def devices(
    connect: Annotated[Optional[list[str]], typer.Option(metavar="ENDPOINT",
                                                         help="instead, list the devices on a running lab's bus "
                                                              "(a Zenoh endpoint, e.g. tcp/127.0.0.1:7447), with "
                                                              "their health")] = None,
    lab_name: Annotated[Optional[str], typer.Option("--lab", callback=check_lab_name,
                                                    help="the lab (the scenario's `lab`), with --connect")] = None,
    security: Annotated[Optional[Path], typer.Option(help="the lab's security directory, with --connect")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="the installed drivers as JSON (with --connect: each "
                                                         "device's whole health report)")] = False,
    csv_out: Annotated[Optional[Path], typer.Option("--csv", help="write the installed drivers (with --connect: the "
                                                                   "devices) to this CSV file")] = None,
) -> None:
    """List the installed device drivers (name, where from, package and version, capabilities), or with
    --connect the devices of a running lab and their health."""
    writable("--csv", csv_out)

    if connect:
        from twin.cli.distributed import show_health
        from twin.core.bus.presence import elsewhere
        from twin.runtime.serve import roster

        if not lab_name:
            _fail(TwinError("--connect needs --lab: the lab whose devices to list (the scenario's `lab` field)"))
        try:
            answers, labs = roster(lab_name, list(connect), str(security) if security else None)
        except TwinError as exc:
            _fail(exc)
        if not answers:
            console.print(f"no device of lab {lab_name!r} is on the bus at {', '.join(connect)} ({elsewhere(labs)})",
                          highlight=False)
            raise typer.Exit(1)
        show_health(answers, as_json, csv_out)
        return

    header = ["driver", "class", "package", "version", "runs"]
    drivers = []
    for name, ep in sorted(plugins.installed("devices").items()):
        try:
            driver = ep.load()
            caps = getattr(driver, "capabilities", None)
            runs = (", ".join(sorted(caps)) if isinstance(caps, (set, frozenset))
                    # the lab gives a driver that takes `steps` its device type's (twin/runtime/assembly.py)
                    else "its device type's steps" if "steps" in getattr(driver, "option_names", ())
                    else "what its options say")
        except Exception as exc:  # a broken plugin is listed, not fatal
            runs = f"failed to load: {exc}"
        drivers.append([name, ep.value, ep.dist.name if ep.dist else "?", ep.dist.version if ep.dist else "?", runs])
    if machine_output(as_json, csv_out, header, drivers, [dict(zip(header, d)) for d in drivers]):
        return
    table = narrow_table(header)  # on a terminal cells wrap, never cut; piped, each driver is one whole line
    for row in drivers:
        table.add_row(*row[:4], Text(printable(row[4]), style="red") if row[4].startswith("failed to load") else row[4])
    if console.is_terminal:
        console.print(table)
    else:
        from rich.console import Console

        Console(width=1000, no_color=True, emoji=False, markup=False).print(table)
