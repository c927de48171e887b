"""The commands for a lab spread over processes: device and scheduler serving, the router, new drivers."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Annotated, Optional

import typer

from twin.cli.common import _fail, app, console, device_app, driver_app, err, scheduler_app, security_app, writable
from twin.cli.stopping import exit_status, sigterm_unwinds, stopped_by
from twin.cli.printable import log_to_stderr
from twin.core.printable import inert, printable, shell_word
from twin.core.errors import TwinError

SecurityOpt = Annotated[Optional[Path], typer.Option(help="the lab's security directory (twin security init): "
                                                          "join through its router with this process's certificate")]
# what a process serving one part of a lab (a device, the scheduler agent) is given
LabEndpoints = Annotated[Optional[list[str]], typer.Option("--connect", metavar="ENDPOINT",
                                                           help="a Zenoh endpoint of the lab or its router, e.g. "
                                                                "tcp/127.0.0.1:7447 (default: the scenario's "
                                                                "bus.connect)")]
ClockInsisted = Annotated[Optional[str], typer.Option(help="scaled | wall: insist on this clock (default: follow "
                                                           "the lab's, whatever it is)")]
def _pace(value: float | None) -> float | None:
    if value is not None and not 0 < value < math.inf:
        raise typer.BadParameter(f"{value:g}: give lab seconds per wall second, a number above 0")
    return value


SpeedInsisted = Annotated[Optional[float], typer.Option(callback=_pace, help="insist on this many lab seconds per "
                                                                             "wall second (default: the lab's)")]
ConnectWait = Annotated[Optional[float], typer.Option(min=0.1, max=86400, metavar="SECONDS",
                                                      help="how long --connect may take to answer: a lab or router "
                                                           "started after this process (default: the scenario's "
                                                           "bus.connect_timeout_ms, 5 s)")]


def _serving(serve, *args) -> None:
    """Run a serve function with INFO logging; its errors end the command with one clear line, and so does Ctrl-C
    or SIGTERM before it serves (while it joins the lab, or its scheduler plans the lab ahead); once it serves, they
    end it cleanly."""
    log_to_stderr(logging.INFO)
    try:
        with sigterm_unwinds():
            serve(*args)
    except TwinError as exc:
        _fail(exc)
    except KeyboardInterrupt as stop:
        err.print(f"{stopped_by(stop)} before it served (joining the lab, or its scheduler planning the lab ahead): "
                  "nothing was served", highlight=False)
        raise typer.Exit(exit_status(stop)) from None


@device_app.command("serve")
def device_serve(
    scenario: Annotated[Path, typer.Argument(help="the scenario the device belongs to")],
    name: Annotated[str, typer.Option("--id", help="the device instance, e.g. spectrometer-2")],
    connect: LabEndpoints = None,
    clock: ClockInsisted = None,
    speed: SpeedInsisted = None,
    security: SecurityOpt = None,
    wait: ConnectWait = None,
) -> None:
    """Serve one device actor of a scenario in this process until SIGINT/SIGTERM, on the lab's clock (commands
    are refused until the lab's clock is heard)."""
    from twin.runtime.serve import serve_device

    _serving(serve_device, scenario, name, connect, clock or ("scaled" if speed is not None else None), speed,
             str(security) if security else None, wait)



@security_app.command("init")
def security_init(
    directory: Annotated[Path, typer.Argument(help="where to write the lab's CA, certificates and configs")],
    lab: Annotated[str, typer.Option(help="the lab (the scenario's `lab` field)")],
    device: Annotated[Optional[list[str]], typer.Option(metavar="DEVICE",
                                                        help="a device instance, e.g. spectrometer-2 (repeat)")] = None,
    host: Annotated[Optional[list[str]], typer.Option(metavar="HOST",
                                                      help="a name or address the router is reached at (repeat; "
                                                           "default localhost and 127.0.0.1)")] = None,
    endpoint: Annotated[str, typer.Option(help="the router's endpoint, written into the configs")] = "tls/127.0.0.1:7447",
    days: Annotated[int, typer.Option(min=1, help="how long the certificates are valid")] = 365,
) -> None:
    """Create (or extend) a lab's security directory: a CA, certificates, the router's access control."""
    from twin.tools.security_init import init

    try:
        written = init(directory, lab, list(device or []), list(host or []), days, endpoint, on_wait=lambda: err.print(
            f"waiting for another `twin security init` of {directory} to finish", highlight=False, markup=False))
    except TwinError as exc:
        _fail(exc)
    except OSError as exc:
        _fail(TwinError(f"{directory}: cannot write the security directory there ({exc.strerror or exc}): give a "
                        "directory you can write"))
    secured = f"--connect {endpoint} --security {shell_word(directory)}"
    console.print(f"wrote {len(written)} files to {directory}\n"
                  f"  router:  twin router --listen {endpoint} --security {shell_word(directory)}\n"
                  f"  lab:     bus: {{kind: zenoh, connect: [{endpoint}], security: {directory}}} in the scenario\n"
                  f"  device:  twin device serve SCENARIO --id ID {secured}\n"
                  f"  watcher: twin watch --lab {lab} {secured} --save w.rrd\n"
                  f"  keep {directory / 'private'} (the CA's key) off the lab's machines", highlight=False, markup=False)


@device_app.command("health")
def device_health(
    scenario: Annotated[Path, typer.Argument(help="the scenario the devices belong to")],
    connect: LabEndpoints = None,
    ids: Annotated[Optional[list[str]], typer.Option("--id", metavar="DEVICE",
                                                     help="a device instance (repeat; default: all)")] = None,
    security: SecurityOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="each device's whole report as JSON, for a monitor")] = False,
    csv_out: Annotated[Optional[Path], typer.Option("--csv", help="write a row per device to this CSV file")] = None,
) -> None:
    """Ask devices of a running lab for their health: on the bus, running what, messages dropped, the driver's own.
    Exit 1 if one did not answer."""
    from twin.runtime.serve import health

    writable("--csv", csv_out)
    try:
        answers = health(scenario, list(ids or []), connect, str(security) if security else None)
    except TwinError as exc:
        _fail(exc)
    show_health(answers, as_json, csv_out)


def show_health(answers: list[dict], as_json: bool = False, csv_out: Path | None = None) -> None:
    """The devices' health reports as a table (or ``--json``: each whole; ``--csv``: a row each, the driver's report
    as JSON text); exit 1 if one did not answer."""
    import csv
    import json

    if csv_out is not None:
        with open(csv_out, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["device", "answered", "running", "dropped", "driver"])
            for a in answers:
                r = a["report"] if isinstance(a["report"], dict) else {}
                running = r.get("running")
                running = "#".join(map(str, running)) if isinstance(running, list) else str(running or "")
                w.writerow([inert(x) for x in (a["device"], a["report"] is not None, running, r.get("dropped", ""),
                                               json.dumps(r.get("driver"), default=str))])
        err.print(f"wrote {csv_out} ({len(answers)} devices)", highlight=False)
    if as_json:
        console.print_json(json.dumps({"devices": [{"device": a["device"], "answered": a["report"] is not None,
                                                    "report": a["report"],
                                                    **({"differs": a["differs"]} if "differs" in a else {})}
                                                   for a in answers]}, default=str))
    else:
        render_health(answers)
    if any(a["report"] is None for a in answers):
        raise typer.Exit(1)


def render_health(answers: list[dict]) -> None:
    """One row per device: whether it answered, what it runs, what it dropped, what its driver says."""
    from rich.table import Table
    from rich.text import Text

    table = Table("device", "answered", "running", "dropped", "driver", caption="driver: its own health() report")
    for a in answers:
        r = a["report"]
        if r is None:
            table.add_row(a["device"], Text("no", style="red"), "", "", "")
            continue
        running = r.get("running")
        running = "#".join(map(str, running)) if isinstance(running, list) else str(running or "idle")[:20]
        driver = r.get("driver", "")
        ok = driver.get("ok") if isinstance(driver, dict) else None
        shown = Text(printable(str(driver)[:60]), style="red" if ok is False else "")
        table.add_row(a["device"], "yes", running, str(r.get("dropped", ""))[:12], shown)
    console.print(table)
    for a in answers:
        if a.get("differs"):
            console.print(Text(printable(f"{a['device']} runs by a scenario that differs from this file: "
                                         f"{'; '.join(a['differs'])} (serve it from this file)"), style="yellow"))


@driver_app.command("new")
def driver_new(
    name: Annotated[str, typer.Argument(help="the driver's name, e.g. acme-hplc (also the package's)")],
    directory: Annotated[Path, typer.Option("--dir", help="where to create the package")] = Path("."),
) -> None:
    """Scaffold a pip-installable driver package (entry point, driver, test, demo scenario)."""
    from twin.tools.scaffold import scaffold

    try:
        root = scaffold(name, directory)
    except TwinError as exc:
        _fail(exc)
    console.print(f"created {root}\n  next: pip install -e {root}  (then `twin devices` lists {name})\n"
                  f"        python -m pytest {root / 'tests'}", highlight=False)


@app.command()
def router(
    listen: Annotated[list[str], typer.Option(metavar="ENDPOINT",
                                              help="endpoint(s) to listen on, e.g. tcp/127.0.0.1:7447")],
    lease_ms: Annotated[int, typer.Option(help="how long a silent peer is kept, ms (a frozen process is seen after it)")] = 1000,
    zenoh_config: Annotated[Optional[list[str]], typer.Option("--config", metavar="PATH=JSON5",
                                                              help="an extra Zenoh config value, "
                                                                   "e.g. transport/link/tx/lease=2000")] = None,
    security: Annotated[Optional[Path], typer.Option(help="the lab's security directory (twin security init): "
                                                          "mutual TLS and the lab's access control")] = None,
    insecure: Annotated[bool, typer.Option(help="listen beyond loopback without security (anyone who reaches "
                                                "it can read and forge every message)")] = False,
) -> None:
    """A Zenoh router for a lab spread over processes or hosts (devices and labs --connect to it)."""
    import json as _json

    from twin.core.bus.router import run_router

    extra = {}
    for item in zenoh_config or []:
        path, sep, value = item.partition("=")
        if not sep:
            _fail(TwinError(f"--config {item!r}: expected PATH=JSON5, e.g. transport/link/tx/lease=2000"))
        try:
            extra[path] = _json.loads(value)
        except (ValueError, RecursionError):  # text, then, which Zenoh's config refuses or takes
            extra[path] = value
    log_to_stderr(logging.INFO)
    try:
        run_router(listen, lease_ms, extra, ready=lambda line: print(line, flush=True),
                   security_dir=str(security) if security else None, insecure=insecure)
    except TwinError as exc:
        _fail(exc)


@scheduler_app.command("serve")
def scheduler_serve(
    scenario: Annotated[Path, typer.Argument(help="the scenario of the lab to schedule")],
    scheduler: Annotated[str, typer.Option(help="rl:POLICY.zip or a rule (fifo, spt, mwkr, least-loaded, ...)")],
    connect: LabEndpoints = None,
    clock: ClockInsisted = None,
    speed: SpeedInsisted = None,
    security: SecurityOpt = None,
    wait: ConnectWait = None,
) -> None:
    """Serve scheduling decisions to a lab whose campaign.scheduler is `remote`, until SIGINT/SIGTERM."""
    from twin.runtime.serve import serve_scheduler

    _serving(serve_scheduler, scenario, scheduler, connect, clock or ("scaled" if speed is not None else None), speed,
             str(security) if security else None, wait)
